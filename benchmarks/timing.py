"""Timing helpers shared by the benchmark scripts: medians over repeated runs, reported
next to the plain-torch reference measured in the same process."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_ms(
    fn: Callable[[], object], repeats: int = 30, warmup: int = 3, max_seconds: float = 20.0
) -> float:
    """Median wall time of ``fn()`` in milliseconds (stops early after ``max_seconds``)."""
    for _ in range(warmup):
        fn()
    times = []
    start = time.perf_counter()
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
        if time.perf_counter() - start > max_seconds and len(times) >= 3:
            break
    return statistics.median(times)


def wall_cpu_samples(fn: Callable[[], object], repeats: int) -> tuple[list, list]:
    """``(wall_ms, cpu_ms)`` of ``repeats`` calls of ``fn()``: wall time and the process
    CPU time each took (user + system, all threads)."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - w0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return wall, cpu


def median_wall_cpu_ms(fn: Callable[[], object], repeats: int, warmup: int = 1) -> dict:
    """``{"wall_ms", "cpu_ms"}``: medians of ``fn()``'s wall time and of the process CPU
    time it took. On a shared machine the CPU time stays meaningful when the wall time is
    inflated by other work; CPU / wall is the parallelism the call reached."""
    for _ in range(warmup):
        fn()
    wall, cpu = wall_cpu_samples(fn, repeats)
    return {"wall_ms": statistics.median(wall), "cpu_ms": statistics.median(cpu)}


def report(rows: list[tuple[str, float, float | None]]) -> None:
    """Prints ``(name, urhead_ms, reference_ms)`` rows with the speed-up ratio."""
    print(f"{'case':<40} {'urhead ms':>10} {'torch ms':>10} {'ratio':>8}")
    for name, ours, ref in rows:
        ratio = f"{ref / ours:7.1f}x" if ref else "     n/a"
        ref_s = f"{ref:10.2f}" if ref else "       n/a"
        print(f"{name:<40} {ours:10.3f} {ref_s} {ratio}")
