"""The stability report: the extreme-case tests record what they checked, and one pytest run
writes ``docs/stability.md`` from those records.

A test asks for the ``stability`` fixture and calls

- ``stability.record(case=14, check="T vs float64 reference", worst=err, tolerance=tol)``:
  asserts ``worst <= tolerance`` (NaN fails) and records the observed worst error;
- ``stability.checked(case=26, check="NaN in means raises NonFiniteError", count=n)``: a
  pass/fail check with no error figure (an exception raised, a set of pixels covered),
  recorded with how many inputs it covered.

Both always assert/record; the report is written only when asked for:

    pytest -n 2 --stability-report docs/stability.md

A record is "pass" only if its bound held *and* its test passed; a test named
``test_caseNN_*`` that fails marks case NN failed even if it recorded nothing. A case with no
record from a test that ran shows as MISSING. Under pytest-xdist each worker sends its records
to the controller (``workeroutput``), which merges them with the test outcomes it sees.

Rust tests can contribute too: with ``URHEAD_STABILITY_LOG=<file>`` set,
``urhead_core::testing::record_stability`` appends one JSON line per check; pass that file
with ``--stability-rust-log <file>`` (or keep the variable set for the pytest run) and its
lines are merged (test names prefixed ``rust:``).
"""

from __future__ import annotations

import datetime
import json
import math
import os
import platform
import re
import subprocess
from collections import defaultdict
from dataclasses import asdict, dataclass
from pathlib import Path

import pytest

# Short forms of NUMERICS.md's "Cases the test suite must contain".
CASES = {
    1: "Triangle straddling the near plane, w = 0 exactly, fully behind",
    2: "Degenerate triangles: repeated index, collinear, edge-on, 1e-12 px²",
    3: "Sliver 1000 px × 1e-3 px, depths (0.01, 1e4, 1e4)",
    4: "Watertight 64×64 UV grid and perspective grid, vertices on pixel centres",
    5: "Depth ties and planes 1e-3 apart at z ∈ {1, 10, 50}",
    6: "Antialias gradient of a translated square vs FD; welded interior edges",
    7: "Texture coordinates −1e-7, 0, 1 + 1e-7, ±1e20, ±inf, NaN; 1×1 and NPOT textures",
    8: "Two UV islands: texels outside get exactly zero gradient",
    9: "Means at z ∈ {−1, 0, near ± 1e-7, 1e9} and NaN",
    10: "Grazing and off-screen means, off-centre principal point: FD on both branches",
    11: "Zero, 1e-30, exp(±100) scales; zero quaternion; alpha ≤ opacity",
    12: "Huge Gaussians covering the image many times over",
    13: "Ill-conditioned covariance (1e-2, 1e-5, 1e-5 at 45°)",
    14: "Saturation: 8 Gaussians of opacity 0.95 → T = 1, 0.05, 2.5e-3, 1.25e-4, stop",
    15: "16 stacked Gaussians at opacity 1.0 (clamped)",
    16: "3000 Gaussians of alpha just above 1/255 on one pixel",
    17: "Thresholds at ± 1 ulp: forward and backward decide identically",
    18: "Gaussian on a tile corner swept by 1/64 px: tiled = untiled",
    19: "normal_to_quat for axis, near-antipodal, tiny, huge, zero and NaN normals",
    20: "Occlusion: on the surface, 1 mm in front, 1 mm behind, at 0.5 m and 5 m",
    21: "Zero Gaussians, all culled, 1×1 image",
    22: "Rodrigues at ω = 0 … 1e-2 and −1e-8·(1,1,1)",
    23: "Rodrigues at |ω| = π ± 1e-6, 2π, 10π",
    24: "Zero pose exact; large poses on all joints vs reference and FD",
    25: "Adam with gradients 0, 1e-30, 1e20, inf, NaN on single texels",
    26: "Bad inputs: non-finite, wrong shape/dtype, out of range, empty: named error",
    27: "1, 2 and many threads, ten runs: bitwise-identical outputs and gradients",
    28: "Units: the subject in millimetres and kilometres: same PSNR or a units error",
    29: "Extreme motion: ±90° yaw, ±45° pitch, jaw wide open, eyes at their limits",
    30: "Empty mask, head partly/wholly off-screen, constant colour, one training frame",
    31: "Every rate ×10 and ×0.1, aggressive FLAME rates; bad steps rolled back, never saved",
    32: "Long run at reduced size: finite, Gaussians within budget, memory flat",
    # urhead's own additions to NUMERICS.md's list (issue 15: reduced precision).
    33: "bfloat16 Adam moments: v decays as exact v does; steps follow the float64 reference",
    34: "float16 maps for frozen rendering: within float16 rounding; out of range falls back",
}
GROUPS = [
    ("Mesh raster / interpolate / texture / antialias", [*range(1, 9), 34]),
    ("Gaussian splatting", range(9, 22)),
    ("Skinning", range(22, 25)),
    ("Optimiser", [25, 33]),
    ("Inputs and limits", range(26, 28)),
    ("The whole fit", range(28, 33)),
]
CASE_TEST = re.compile(r"test_case0?(\d+)_")
REPORT_OPTION = "--stability-report"
RUST_OPTION = "--stability-rust-log"
RUST_LOG_ENV = "URHEAD_STABILITY_LOG"  # where the Rust tests append (testing.rs)
WORKER_KEY = "urhead_stability_records"


