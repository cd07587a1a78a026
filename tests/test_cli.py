"""The command line itself: help and --version without importing torch, ``python -m
urhead``, defaults in every help, one thread policy for every command, Ctrl-C's message,
and progress lines fit for a log file."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest
import torch

import urhead
from urhead import _progress, cli
from urhead.cli import COMMANDS, build_parser, main


def run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )


def test_help_and_version_do_not_import_torch():
    # torch's import is what made `urhead --help` take seconds.
    for argv in (["--help"], ["--version"], ["nonsense"]):
        done = run_python(
            "import sys\n"
            "from urhead.cli import main\n"
            "try:\n"
            f"    main({argv!r})\n"
            "except SystemExit:\n"
            "    pass\n"
            "print('torch imported:', 'torch' in sys.modules)"
        )
        assert "torch imported: False" in done.stdout, (argv, done.stdout, done.stderr)
    assert "invalid choice: 'nonsense'" in done.stderr  # argparse's error, no command loaded


def test_python_m_urhead_version_and_help():
    version = subprocess.run(
        [sys.executable, "-m", "urhead", "--version"], capture_output=True, text=True, check=True
    )
    assert version.stdout.strip() == f"urhead {urhead.__version__}"
    help_text = subprocess.run(
        [sys.executable, "-m", "urhead", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for name in COMMANDS:
        assert name in help_text


def test_the_command_table_matches_the_modules():
    parser = build_parser()  # every command complete
    sub = next(a for a in parser._actions if a.dest == "command")
    helps = {a.dest: a.help for a in sub._choices_actions}
    assert helps == {name: summary for name, (_, summary) in COMMANDS.items()}


@pytest.mark.parametrize(
    "command, expected",
    [
        ("render", ["views in the orbit (default: 60)", "MP4 frame rate (default: 25.0)"]),
        ("eval", ["frames to score (default: test)", "--refine-flame (default: 20)"]),
        ("synth", ["(default: 600)"]),
        ("reenact", ["MP4 frame rate (default: 25.0)"]),
        # fit: the field's default and the quick preset's value, side by side
        ("fit", ["(default: paper)", "--preset quick: 1500)"]),
    ],
)
def test_help_shows_defaults(command, expected, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())  # unwrap argparse's line breaks
    for phrase in expected:
        assert phrase in text, (command, phrase)


@pytest.fixture
def spy_on_run(monkeypatch):
    """Replaces every command's ``run`` with one that records the thread settings it
    starts with; restores torch's thread count afterwards."""
    import importlib

    seen = {}
    monkeypatch.delenv("URHEAD_NUM_THREADS", raising=False)
    previous = torch.get_num_threads()
    for name, (module, _) in COMMANDS.items():

        def spy(args, name=name):
            seen[name] = (torch.get_num_threads(), os.environ.get("URHEAD_NUM_THREADS"))
            return 0

        monkeypatch.setattr(importlib.import_module(module), "run", spy)
    yield seen
    torch.set_num_threads(previous)


def test_every_command_runs_under_the_thread_policy(spy_on_run, tmp_path):
    argvs = {
        "convert-flame": ["convert-flame", "x.pkl", "-o", str(tmp_path / "h.npz")],
        "synth": ["synth", "--out", str(tmp_path / "s")],
        "fit": ["fit", str(tmp_path), "--out", str(tmp_path / "o")],
        "fit-many": ["fit-many", str(tmp_path), "--out", str(tmp_path / "o")],
        "eval": ["eval", str(tmp_path)],
        "render": ["render", str(tmp_path), "--out", str(tmp_path / "r")],
        "reenact": ["reenact", str(tmp_path), "--driver", "d", "--out", "r.mp4"],
        "export": ["export", str(tmp_path), "--maps", str(tmp_path / "m")],
    }
    assert sorted(argvs) == sorted(COMMANDS)
    for name, argv in argvs.items():
        torch.set_num_threads(2)
        os.environ.pop("URHEAD_NUM_THREADS", None)
        assert main(argv) == 0
        # torch one thread, the Rust kernels every core
        assert spy_on_run[name] == (1, str(os.cpu_count())), name


def test_an_explicit_urhead_num_threads_is_kept(spy_on_run, monkeypatch, tmp_path):
    monkeypatch.setenv("URHEAD_NUM_THREADS", "3")
    assert main(["render", str(tmp_path), "--out", str(tmp_path / "r")]) == 0
    assert spy_on_run["render"] == (1, "3")


def test_ctrl_c_says_how_to_resume(monkeypatch, tmp_path, capsys):
    import urhead.train.command as fit_command
    import urhead.use.render as render_command

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(render_command, "run", interrupted)
    monkeypatch.setattr(fit_command, "run", interrupted)
    previous = torch.get_num_threads()
    try:
        assert main(["render", str(tmp_path), "--out", str(tmp_path / "r")]) == 130
        assert "run the same command again" in capsys.readouterr().err
        assert main(["fit", str(tmp_path), "--out", str(tmp_path / "o")]) == 130
        assert "No checkpoint was written yet" in capsys.readouterr().err
    finally:
        torch.set_num_threads(previous)


def test_only_the_requested_command_module_is_built():
    assert cli.requested_command(["render", "--help"]) == "render"
    assert cli.requested_command(["--help"]) == ""
    assert cli.requested_command(["nonsense"]) == ""


def test_plain_progress_writes_a_few_whole_lines(monkeypatch):
    clock = iter(range(0, 1000, 3))  # 3 s per step
    monkeypatch.setattr(_progress.time, "monotonic", lambda: float(next(clock)))
    stream = io.StringIO()  # not a terminal: plain lines
    with _progress.progress(20, "render", stream=stream, interval=10.0) as bar:
        for _ in range(20):
            bar.update(1)
    text = stream.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert lines[0].startswith("render: 1/20 frames (5 %)")
    assert lines[-1].startswith("render: 20/20 frames (100 %)")
    assert 5 <= len(lines) <= 8  # every ~10 s of 60, not every step
    assert all("left" in line for line in lines[:-1])


def test_plain_progress_resumes_and_shows_the_fit_postfix(monkeypatch):
    clock = iter(range(0, 1000, 4))
    monkeypatch.setattr(_progress.time, "monotonic", lambda: float(next(clock)))
    stream = io.StringIO()
    with _progress.progress(100, "fit", "it", stream=stream, initial=90) as bar:
        bar.set_postfix(loss="0.0123", psnr="24.50")
        bar.update(1)
        bar.set_description("fit (held-out 25.00 dB)")
        for _ in range(9):
            bar.update(1)
    lines = stream.getvalue().splitlines()
    # Resumed at 90: the first line counts from there and its estimate uses one step.
    assert lines[0].startswith("fit: 91/100 its (91 %)") and "~36 s left" in lines[0]
    assert lines[0].endswith("(loss=0.0123, psnr=24.50)")
    assert lines[-1].startswith("fit (held-out 25.00 dB): 100/100 its (100 %)")


def test_progress_on_a_terminal_is_tqdm():
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    stream = Terminal()
    with _progress.progress(3, "eval", stream=stream) as bar:
        bar.update(3)
    assert "\r" in stream.getvalue() and "3/3" in stream.getvalue()
