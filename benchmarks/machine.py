"""The machine a benchmark ran on: CPU, cores, memory, versions, thread settings."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

import torch

import urhead
from urhead._threads import num_threads


def _cpuinfo_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return None


def _command(*args: str) -> str:
    try:
        return subprocess.run(args, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def describe() -> dict:
    return {
        "cpu": _cpuinfo_model(),
        "logical_cpus": os.cpu_count(),
        "memory_gb": _memory_gb(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "urhead": getattr(urhead, "__version__", "unknown"),
        "rustc": _command("rustc", "--version"),
        "commit": _command("git", "rev-parse", "--short", "HEAD"),
        "urhead_threads": num_threads(),
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)"),
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def markdown(m: dict) -> str:
    memory = f"{m['memory_gb']:.0f} GB RAM" if m["memory_gb"] else "RAM unknown"
    load = ", ".join(f"{x:.2f}" for x in m["load_average"]) if m["load_average"] else "unknown"
    return "\n".join(
        [
            f"- CPU: {m['cpu']}, {m['logical_cpus']} logical CPUs, {memory}",
            f"- {m['os']}; Python {m['python']}, torch {m['torch']}, urhead {m['urhead']} "
            f"(commit `{m['commit']}`), {m['rustc']}",
            f"- threads: urhead kernels {m['urhead_threads']} (`URHEAD_NUM_THREADS`), torch "
            f"{m['torch_threads']} (`torch.set_num_threads`), OMP_WAIT_POLICY="
            f"{m['omp_wait_policy']}",
            f"- load average (1, 5, 15 min) when the run started: {load}",
        ]
    )
