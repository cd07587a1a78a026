"""``urhead fit-many`` through a real Ray cluster started for this module (``ray start
--head`` on 2 CPUs): fits equal ``urhead fit`` bit for bit, a broken subject is reported
while the others finish, finished subjects are skipped, and a subject whose worker is
killed mid-fit resumes from its checkpoint and finishes."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from test_fit import TINY  # the tiny synthetic subject of the fit's own tests
from urhead.cli import main
from urhead.config import FitConfig
from urhead.data.synth.subject import synthesize
from urhead.model import load_avatar
from urhead.train.checkpoint import find_checkpoint
from urhead.train.summary import Summary

# One cluster for the module: xdist's loadgroup keeps these tests on one worker.
pytestmark = pytest.mark.xdist_group("ray")

TINY_FIT = {
    "iterations": 40,
    "uv_resolution": 64,
    "initial_gaussians": 300,
    "max_gaussians": 450,
    "sample_every": 10,
    "sample_cap": 60,
    "error_grid": 32,
    "color_init_frames": 2,
    "eval_frames": 2,
    "eval_every_seconds": 1000,
    "checkpoint_every": 10,
}


def _options(**changes) -> list[str]:
    """TINY_FIT with ``changes`` as command-line options."""
    pairs = {**TINY_FIT, **changes}.items()
    return [word for k, v in pairs for word in ("--" + k.replace("_", "-"), str(v))]


FIT_OPTIONS = _options()
# Long enough to kill the worker after a checkpoint and before the end.
KILLABLE_OPTIONS = _options(iterations=150, checkpoint_every=5)


@pytest.fixture(scope="module")
def subjects(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("subjects")
    alice = synthesize(base / "alice", TINY, progress=False)
    bob = synthesize(base / "bob", replace(TINY, seed=TINY.seed + 1), progress=False)
    broken = shutil.copytree(alice, base / "broken")
    for f in broken.glob("transforms*.json"):
        f.write_text('{"frames": [')
    return {"alice": alice, "bob": bob, "broken": broken}


@pytest.fixture(scope="module")
def ray_cluster():
    """``(address, pid)`` of a Ray head started here and stopped (its whole process tree)
    at the end. It takes a token of its own, which this process and the drivers it starts
    inherit (not whatever token ~/.ray holds). Its temporary folder is short: Ray's socket
    paths must fit in 107 characters."""
    with pytest.MonkeyPatch.context() as patch:
        # A Ray driver replaces builtins.print for its progress bars, for good: not in the
        # test process, whose later tests see print.
        patch.setenv("RAY_TQDM_PATCH_PRINT", "0")
        patch.setenv("RAY_AUTH_MODE", "token")
        patch.setenv("RAY_AUTH_TOKEN", secrets.token_hex(32))
        patch.delenv("RAY_AUTH_TOKEN_PATH", raising=False)
        pytest.importorskip("ray")  # after the token: Ray reads it once per process
        temp = Path(tempfile.mkdtemp(prefix="urhead-ray-"))
        head = subprocess.Popen(
            [
                # Ray's CLI through this interpreter: its `ray` script is beside whichever
                # Python installed the package (a venv's or the system's), not always ours.
                *(sys.executable, "-c", "from ray.scripts.scripts import main; main()"),
                *("start", "--head", "--block", "--port=0", "--num-cpus=2"),
                *("--include-dashboard=false", "--object-store-memory=200000000"),
                *("--disable-usage-stats", f"--temp-dir={temp}"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            address_file = temp / "ray_current_cluster"
            deadline = time.time() + 60
            while not address_file.is_file() or not address_file.read_text().strip():
                assert head.poll() is None, "ray start --head exited"
                assert time.time() < deadline, "the Ray head did not start within 60 s"
                time.sleep(0.2)
            yield address_file.read_text().strip(), head.pid
        finally:
            head.send_signal(signal.SIGTERM)  # ray start --block stops what it started
            try:
                head.wait(timeout=60)
            except subprocess.TimeoutExpired:
                head.kill()
                head.wait()
            shutil.rmtree(temp, ignore_errors=True)


def _fit(subject: Path, out: Path, options: list[str], monkeypatch) -> Path:
    """Plain ``urhead fit`` with the kernels on one thread, as each fit-many task here."""
    monkeypatch.setenv("URHEAD_NUM_THREADS", "1")
    assert main(["fit", str(subject), "--out", str(out), "--quiet", *options]) == 0
    return out


def _assert_same_fit(a: Path, b: Path) -> None:
    x, y = load_avatar(a / "avatar"), load_avatar(b / "avatar")
    assert torch.equal(x.maps, y.maps)
    assert torch.equal(x.gaussian_uv, y.gaussian_uv)
    assert torch.equal(x.frame_params, y.frame_params)
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert _untimed(ma) == _untimed(mb)
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())


def _untimed(metrics: dict) -> dict:
    """The metrics without the timings (``seconds``, ``evaluation_seconds``, ...)."""
    return {k: v for k, v in metrics.items() if not k.endswith("seconds")}


def _summary(root: Path) -> dict[str, dict]:
    return {r["subject"]: r for r in json.loads((root / "summary.json").read_text())["subjects"]}


def test_fits_equal_urhead_fit_and_a_broken_subject_is_reported(
    subjects, ray_cluster, tmp_path, monkeypatch, capsys
):
    address, _ = ray_cluster
    root = tmp_path / "root"
    names = ["alice", "bob", "broken"]
    args = ["fit-many", *(str(subjects[n]) for n in names), "--out", str(root)]
    args += ["--address", address, "--cpus-per-fit", "1", *FIT_OPTIONS]
    assert main(args) == 1, "a subject failed"
    out, err = capsys.readouterr()
    assert "1 of 3 subjects failed" in err

    summary = _summary(root)
    assert [summary[n]["status"] for n in names] == ["done", "done", "failed"]
    for name in ("alice", "bob"):
        reference = _fit(subjects[name], tmp_path / f"fit-{name}", FIT_OPTIONS, monkeypatch)
        _assert_same_fit(reference, root / name)
        metrics = json.loads((reference / "metrics.json").read_text())
        row = summary[name]
        assert row["psnr"] == metrics["psnr"]
        assert row["psnr_full"] == metrics.get("psnr_full")
        assert row["seconds"] > 0 and row["error"] is None
        assert f"] {name}: done in" in out
    error = summary["broken"]["error"]
    assert "transforms" in error and "not valid JSON" in error and str(subjects["broken"]) in error
    assert "broken: failed: DatasetError" in out
    assert "subject  status  PSNR mask  PSNR full  seconds  error" in out  # the table

    # Again: the finished subjects are skipped, not refitted (no task at all).
    stamps = {n: (root / n / "avatar" / "maps.npy").stat().st_mtime_ns for n in ("alice", "bob")}
    finished = [a for a in args if a != str(subjects["broken"])]
    assert main(finished) == 0
    again = _summary(root)
    assert [again[n]["status"] for n in ("alice", "bob")] == ["skipped", "skipped"]
    for name in ("alice", "bob"):
        assert (root / name / "avatar" / "maps.npy").stat().st_mtime_ns == stamps[name]
        assert again[name]["seconds"] == summary[name]["seconds"]

    # Other options for a finished subject: refused, not silently kept.
    other = [*finished[: -len(FIT_OPTIONS)], *_options(checkpoint_every=11)]
    assert main(other) == 1
    assert "different configuration" in _summary(root)["alice"]["error"]


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid``, from /proc."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _worker_running(cluster_pid: int, task_name: str) -> int | None:
    """The Ray worker of our cluster executing ``task_name`` (Ray retitles it ``ray::NAME``)."""
    for pid in _descendants(cluster_pid):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if title.startswith(f"ray::{task_name}"):
            return pid
    return None


def test_a_killed_worker_s_subject_resumes_and_finishes(
    subjects, ray_cluster, tmp_path, monkeypatch
):
    address, cluster_pid = ray_cluster
    root = tmp_path / "root"
    command = [sys.executable, "-m", "urhead.cli", "fit-many", str(subjects["alice"])]
    command += ["--out", str(root), "--address", address, *KILLABLE_OPTIONS]
    driver = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ
    )
    killed_at = None
    deadline = time.time() + 120
    while killed_at is None and time.time() < deadline and driver.poll() is None:
        checkpoint = find_checkpoint(root / "alice")
        if checkpoint is not None:
            iteration = torch.load(checkpoint / "state.pt", weights_only=True)["iteration"]
            worker = _worker_running(cluster_pid, "fit alice")
            if iteration >= 20 and worker is not None:
                os.kill(worker, signal.SIGKILL)
                killed_at = iteration
        time.sleep(0.05)
    output, _ = driver.communicate(timeout=300)
    assert killed_at is not None, f"no worker to kill mid-fit:\n{output}"
    assert driver.returncode == 0, output
    assert "alice: resuming from" in output
    assert _summary(root)["alice"]["status"] == "done"
    reference = _fit(subjects["alice"], tmp_path / "fit-alice", KILLABLE_OPTIONS, monkeypatch)
    _assert_same_fit(reference, root / "alice")


def test_more_cpus_per_fit_than_any_node_has_is_refused(subjects, ray_cluster, tmp_path, capsys):
    address, _ = ray_cluster
    args = ["fit-many", str(subjects["alice"]), "--out", str(tmp_path), "--address", address]
    assert main([*args, "--cpus-per-fit", "3", *FIT_OPTIONS]) == 1
    assert "--cpus-per-fit 3: no node of the Ray cluster has that many CPUs" in (
        capsys.readouterr().err
    )
    assert not (tmp_path / "alice").exists()


def test_two_subjects_of_one_name_are_refused(tmp_path, monkeypatch, capsys):
    """Refused before Ray is looked for: the arguments' mistake is named without it too."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    a, b = tmp_path / "a" / "same", tmp_path / "b" / "same"
    assert main(["fit-many", str(a), str(b), "--out", str(tmp_path / "root")]) == 1
    assert "would both write ROOT/same" in capsys.readouterr().err


