"""The stability report's bookkeeping (tests/stability.py): a bound that does not hold, a
NaN, a failed test or a missing record must never show as a pass."""

import json

import pytest

from stability import CASES, Record, Stability, read_rust_log, render_report, summarise

T1, T2 = "tests/test_a.py::test_case14_x[float32]", "tests/test_a.py::test_case14_x[float64]"


def case_line(text: str, case: int) -> str:
    return next(line for line in text.splitlines() if line.startswith(f"| [{case}](#case-{case})"))


def test_record_asserts_and_records_even_when_the_bound_fails():
    sink = []
    rec = Stability(sink, T1)
    rec.record(14, "T error", 1e-7, 1e-6)
    with pytest.raises(AssertionError, match="case 14"):
        rec.record(14, "T error", 2e-6, 1e-6)
    with pytest.raises(AssertionError):
        rec.record(14, "T error", float("nan"), 1e-6)
    assert [r.worst for r in sink][:2] == [1e-7, 2e-6] and len(sink) == 3
    with pytest.raises(ValueError, match="case"):
        rec.record(max(CASES) + 1, "no such case", 0, 0)


def test_close_is_allclose_as_a_ratio():
    import torch

    sink = []
    rec = Stability(sink, T1)
    a = torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)
    b = torch.tensor([1.0 + 5e-6, 2.0, 0.0], dtype=torch.float64)
    rec.close(14, "g", a, b, rtol=1e-5, atol=0.0)  # |a − b| = 5e-6 of an allowed ~1e-5
    assert sink[0].worst == pytest.approx(5e-6 / (1e-5 * (1 + 5e-6)), rel=1e-3)
    with pytest.raises(AssertionError):
        rec.close(14, "g", a, b, rtol=1e-6, atol=0.0)


def test_worst_of_worsts_and_status():
    records = [
        Record(14, "T error", T1, 1e-7, 1e-6),
        Record(14, "T error", T2, 3e-7, 1e-6),
        Record(9, "culled", T1, None, None, 6),
    ]
    rows = summarise(records, {T1: "passed", T2: "passed"})
    assert rows[14][0].worst == 3e-7 and rows[14][0].passed and rows[14][0].count == 2
    text, counts = render_report(records, {T1: "passed", T2: "passed"})
    assert counts == {"pass": 2, "FAIL": 0, "MISSING": len(CASES) - 2}
    assert case_line(text, 14).endswith("| pass |") and case_line(text, 1).endswith("MISSING |")


def test_a_failed_test_fails_its_records_and_its_named_case():
    records = [Record(14, "T error", T1, 1e-7, 1e-6)]
    _, counts = render_report(records, {T1: "failed"})
    assert counts["FAIL"] == 1
    # A test named test_case9_… that failed before recording anything still fails case 9.
    text, _ = render_report([], {"tests/test_b.py::test_case9_y": "failed"})
    assert case_line(text, 9).endswith("| FAIL |")


def test_nan_worst_and_exceeded_bound_fail():
    for worst in (float("nan"), 2e-6):
        text, counts = render_report([Record(3, "sum", T1, worst, 1e-6)], {T1: "passed"})
        assert counts["FAIL"] == 1 and case_line(text, 3).endswith("| FAIL |")


def test_records_of_skipped_tests_do_not_count():
    _, counts = render_report([Record(5, "ties", T1, 0.0, 0.0)], {T1: "skipped"})
    assert counts["MISSING"] == len(CASES)


def test_rust_log_lines_are_merged(tmp_path):
    log = tmp_path / "rust.jsonl"
    lines = [
        dict(case=10, check="FD", test="splat::fd", worst=1e-9, tolerance=1e-7),
        dict(case=27, check="bits", test="raster::bits", worst=3.0, tolerance=0.0),
    ]
    log.write_text("".join(json.dumps(x) + "\n" for x in lines))
    outcomes = {}
    records = read_rust_log(log, outcomes)
    _, counts = render_report(records, outcomes)
    assert outcomes == {"rust:splat::fd": "passed", "rust:raster::bits": "failed"}
    assert counts["pass"] == 1 and counts["FAIL"] == 1
