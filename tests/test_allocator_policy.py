"""The command line's allocator policy (``urhead._memory.keep_freed_memory``): freed blocks
stay in the process for the next iteration instead of going back to the kernel."""

import platform
import subprocess
import sys
import textwrap

import pytest

PROBE = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    from urhead._memory import keep_freed_memory

    page = os.sysconf("SC_PAGE_SIZE")

    def resident():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * page

    applied = keep_freed_memory() if sys.argv[1] == "policy" else False
    before = resident()
    block = np.ones(16 << 20, np.uint8)  # 16 MiB: above glibc's default mmap threshold
    held = resident()
    del block
    print(applied, held - before, resident() - before)
    """
)


def probe(mode: str) -> tuple[bool, int, int]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0] == "True", int(out[1]), int(out[2])


@pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="the policy is glibc's mallopt; the probe reads /proc",
)
def test_freed_memory_is_kept_with_the_policy_and_given_back_without():
    applied, held, after_free = probe("policy")
    assert applied
    assert held >= 15 << 20
    assert after_free >= 15 << 20  # still resident: the next iteration reuses it
    _, held, after_free = probe("default")
    assert held >= 15 << 20
    assert after_free < 4 << 20  # unmapped at once: the next one faults it back in