@dataclass
class Record:
    case: int
    check: str
    test: str
    worst: float | None  # None for a pass/fail check without an error figure
    tolerance: float | None
    count: int | None = None

    def within(self) -> bool:
        if self.worst is None:
            return True
        return self.worst <= self.tolerance  # False for NaN


class Stability:
    """Per-test recorder handed out by the ``stability`` fixture."""

    def __init__(self, sink: list[Record], test: str):
        self._sink, self._test = sink, test

    def record(self, case: int, check: str, worst, tolerance: float) -> None:
        """Records the worst error ``worst`` of ``check`` and asserts it is within
        ``tolerance`` (a NaN worst fails)."""
        worst = float(worst.detach() if hasattr(worst, "detach") else worst)
        tolerance = float(tolerance)
        self._add(Record(case, check, self._test, worst, tolerance))
        assert worst <= tolerance, f"case {case}, {check}: worst {worst:.3g} > {tolerance:.3g}"

    def close(self, case: int, check: str, actual, expected, rtol: float, atol: float) -> None:
        """``torch.allclose(actual, expected, rtol, atol)`` as a recorded figure: worst
        ``max |a − b| / (atol + rtol·|b|)`` against the bound 1."""
        import torch

        a, b = torch.as_tensor(actual).double(), torch.as_tensor(expected).double()
        diff, allowed = (a - b).abs(), atol + rtol * b.abs()
        ratio = torch.where(diff == 0, torch.zeros_like(diff), diff / allowed)
        worst = float(ratio.max()) if ratio.numel() else 0.0
        self.record(case, f"{check}, |a − b| / ({atol:g} + {rtol:g}·|b|)", worst, 1.0)

    def checked(self, case: int, check: str, count: int = 1) -> None:
        """Records a pass/fail check covering ``count`` inputs; call it after the asserts
        it summarises. Its status in the report is the test's outcome."""
        self._add(Record(case, check, self._test, None, None, int(count)))

    def _add(self, record: Record) -> None:
        if record.case not in CASES:
            raise ValueError(f"case must be one of NUMERICS.md's 1–{max(CASES)}, got {record.case}")
        self._sink.append(record)


