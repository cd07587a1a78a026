"""Threads: how many a kernel call uses, and the policy every command applies."""

import math
import os
from pathlib import Path

import torch

from urhead.errors import InvalidArgumentError

MAX_THREADS = 1024
"""More kernel threads than this only costs memory and scheduling (a pool is made per count)."""


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
    if not 1 <= n <= MAX_THREADS:
        raise InvalidArgumentError(
            f"URHEAD_NUM_THREADS must be an integer from 1 to {MAX_THREADS}, got {raw!r}"
        )
    return n


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity mask, lowered to the cgroup v2 CPU
    quota (``cpu.max``, rounded up) when there is one."""
    count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            count = min(count, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, count or 1)


def configure_threads(kernel_threads: int | None = None) -> None:
    """The command line's policy: Rust kernels get ``kernel_threads`` (default: an explicit
    ``URHEAD_NUM_THREADS``, else the CPUs this process may use); torch gets one thread.
    torch's OpenMP workers
    spin after each op and, on a small machine, starve the Rust pool (measured: up to 2×
    slower fit iterations, 2.5–4.3× slower render/reenact/export on 2 cores); the few torch
    ops around the kernels are cheap single-threaded."""
    if kernel_threads is None:
        os.environ.setdefault("URHEAD_NUM_THREADS", str(usable_cpus()))
        num_threads()  # an explicit value out of range is an error before any work
    else:
        os.environ["URHEAD_NUM_THREADS"] = str(kernel_threads)
    torch.set_num_threads(1)
