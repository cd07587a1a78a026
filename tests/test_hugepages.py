"""Large long-lived tensors (maps, Adam moments) allocated on transparent huge pages."""

import re
import sys
from pathlib import Path

import pytest
import torch

from urhead import hugepages
from urhead.errors import DTypeError
from urhead.optim import MOMENT_DTYPES, SparseAdam

THP_SETTING = Path("/sys/kernel/mm/transparent_hugepage/enabled")
# 64 MiB: above glibc's largest mmap threshold (32 MiB), so always a fresh mapping (a smaller
# block may reuse heap memory already backed by 4 KiB pages, where advice comes too late).
LARGE = (1024, 1024, 16)


def thp_mode() -> str | None:
    """The bracketed THP mode ('always', 'madvise', 'never'), None where there is none."""
    try:
        match = re.search(r"\[(\w+)\]", THP_SETTING.read_text())
    except OSError:
        return None
    return match[1] if match else None


def huge_page_kib(t: torch.Tensor) -> int:
    """AnonHugePages (KiB) of the mappings overlapping ``t``'s storage."""
    return sum(
        int(line.split()[1])
        for _, lines in _mappings_of(t)
        for line in lines
        if line.startswith("AnonHugePages:")
    )


def advised_fraction(t: torch.Tensor) -> float:
    """The fraction of ``t``'s storage in mappings that carry ``MADV_HUGEPAGE`` (the ``hg``
    flag): the part urhead controls (the aligned interior of the table; its unaligned ends
    cannot be). How much of that the kernel then backs with 2 MiB pages is best effort: on a
    loaded, fragmented machine a 64 MiB table once got 26 MiB."""
    advised = sum(
        overlap
        for overlap, lines in _mappings_of(t)
        if any(line.startswith("VmFlags:") and " hg" in line for line in lines)
    )
    return advised / (t.numel() * t.element_size())


def unbacked_while_a_probe_is_backed(t: torch.Tensor, read_first: bool = False) -> bool:
    """Whether ``t`` (advised, touched) has no 2 MiB pages while a fresh advised table
    touched the same way at this moment gets some. Under CI's parallel load on a fragmented
    machine the kernel sometimes has none to give, which is not urhead's to test.
    ``read_first``: ``t`` was read before it was written (an Adam step reads a moment before
    writing it), so its zero pages were first mapped to the shared huge zero page and the
    write copies it — a different kernel path from a first write, which may find no huge
    page under load where a first write would."""
    if huge_page_kib(t) > 0:
        return False
    probe = hugepages.zeros(LARGE)
    if read_first:
        float(probe.sum())
    probe.fill_(1.0)
    return huge_page_kib(probe) > 0


def assert_backed_within_attempts(make_tables, attempts: int = 3) -> None:
    """``make_tables()`` allocates and touches fresh tables and returns ``[(name, table,
    read_first)]``; at least one of ``attempts`` rounds has every table backed by huge
    pages or a probe beside it without any. One round is not enough: how many huge pages the
    kernel has free changes from moment to moment under CI's parallel load (seen: an Adam
    moment with 0 KiB, then a probe touched the same way with 62 MiB)."""
    for _ in range(attempts):
        unbacked = [
            name
            for name, t, read_first in make_tables()
            if unbacked_while_a_probe_is_backed(t, read_first)
        ]
        if not unbacked:
            return
    pytest.fail(f"{unbacked}: no huge pages in {attempts} rounds, while probes beside got some")


def _mappings_of(t: torch.Tensor) -> list[tuple[int, list[str]]]:
    """``(bytes of t's storage inside, smaps lines)`` of each mapping overlapping it."""
    lo = t.data_ptr()
    hi = lo + t.numel() * t.element_size()
    found: list[tuple[int, list[str]]] = []
    lines: list[str] | None = None
    for line in Path("/proc/self/smaps").read_text().splitlines():
        span = re.match(r"^([0-9a-f]+)-([0-9a-f]+) ", line)
        if span:
            start, end = int(span[1], 16), int(span[2], 16)
            lines = None
            if start < hi and end > lo:
                lines = []
                found.append((min(end, hi) - max(start, lo), lines))
        elif lines is not None:
            lines.append(line)
    return found


def test_zeros_are_zeros_of_the_asked_shape_and_dtype():
    for dtype in (torch.float32, torch.int32):
        for shape in ((0,), (3, 5, 7), (1 << 21,)):
            t = hugepages.zeros(shape, dtype)
            assert t.shape == shape and t.dtype == dtype and t.is_contiguous()
            assert not t.any()


def test_other_dtypes_are_refused_with_a_typed_error():
    with pytest.raises(DTypeError, match=r"float32, int32, bfloat16 or float16.*float64"):
        hugepages.zeros((4,), torch.float64)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_16_bit_tables_are_zero_and_write_through(dtype):
    table = hugepages.zeros((3, 5), dtype)
    assert table.dtype == dtype and table.shape == (3, 5) and not table.any()
    copied = hugepages.copy(torch.tensor([[1.5, -2.0], [3.25, 1e-3]], dtype=dtype))
    assert copied.dtype == dtype
    assert copied.float().tolist() == [[1.5, -2.0], [3.25, torch.tensor(1e-3).to(dtype).item()]]


def test_copy_is_equal_and_independent():
    source = torch.randn(64, 64, 9, requires_grad=True)
    out = hugepages.copy(source)
    assert torch.equal(out, source.detach()) and not out.requires_grad
    out += 1
    assert not torch.equal(out, source.detach())


@pytest.mark.skipif(
    sys.platform != "linux" or thp_mode() not in ("always", "madvise"),
    reason="transparent huge pages need Linux with THP in 'always' or 'madvise' mode",
)
def test_a_large_table_is_backed_by_huge_pages():
    # (Whether a plain torch tensor gets 4 KiB pages depends on what the allocator reuses:
    # memory advised earlier in the process keeps its advice, so that is not asserted.)
    def fresh_table():
        ours = hugepages.zeros(LARGE)
        ours.fill_(1.0)  # first touch: the kernel backs the advised range
        assert advised_fraction(ours) >= 0.9
        return [("a fresh table", ours, False)]

    # some of it on 2 MiB pages (all of it on an idle machine)
    assert_backed_within_attempts(fresh_table)


@pytest.mark.parametrize("moments", ["float32", "bfloat16"])
def test_sparse_adam_state_and_restored_state_are_huge_page_tables(moments):
    def stepped_and_restored():
        param = torch.randn(LARGE)
        param.grad = torch.randn(LARGE)  # every row: the step touches all of the moments
        opt = SparseAdam([param], lr=1e-2, moments=moments)
        opt.step()
        restored = SparseAdam([param], lr=1e-2, moments=moments)
        restored.load_state_dict(opt.state_dict())
        for name in ("exp_avg", "exp_avg_sq", "steps"):
            a, b = opt.state[param][name], restored.state[param][name]
            assert torch.equal(a, b) and a.data_ptr() != b.data_ptr()
        tables = []
        # The step reads each moment before writing it; load_state_dict writes its copies.
        for state, read_first in ((opt.state[param], True), (restored.state[param], False)):
            assert state["steps"].dtype == torch.int32
            for name in ("exp_avg", "exp_avg_sq"):
                assert state[name].dtype == MOMENT_DTYPES[moments]
                if sys.platform == "linux" and thp_mode() in ("always", "madvise"):
                    assert advised_fraction(state[name]) >= 0.9, name
                    tables.append((name, state[name], read_first))
        return tables

    assert_backed_within_attempts(stepped_and_restored)