class StabilityPlugin:
    def __init__(self, config):
        self.config = config
        self.records: list[Record] = []
        self.outcomes: dict[str, str] = {}

    @pytest.fixture
    def stability(self, request) -> Stability:
        return Stability(self.records, request.node.nodeid)

    def pytest_runtest_logreport(self, report):
        # "failed" in any phase wins; a skip in setup counts as skipped.
        previous = self.outcomes.get(report.nodeid)
        if report.failed:
            self.outcomes[report.nodeid] = "failed"
        elif report.skipped and previous is None:
            self.outcomes[report.nodeid] = "skipped"
        elif report.when == "call" and report.passed and previous is None:
            self.outcomes[report.nodeid] = "passed"

    @pytest.hookimpl(optionalhook=True)
    def pytest_testnodedown(self, node, error):
        payload = getattr(node, "workeroutput", {}).get(WORKER_KEY)
        if payload:
            self.records.extend(Record(**r) for r in json.loads(payload))

    def pytest_sessionfinish(self, session):
        if hasattr(self.config, "workeroutput"):  # an xdist worker: hand records over
            self.config.workeroutput[WORKER_KEY] = json.dumps([asdict(r) for r in self.records])
            return
        path = self.config.getoption(REPORT_OPTION) or os.environ.get("URHEAD_STABILITY_REPORT")
        if not path:
            return
        records = list(self.records)
        explicit = self.config.getoption(RUST_OPTION)
        rust_log = explicit or os.environ.get(RUST_LOG_ENV)
        rust_note = "not included (set URHEAD_STABILITY_LOG for `cargo test`)"
        if explicit and not Path(explicit).exists():
            raise pytest.UsageError(f"{RUST_OPTION}: no such file {explicit}")
        if rust_log and Path(rust_log).exists():
            rust = read_rust_log(Path(rust_log), self.outcomes)
            records += rust
            rust_note = f"{len(rust)} records merged from the Rust tests' log"
        text, counts = render_report(records, self.outcomes, rust_note)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
        session.config.get_terminal_writer().line(
            f"stability report: {path} ({counts['pass']} pass, {counts['FAIL']} fail, "
            f"{counts['MISSING']} missing)"
        )


def pytest_addoption(parser):
    group = parser.getgroup("urhead stability report")
    group.addoption(
        REPORT_OPTION,
        metavar="PATH",
        help="write the NUMERICS.md stability report (markdown) to PATH at the end of the run "
        "(or set URHEAD_STABILITY_REPORT)",
    )
    group.addoption(
        RUST_OPTION,
        metavar="PATH",
        help="merge the JSON lines Rust tests wrote under URHEAD_STABILITY_LOG=PATH "
        "(default: $URHEAD_STABILITY_LOG if that file exists)",
    )


def pytest_configure(config):
    config.pluginmanager.register(StabilityPlugin(config), "urhead-stability")


def read_rust_log(path: Path, outcomes: dict[str, str]) -> list[Record]:
    """Records from the Rust tests' JSON lines. A Rust record is written before its
    assert, so a failed bound shows as a worst above the tolerance."""
    records = []
    for line in path.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            test = f"rust:{r['test']}"
            outcomes.setdefault(test, "passed" if r["worst"] <= r["tolerance"] else "failed")
            records.append(Record(r["case"], r["check"], test, r["worst"], r["tolerance"]))
    return records


# --- the report ---------------------------------------------------------------------------


@dataclass
class Row:
    case: int
    check: str
    worst: float | None
    tolerance: float | None
    count: int
    tests: list[str]
    passed: bool


def summarise(records: list[Record], outcomes: dict[str, str]) -> dict[int, list[Row]]:
    """Rows per case: records of the same check and tolerance merged (worst of worsts)."""
    groups = defaultdict(list)
    for r in records:
        if outcomes.get(r.test) == "skipped":
            continue
        groups[(r.case, r.check, r.tolerance)].append(r)
    rows = defaultdict(list)
    for (case, check, tolerance), rs in sorted(groups.items(), key=lambda kv: kv[0][:2]):
        worsts = [r.worst for r in rs if r.worst is not None]
        worst = None
        if worsts:
            worst = math.nan if any(math.isnan(w) for w in worsts) else max(worsts)
        tests = sorted({r.test for r in rs})
        passed = all(r.within() for r in rs) and all(outcomes.get(t) == "passed" for t in tests)
        count = sum(r.count if r.count is not None else 1 for r in rs)
        rows[case].append(Row(case, check, worst, tolerance, count, tests, passed))
    return rows


def case_status(rows: list[Row], failed_named: list[str]) -> str:
    if failed_named or any(not r.passed for r in rows):
        return "FAIL"
    return "pass" if rows else "MISSING"


def fmt(x: float | None) -> str:
    if x is None:
        return "—"
    if x == 0:
        return "0"
    return f"{x:.2e}"


def cell(text: str) -> str:
    return text.replace("|", "\\|")


def test_list(tests: list[str]) -> str:
    """Test ids grouped by function: ``test_x::test_case7_foo`` ×6 for six parametrisations."""
    functions = defaultdict(int)
    for test in tests:
        functions[test.replace("tests/", "").replace(".py::", "::").split("[")[0]] += 1
    return "<br>".join(f"`{f}`" + (f" ×{n}" if n > 1 else "") for f, n in functions.items())


