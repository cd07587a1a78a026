"""Large long-lived tensors on transparent huge pages.

The UV maps (2048² × 56 float32 = 940 MB at the paper's settings) and the sparse Adam
moments beside them are read and written at ~350k random texels an iteration. On 4 KiB
pages nearly every such access misses the TLB; on 2 MiB pages it does not (texture lookups
and a whole training step both get markedly faster, docs/benchmarks.md). Torch's allocator
gives 4 KiB pages unless the system enables THP for everything, so these tensors are
allocated by urhead's native module instead: fresh zero pages advised with
``madvise(MADV_HUGEPAGE)`` before anything touches them, then made resident by a
first write (a table read before it is written, as an Adam moment is, would otherwise map
the shared huge zero page and, under memory pressure, fall back to 4 KiB pages on the
copy). Only advice: on other systems, or
where THP is off (``/sys/kernel/mm/transparent_hugepage/enabled`` says ``never``), they are
ordinary memory, and the tensors behave as any CPU tensor does. A table below glibc's mmap
threshold (at most 32 MiB) may reuse heap memory already on 4 KiB pages; the tables this
is for are far larger (the quick preset's maps: 58 MB).
"""

from __future__ import annotations

import math

import torch

from urhead.errors import DTypeError
from urhead.ops._bridge import native

# numpy has no bfloat16: its tables (and float16 ones) are allocated as uint16 bits and
# viewed back.
_DTYPE_NAMES = {
    torch.float32: "float32",
    torch.int32: "int32",
    torch.bfloat16: "uint16",
    torch.float16: "uint16",
}


def zeros(shape: tuple[int, ...] | torch.Size, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A contiguous tensor of zeros of ``shape`` (float32, int32, bfloat16 or float16) on
    huge pages."""
    if dtype not in _DTYPE_NAMES:
        raise DTypeError(f"huge-page tensors are float32, int32, bfloat16 or float16, got {dtype}")
    flat = torch.from_numpy(native("huge_page_zeros")(math.prod(shape), _DTYPE_NAMES[dtype]))
    return flat.view(dtype).reshape(shape)


def copy(tensor: torch.Tensor) -> torch.Tensor:
    """A contiguous copy of ``tensor`` (float32, int32, bfloat16 or float16, CPU) on huge
    pages; it never shares memory or autograd history with ``tensor``."""
    out = zeros(tensor.shape, tensor.dtype)
    out.copy_(tensor.detach())
    return out