def test_without_ray_the_message_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert main(["fit-many", str(tmp_path), "--out", str(tmp_path / "root")]) == 1
    assert "pip install 'urhead[cluster]'" in capsys.readouterr().err


def test_summary_rows_progress_and_table(tmp_path):
    """Without Ray: the rows follow the outcomes, psnr_full is shown when a fit reports it,
    and the file is whole after every write."""
    subjects = [tmp_path / "subjects" / n for n in ("ann", "ben", "cat")]
    summary = Summary(tmp_path, subjects, FitConfig())
    summary.write()
    assert json.loads((tmp_path / "summary.json").read_text())["pending"] == 3
    summary.finished("ann", {"metrics": {"psnr": 20.5, "psnr_full": 18.25}, "seconds": 3.216})
    summary.finished("ben", {"metrics": {"psnr": 19.0}, "seconds": 2.0})
    summary.finished("cat", {"error": "DatasetError: cat/transforms.json: is not valid JSON"})
    summary.write()
    written = json.loads((tmp_path / "summary.json").read_text())
    assert (written["done"], written["failed"], written["pending"]) == (2, 1, 0)
    ann, ben, cat = written["subjects"]
    assert (ann["psnr"], ann["psnr_full"], ann["seconds"]) == (20.5, 18.25, 3.22)
    assert ben["psnr_full"] is None and cat["status"] == "failed"
    assert summary.progress_line("ann") == (
        "[3/3] ann: done in 3.2 s, held-out PSNR 20.50 dB in the mask, 18.25 dB full image"
    )
    assert summary.progress_line("cat").endswith("failed: " + cat["error"])
    table = summary.table().splitlines()
    assert table[1].split() == ["ann", "done", "20.50", "18.25", "3.2"]
    assert table[2].split() == ["ben", "done", "19.00", "-", "2.0"]