def machine_line() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    python = platform.python_version()
    return f"{cpu}, {os.cpu_count()} logical CPUs, Python {python}, torch {torch.__version__}"


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def render_report(
    records: list[Record], outcomes: dict[str, str], rust_note: str = "not included"
) -> tuple[str, dict]:
    """The markdown report and the number of cases per status ("pass", "FAIL", "MISSING")."""
    rows = summarise(records, outcomes)
    named = defaultdict(list)  # case → tests named test_caseNN_* (whether or not they record)
    for test in outcomes:
        m = CASE_TEST.search(test.split("::")[-1])
        if m and int(m.group(1)) in CASES:
            named[int(m.group(1))].append(test)
    failed_named = {c: [t for t in ts if outcomes[t] == "failed"] for c, ts in named.items()}
    status = {c: case_status(rows.get(c, []), failed_named.get(c, [])) for c in CASES}
    counts = {s: sum(v == s for v in status.values()) for s in ("pass", "FAIL", "MISSING")}

    lines = [
        "# Numerical stability report",
        "",
        "Generated by the test suite — do not edit. Regenerate with",
        "",
        "```bash",
        "export URHEAD_STABILITY_LOG=/tmp/urhead-stability.jsonl && rm -f $URHEAD_STABILITY_LOG",
        "cargo test -p urhead-core --tests && python -m pytest -n 2 --stability-report "
        "docs/stability.md",
        "```",
        "",
        "Each row is a check an extreme-case test ran in this run, the worst error it observed "
        "(over all parametrisations of the tests listed) and the bound the test asserts "
        "(the project sets bounds from observed worst errors and never widens one to pass). "
        "A check without an error figure (an exception raised, a set of pixels "
        "covered exactly) shows how many inputs it covered. A case passes only if every check "
        "held and every test listed for it passed; a case no test recorded a check for is "
        "MISSING. The cases are those of NUMERICS.md (design notes shared by the project), "
        "with cases 33 (bfloat16 optimiser moments) and 34 (float16 maps for rendering) "
        "added by urhead.",
        "",
        f"- run: {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, commit "
        f"`{git_commit()}`, {len(outcomes)} tests, {len(records)} records",
        f"- machine: {machine_line()}",
        f"- Rust checks: {rust_note}",
        f"- result: **{counts['pass']} pass, {counts['FAIL']} fail, "
        f"{counts['MISSING']} missing** of {len(CASES)} cases",
        "",
        "| case | what | checks | worst / tolerance (tightest margin) | status |",
        "|---|---|---|---|---|",
    ]
    for case, title in CASES.items():
        rs = rows.get(case, [])
        bounded = [r for r in rs if r.worst is not None]
        margin = "—"
        if bounded:
            # The check closest to its bound; exact (zero-tolerance) checks rank by worst.
            tight = max(bounded, key=lambda r: (r.tolerance > 0, r.worst / (r.tolerance or 1)))
            margin = f"{fmt(tight.worst)} / {fmt(tight.tolerance)}"
        lines.append(
            f"| [{case}](#case-{case}) | {cell(title)} | {len(rs)} | {margin} | {status[case]} |"
        )
    for group, cases in GROUPS:
        lines += ["", f"## {group}"]
        for case in cases:
            lines += ["", f"### Case {case}", "", f"{CASES[case]} — **{status[case]}**", ""]
            rs = rows.get(case, [])
            if not rs:
                lines.append("No test recorded a check for this case in this run.")
            else:
                lines += [
                    "| check | worst | tolerance | inputs | status | tests |",
                    "|---|---|---|---|---|---|",
                ]
                for r in rs:
                    mark = "pass" if r.passed else "FAIL"
                    lines.append(
                        f"| {cell(r.check)} | {fmt(r.worst)} | {fmt(r.tolerance)} | {r.count} | "
                        f"{mark} | {test_list(r.tests)} |"
                    )
            failing = failed_named.get(case, [])
            if failing:
                lines += ["", "Failed tests: " + test_list(failing)]
    return "\n".join(lines) + "\n", counts
