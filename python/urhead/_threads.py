"""How many threads a kernel call uses: ``URHEAD_NUM_THREADS`` if set, otherwise
``torch.get_num_threads()``, so urhead follows whatever the caller configured for torch."""

import os

import torch

from urhead.errors import InvalidArgumentError


def num_threads() -> int:
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
