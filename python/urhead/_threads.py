"""Threads: how many a kernel call uses, and the policy every command applies."""

import os

import torch

from urhead.errors import InvalidArgumentError


def num_threads() -> int:
    """``URHEAD_NUM_THREADS`` if set, otherwise ``torch.get_num_threads()``, so urhead
    follows whatever the caller configured for torch."""
    raw = os.environ.get("URHEAD_NUM_THREADS")
    if raw is None or raw == "":
        return max(1, torch.get_num_threads())
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise InvalidArgumentError(f"URHEAD_NUM_THREADS must be a positive integer, got {raw!r}")
    return n


def configure_threads(kernel_threads: int | None = None) -> None:
    """The command line's policy: Rust kernels get ``kernel_threads`` (default: an explicit
    ``URHEAD_NUM_THREADS``, else every core); torch gets one thread. torch's OpenMP workers
    spin after each op and, on a small machine, starve the Rust pool (measured: up to 2×
    slower fit iterations, 2.5–4.3× slower render/reenact/export on 2 cores); the few torch
    ops around the kernels are cheap single-threaded."""
    if kernel_threads is None:
        os.environ.setdefault("URHEAD_NUM_THREADS", str(os.cpu_count() or 1))
    else:
        os.environ["URHEAD_NUM_THREADS"] = str(kernel_threads)
    torch.set_num_threads(1)
