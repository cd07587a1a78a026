"""The memory this process may use, as the machine and its cgroup report it, and how
its allocator keeps what it frees."""

from __future__ import annotations

import ctypes
import platform
from pathlib import Path

# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_KEEP_FREED = (
    (_M_MMAP_THRESHOLD, 32 << 20),  # glibc's largest: blocks up to 32 MiB from the heap
    (_M_TRIM_THRESHOLD, 2**31 - 1),  # the heap's free top is (nearly) never given back
    (_M_TOP_PAD, 256 << 20),  # and grows 256 MiB at a time
)


def keep_freed_memory() -> bool:
    """The command line's allocator policy: glibc's malloc keeps the memory an iteration
    frees for the next one, instead of unmapping blocks above its mmap threshold and
    trimming the heap, so that every iteration faults fresh zeroed pages back in (a fit
    allocates and frees tens of MB of images, lookups and their gradients an iteration).
    Measured at the paper's settings (README "Speed"): a training iteration −21 ms wall /
    −28 ms CPU (median differences of 11 paired processes). Process-wide, like
    :func:`urhead._threads.configure_threads`; the process keeps its peak heap resident.
    Returns whether it applied (glibc only; elsewhere nothing changes)."""
    if platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in _KEEP_FREED)


def available_memory_bytes(
    meminfo: Path = Path("/proc/meminfo"), cgroup: Path = Path("/sys/fs/cgroup")
) -> int | None:
    """MemAvailable, lowered to the cgroup's limit left (cgroup v2 ``memory.max`` minus
    ``memory.current``); None when neither is known."""
    found = []
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            found.append(int(limit) - int((cgroup / "memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return min(found) if found else None
