"""Ray's overhead per subject: ``urhead fit`` against ``urhead fit-many`` on one tiny
synthetic subject (the fit itself takes a few seconds), medians of wall-clock and CPU
seconds over a few runs. Two ways of running fit-many: starting a local Ray for the run
(no ``--address``), and joining a Ray head that is already up (``--address``, the cluster
case). Needs ``pip install 'urhead[cluster]'``.

    python benchmarks/bench_fit_many.py [--runs 3] [--cpus 2]

CPU seconds are those of the command's process tree and, when joining a running head, of
the head's (its workers included) during the run.
"""

from __future__ import annotations

import argparse
import os
import secrets
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from urhead.data.synth.subject import SynthConfig, synthesize

FIT_OPTIONS = [
    *("--iterations", "100", "--uv-resolution", "64", "--error-grid", "32"),
    *("--initial-gaussians", "300", "--max-gaussians", "450", "--sample-every", "10"),
    *("--sample-cap", "60", "--color-init-frames", "2", "--eval-frames", "2"),
    *("--eval-every-seconds", "1000"),
]
TICKS = os.sysconf("SC_CLK_TCK")


def process_cpu() -> dict[int, tuple[int, float]]:
    """``{pid: (parent pid, CPU seconds of the process itself)}`` for every process."""
    table = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        table[int(stat.parent.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / TICKS)
    return table


def tree(table: dict, roots: set[int]) -> dict[int, float]:
    """CPU seconds of the processes at and under ``roots``."""
    found = {}
    for pid, (_, cpu) in table.items():
        p, seen = pid, 0
        while p not in roots and p in table and seen < 64:
            p, seen = table[p][0], seen + 1
        if p in roots:
            found[pid] = cpu
    return found


def timed(command: list[str], env: dict, head_pid: int | None = None) -> tuple[float, float]:
    """Wall seconds of ``command`` and the CPU seconds its process tree (and the Ray head's,
    when given) used meanwhile, sampled every 50 ms: Ray's processes are reaped without
    accounting to a parent, so each is counted while it lives (losing up to its last
    50 ms; the same for all three ways of fitting)."""
    heads = {head_pid} if head_pid else set()
    before = tree(process_cpu(), heads)
    last: dict[int, float] = {}
    start = time.perf_counter()
    proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    while proc.poll() is None:
        last.update(tree(process_cpu(), heads | {proc.pid}))
        time.sleep(0.05)
    wall = time.perf_counter() - start
    _, errors = proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{errors.decode()}")
    return wall, sum(cpu - before.get(pid, 0.0) for pid, cpu in last.items())


def start_head(cpus: int, temp: Path, env: dict) -> tuple[subprocess.Popen, str]:
    head = subprocess.Popen(
        [
            *(str(Path(sys.executable).with_name("ray")), "start", "--head", "--block"),
            *("--port=0", f"--num-cpus={cpus}"),
            *("--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={temp}"),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    address = temp / "ray_current_cluster"
    while not address.is_file() or not address.read_text().strip():
        if head.poll() is not None:
            raise RuntimeError("ray start --head exited")
        time.sleep(0.2)
    return head, address.read_text().strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--cpus", type=int, default=2, help="CPUs of the fit (and the head)")
    parser.add_argument("--batch", type=int, default=4, help="subjects of the batch run")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="urhead-bench-ray-"))
    # The head and the drivers share a token of this run (not whatever ~/.ray holds).
    env = dict(os.environ, URHEAD_NUM_THREADS=str(args.cpus), RAY_AUTH_MODE="token")
    env["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    urhead = [sys.executable, "-m", "urhead.cli"]
    config = SynthConfig(
        frames=10, resolution=64, seed=5, difficulty="easy", samples_per_side=1,
        edge_samples_per_side=1,
    )  # fmt: skip
    try:
        subject = synthesize(work / "subject", config, progress=False)
        batch = [str(shutil.copytree(subject, work / f"subject{k}")) for k in range(args.batch)]
        many = [*urhead, "fit-many", "--cpus-per-fit", str(args.cpus), *FIT_OPTIONS]
        head, address = start_head(args.cpus, work / "ray", env)
        # Each way of fitting: its command for run i, whether it joins the head, subjects.
        ways = {
            "urhead fit": (lambda i: [*urhead, "fit", str(subject), "--quiet", *FIT_OPTIONS,
                                      "--out", str(work / f"fit{i}")], False, 1),
            "fit-many, local Ray started": (lambda i: [*many, str(subject),
                                            "--out", str(work / f"local{i}")], False, 1),
            "fit-many, joining a head": (lambda i: [*many, str(subject), "--address", address,
                                         "--out", str(work / f"join{i}")], True, 1),
            f"fit-many, {args.batch} subjects, joining": (lambda i: [*many, *batch,
                "--address", address, "--out", str(work / f"batch{i}")], True, args.batch),
        }  # fmt: skip
        runs: dict[str, list[tuple[float, float]]] = {name: [] for name in ways}
        try:
            for i in range(args.runs):  # interleaved, so load changes hit every way alike
                for name, (command, joins, _) in ways.items():
                    runs[name].append(timed(command(i), env, head.pid if joins else None))
        finally:
            head.send_signal(signal.SIGTERM)
            head.wait()
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(
        f"medians of {args.runs} runs, {args.cpus} CPU(s) per fit, seconds per subject "
        "(wall / CPU) and the overhead against urhead fit"
    )
    per_subject = {
        name: [statistics.median(r[j] for r in runs[name]) / count for j in (0, 1)]
        for name, (_, _, count) in ways.items()
    }
    fit_wall, fit_cpu = per_subject["urhead fit"]
    for name, (wall, cpu) in per_subject.items():
        overhead = (
            f"   {wall - fit_wall:+.1f} / {cpu - fit_cpu:+.1f}" if name != "urhead fit" else ""
        )
        print(f"{name:34s}{wall:6.1f} / {cpu:5.1f}{overhead}")


if __name__ == "__main__":
    main()
