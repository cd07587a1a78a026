"""Attack the ``urhead`` command line with corrupted and hostile inputs and classify what
each attempt does (issue 14).

    python benchmarks/attack_cli.py [--work DIR] [--only NAME,...]

Each case prepares its inputs from a few tiny fixtures (8-frame 64² synthetic subjects, a
20-iteration fit), runs one ``urhead`` command in a subprocess and is classified as

- ``clean error``: non-zero exit, a one-line ``urhead CMD: error:`` naming the file or
  option at fault, before the work started;
- ``late error``: a clean error that came only after the work (training ran);
- ``unnamed``: a clean error whose message does not name the file at fault;
- ``traceback``: a Python traceback escaped; ``crash``: killed by a signal;
- ``silent``: exit 0 over a wrong result (bad input accepted, a fit overwritten, …);
- ``half-written``: exit 0 with a broken output;
- ``ok``: the intended behaviour where success is correct (a repaired cache, for one).

Prints a table (case, class, first line of the message) and the count per class. Run with
``OMP_NUM_THREADS=1 URHEAD_NUM_THREADS=1``; it takes a few minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

URHEAD = [sys.executable, "-m", "urhead"]
SUBJECT_ARGS = ["--frames", "8", "--samples", "1", "--edge-samples", "1", "--quiet"]
FIT_ARGS = [
    *("--preset", "quick", "--iterations", "20", "--uv-resolution", "64"),
    *("--refine-steps", "0", "--eval-frames", "2", "--quiet"),
]
WORK_MARKER = "left out:"  # the fit logs what it leaves out just before it trains


@dataclass
class Attempt:
    argv: list
    names: str | None = None
    """A text the error message must contain (the file or option at fault)."""
    env: dict = field(default_factory=dict)
    check: object = None
    """check(proc) → a class overriding "silent" / "ok" when the command exits 0."""
    expect_success: bool = False
    cleanup: object = None
    broken_after_failure: Path | None = None
    """A folder where a failed command must leave no broken output (else half-written)."""


CASES = {}


def case(fn):
    CASES[fn.__name__] = fn
    return fn


def urhead(*args) -> list:
    return [*URHEAD, *map(str, args)]


def run_quiet(argv, **kw) -> None:
    subprocess.run(argv, check=True, capture_output=True, **kw)


# --- fixtures ------------------------------------------------------------------------


class Fixtures:
    def __init__(self, work: Path):
        self.work = work
        self.subject = self._synth("subject", 64, 0)
        self.other_subject = self._synth("other_subject", 64, 1)
        self.small_subject = self._synth("small_subject", 48, 0)
        self.avatar_fit = work / "fit"
        if not (self.avatar_fit / "avatar" / "avatar.json").is_file():
            run_quiet(urhead("fit", self.subject, "--out", self.avatar_fit, *FIT_ARGS))
        self.avatar = self.avatar_fit / "avatar"
        self.other_head = work / "other_head.npz"
        if not self.other_head.is_file():
            run_quiet(
                [
                    sys.executable,
                    "-c",
                    "import sys; from urhead.head import procedural_head, save_head; "
                    "save_head(procedural_head(1), sys.argv[1])",
                    str(self.other_head),
                ]
            )
        self.checkpoint_fit = work / "checkpointed"
        if not (self.checkpoint_fit / "checkpoint").is_dir():
            run_quiet(
                [
                    sys.executable,
                    "-c",
                    _CHECKPOINT_SNIPPET,
                    str(self.subject),
                    str(self.checkpoint_fit),
                    *FIT_ARGS,
                ]
            )

    def _synth(self, name: str, resolution: int, seed: int) -> Path:
        out = self.work / name
        if not (out / "transforms.json").is_file():
            run_quiet(
                urhead(
                    "synth", "--out", out, "--resolution", resolution, "--seed", seed, *SUBJECT_ARGS
                )
            )
        return out

    def copy(self, what: Path, name: str) -> Path:
        dest = self.work / "cases" / name
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(what, dest)
        return dest

    def scratch(self, name: str) -> Path:
        dest = self.work / "cases" / name
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        return dest


_CHECKPOINT_SNIPPET = """
import sys
from pathlib import Path
from urhead.cli import build_parser
from urhead.data import load_subject
from urhead.head import procedural_head
from urhead.train.checkpoint import save_checkpoint
from urhead.train.command import fit_config
from urhead.train.trainer import Trainer
subject, out = sys.argv[1], Path(sys.argv[2])
args = build_parser("fit").parse_args(["fit", subject, "--out", str(out), *sys.argv[3:]])
trainer = Trainer(load_subject(subject), procedural_head(0), fit_config(args), out,
                  progress=False)
state = trainer.start()
trainer.step(state)
save_checkpoint(out, state.avatar, trainer._checkpoint_state(state))
"""


# --- helpers that damage files ----------------------------------------------------------


def first_frame(subject: Path, split: str) -> dict:
    return json.loads((subject / f"transforms_{split}.json").read_text())["frames"][0]


def truncate_body(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: max(60, len(data) // 3)])


def rewrite_npz(path: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def edit_json(path: Path, edit) -> None:
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def decodes(path: Path) -> bool:
    import cv2

    try:
        data = np.fromfile(path, np.uint8)
    except OSError:
        return False
    return data.size > 0 and cv2.imdecode(data, cv2.IMREAD_UNCHANGED) is not None


def broken_outputs(folder: Path) -> list:
    """PNGs that do not decode and MP4s without frames under ``folder``, hidden
    temporaries aside (they never took an output's name)."""

    def visible(pattern):
        found = folder.rglob(pattern)
        return [
            p
            for p in found
            if not any(part.startswith(".") for part in p.relative_to(folder).parts)
        ]

    broken = [p for p in visible("*.png") if not decodes(p)]
    for mp4 in visible("*.mp4"):
        try:
            import av

            with av.open(str(mp4)) as f:
                if not any(True for _ in f.decode(video=0)):
                    broken.append(mp4)
        except Exception:
            broken.append(mp4)
    return broken


def half_written_unless_whole(folder: Path):
    def check(proc):
        return "half-written" if broken_outputs(folder) else "ok"

    return check


NON_UTF8 = os.fsdecode(b"dir\xff")


# --- subjects -----------------------------------------------------------------------


@case
def train_image_body_corrupt(f: Fixtures):
    s = f.copy(f.subject, "train_image_body_corrupt")
    image = s / first_frame(s, "train")["file_path"]
    truncate_body(image)
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names=image.name)


@case
def test_image_body_corrupt(f: Fixtures):
    s = f.copy(f.subject, "test_image_body_corrupt")
    image = s / first_frame(s, "test")["file_path"]
    truncate_body(image)
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names=image.name)


@case
def test_image_gray(f: Fixtures):
    import cv2

    s = f.copy(f.subject, "test_image_gray")
    image = s / first_frame(s, "test")["file_path"]
    cv2.imwrite(str(image), cv2.imread(str(image), cv2.IMREAD_GRAYSCALE))
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names=image.name)


@case
def train_test_overlap(f: Fixtures):
    s = f.copy(f.subject, "train_test_overlap")
    test = json.loads((s / "transforms_test.json").read_text())

    def add(meta):
        meta["frames"].append(test["frames"][0])
        meta["timestep_indices"].append(test["frames"][0]["timestep_index"])

    edit_json(s / "transforms_train.json", add)
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names="transforms_")


@case
def non_rigid_transform(f: Fixtures):
    s = f.copy(f.subject, "non_rigid_transform")

    def scale(meta):
        m = np.asarray(meta["frames"][0]["transform_matrix"])
        m[:3, :3] *= 1.5
        meta["frames"][0]["transform_matrix"] = m.tolist()

    edit_json(s / "transforms_train.json", scale)
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names="transform_matrix")


@case
def flame_npz_bad_zip(f: Fixtures):
    s = f.copy(f.subject, "flame_npz_bad_zip")
    npz = s / first_frame(s, "train")["flame_param_path"]
    npz.write_bytes(npz.read_bytes()[:100])
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names=npz.name)


@case
def transforms_not_json(f: Fixtures):
    s = f.copy(f.subject, "transforms_not_json")
    (s / "transforms_train.json").write_text("{ not json")
    return Attempt(urhead("fit", s, "--out", s / "out", *FIT_ARGS), names="transforms_train")


@case
def fit_non_utf8_subject_path(f: Fixtures):
    s = f.copy(f.subject, NON_UTF8)
    return Attempt(
        urhead("fit", s, "--out", s.parent / "non_utf8_fit", *FIT_ARGS), expect_success=True
    )


@case
def synth_non_utf8_out(f: Fixtures):
    out = f.scratch("synth_non_utf8") / NON_UTF8
    return Attempt(
        urhead("synth", "--out", out, "--resolution", 32, "--frames", 3, *SUBJECT_ARGS[2:]),
        expect_success=True,
        check=lambda proc: "ok" if decodes(next((out / "images").glob("*.png"))) else "silent",
    )


@case
def render_non_utf8_out(f: Fixtures):
    out = f.scratch("render_non_utf8") / NON_UTF8
    return Attempt(
        urhead("render", f.avatar, "--out", out),
        expect_success=True,
        check=half_written_unless_whole(out),
    )


@case
def export_mesh_non_utf8_out(f: Fixtures):
    out = f.scratch("export_non_utf8") / NON_UTF8
    return Attempt(
        urhead("export", f.avatar, "--mesh", out / "mesh", "--maps", out / "maps", "--frames", "0"),
        expect_success=True,
        check=half_written_unless_whole(out),
    )


@case
def fit_head_bad_zip(f: Fixtures):
    d = f.scratch("fit_head_bad_zip")
    head = d / "head.npz"
    head.write_bytes(b"PK\x03\x04" + b"\0" * 50)
    return Attempt(
        urhead("fit", f.subject, "--out", d / "out", "--head", head, *FIT_ARGS), names="head.npz"
    )


# --- configuration ---------------------------------------------------------------------


@case
def prune_screen_fraction_nan(f: Fixtures):
    d = f.scratch("prune_nan")
    return Attempt(
        urhead("fit", f.subject, "--out", d, *FIT_ARGS, "--prune-screen-fraction", "nan"),
        names="prune",
    )


@case
def prune_screen_fraction_negative(f: Fixtures):
    d = f.scratch("prune_negative")
    return Attempt(
        urhead("fit", f.subject, "--out", d, *FIT_ARGS, "--prune-screen-fraction", "-1"),
        names="prune",
    )


@case
def uv_resolution_8192(f: Fixtures):
    d = f.scratch("uv_8192")
    argv = urhead("fit", f.subject, "--out", d, *FIT_ARGS, "--uv-resolution", "8192")
    # Bound the address space so a build that does try to allocate fails instead of
    # taking the shared machine's memory.
    limit = "import resource,runpy,sys; resource.setrlimit(resource.RLIMIT_AS, (6 << 30,) * 2); "
    argv = [
        sys.executable,
        "-c",
        limit + "sys.argv=['urhead',*sys.argv[1:]]; "
        "runpy.run_module('urhead', run_name='__main__')",
        *argv[3:],
    ]
    return Attempt(argv, names="--uv-resolution")


@case
def num_threads_huge(f: Fixtures):
    # A missing avatar: a build without the bound reports the avatar, never spawning.
    return Attempt(
        urhead("render", f.work / "no_such_avatar", "--out", f.scratch("threads")),
        env={"URHEAD_NUM_THREADS": "100000"},
        names="URHEAD_NUM_THREADS",
    )


# --- FLAME pickles -------------------------------------------------------------------


def _flame_pickle(path: Path, mutate) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from flame_fixtures import flame_like_model, write_flame2020_pickle

    model = flame_like_model()
    mutate(model)
    write_flame2020_pickle(path, model)


@case
def flame_pickle_sparse_index_out_of_range(f: Fixtures):
    import scipy.sparse as sp

    d = f.scratch("flame_sparse")

    def mutate(model):
        j = sp.csc_matrix(model["J_regressor"])
        j.indices[0] = 10**6
        model["J_regressor"] = j

    _flame_pickle(d / "generic_model.pkl", mutate)
    return Attempt(
        urhead("convert-flame", d / "generic_model.pkl", "--output", d / "h.npz"),
        names="generic_model.pkl",
    )


@case
def flame_pickle_truncated(f: Fixtures):
    d = f.scratch("flame_truncated")
    _flame_pickle(d / "generic_model.pkl", lambda m: None)
    p = d / "generic_model.pkl"
    p.write_bytes(p.read_bytes()[:200])
    return Attempt(urhead("convert-flame", p, "--output", d / "h.npz"), names="generic_model.pkl")


# --- avatars -------------------------------------------------------------------------


def avatar_copy(f: Fixtures, name: str) -> Path:
    return f.copy(f.avatar, name)


@case
def avatar_maps_truncated(f: Fixtures):
    a = avatar_copy(f, "maps_truncated")
    truncate_body(a / "maps.npy")
    return Attempt(urhead("eval", a, "--no-stlpips"), names="maps.npy")


@case
def avatar_frames_bad_zip(f: Fixtures):
    a = avatar_copy(f, "frames_bad_zip")
    (a / "frames.npz").write_bytes(b"garbage")
    return Attempt(urhead("eval", a, "--no-stlpips"), names="frames.npz")


@case
def avatar_json_missing_key(f: Fixtures):
    a = avatar_copy(f, "json_missing_key")
    edit_json(a / "avatar.json", lambda m: m.pop("resolution"))
    return Attempt(urhead("eval", a, "--no-stlpips"), names="avatar.json")


@case
def avatar_json_not_json(f: Fixtures):
    a = avatar_copy(f, "json_not_json")
    (a / "avatar.json").write_text("{")
    return Attempt(urhead("eval", a, "--no-stlpips"), names="avatar.json")


@case
def avatar_nan_uv(f: Fixtures):
    a = avatar_copy(f, "nan_uv")
    with np.load(a / "gaussians.npz") as g:
        uv = g["uv"].copy()
    uv[0] = np.nan
    rewrite_npz(a / "gaussians.npz", uv=uv)
    return Attempt(urhead("eval", a, "--no-stlpips"), names="gaussians.npz")


@case
def avatar_uv_out_of_range(f: Fixtures):
    a = avatar_copy(f, "uv_range")
    with np.load(a / "gaussians.npz") as g:
        uv = g["uv"].copy()
    uv[0] = 7.0
    rewrite_npz(a / "gaussians.npz", uv=uv)
    return Attempt(urhead("eval", a, "--no-stlpips"), names="gaussians.npz")


@case
def avatar_bary_outside(f: Fixtures):
    a = avatar_copy(f, "bary_outside")
    with np.load(a / "gaussians.npz") as g:
        bary = g["bary"].copy()
    bary[0] = (2.0, -0.5, -0.5)
    rewrite_npz(a / "gaussians.npz", bary=bary)
    return Attempt(urhead("eval", a, "--no-stlpips"), names="gaussians.npz")


@case
def avatar_swapped_head(f: Fixtures):
    a = avatar_copy(f, "swapped_head")
    shutil.copy(f.other_head, a / "head.npz")
    return Attempt(urhead("eval", a, "--no-stlpips"), names="head.npz")


@case
def avatar_nan_background(f: Fixtures):
    a = avatar_copy(f, "nan_background")
    edit_json(a / "avatar.json", lambda m: m.update(background=[float("nan")] * 3))
    return Attempt(
        urhead("render", a, "--out", f.scratch("nan_background_out")), names="avatar.json"
    )


@case
def avatar_nan_maps(f: Fixtures):
    a = avatar_copy(f, "nan_maps")
    maps = np.load(a / "maps.npy")
    maps[0, 0, 0] = np.nan
    np.save(a / "maps.npy", maps)
    return Attempt(urhead("eval", a, "--no-stlpips"), names="maps.npy")


# --- resume --------------------------------------------------------------------------


@case
def resume_other_subject_same_size(f: Fixtures):
    out = f.copy(f.checkpoint_fit, "resume_same_size")
    return Attempt(
        urhead("fit", f.other_subject, "--out", out, "--resume", *FIT_ARGS), names="subject"
    )


@case
def resume_other_subject_other_size(f: Fixtures):
    out = f.copy(f.checkpoint_fit, "resume_other_size")
    return Attempt(
        urhead("fit", f.small_subject, "--out", out, "--resume", *FIT_ARGS), names="subject"
    )


@case
def resume_other_head(f: Fixtures):
    out = f.copy(f.checkpoint_fit, "resume_other_head")
    return Attempt(
        urhead("fit", f.subject, "--out", out, "--resume", "--head", f.other_head, *FIT_ARGS),
        names="head",
    )


# --- outputs -------------------------------------------------------------------------


def mount_small_disk(folder: Path, size_bytes: int):
    """Mounts a tmpfs of ``size_bytes`` (whole pages, at least one) on ``folder``: a disk
    that really fills. Returns the unmount, or None when mounting is not permitted."""
    pages = max(1, size_bytes // 4096)
    mount = ["mount", "-t", "tmpfs", "-o", f"size={pages * 4}k", "tmpfs", str(folder)]
    if subprocess.run(mount, capture_output=True).returncode:
        return None
    return lambda: subprocess.run(["umount", str(folder)], check=True)


def files_written(f: Fixtures, name: str, argv_of) -> list[Path]:
    """The files ``argv_of(folder)`` writes into an empty folder on the real disk."""
    probe = f.scratch(name + "_probe")
    run_quiet(argv_of(probe))
    return [p for p in probe.rglob("*") if p.is_file()]


def bytes_written(f: Fixtures, name: str, argv_of) -> int:
    return sum(p.stat().st_size for p in files_written(f, name, argv_of))


def half_of_it(files: list[Path]) -> int:
    return sum(p.stat().st_size for p in files) // 2


def pngs_and_one_page(files: list[Path]) -> int:
    """Room for every PNG (whole tmpfs pages) and one page more: the disk fills while the
    video is written."""
    return sum(-(-p.stat().st_size // 4096) * 4096 for p in files if p.suffix == ".png") + 4096


def full_disk(f: Fixtures, name: str, argv_of, room=half_of_it) -> Attempt | None:
    """``argv_of(out)`` on a tmpfs of ``room(files the command writes)`` bytes (default:
    half of them): the disk fills in the middle of the output. Skipped where mounting
    needs privileges this process lacks."""
    size = room(files_written(f, name, argv_of))
    out = f.scratch(name)
    unmount = mount_small_disk(out, size)
    if unmount is None:
        return None
    return Attempt(
        argv_of(out),
        names=str(out),
        check=half_written_unless_whole(out),
        broken_after_failure=out,
        cleanup=unmount,
    )


@case
def render_full_disk(f: Fixtures):
    return full_disk(f, "full_disk", lambda out: urhead("render", f.avatar, "--out", out / "r"))


@case
def render_full_disk_during_video(f: Fixtures):
    return full_disk(
        f,
        "full_disk_video",
        lambda out: urhead("render", f.avatar, "--out", out / "r"),
        room=pngs_and_one_page,
    )


@case
def export_full_disk(f: Fixtures):
    return full_disk(
        f,
        "full_disk_export",
        lambda out: urhead("export", f.avatar, *("--maps", out / "maps", "--mesh", out / "mesh")),
    )


@case
def synth_full_disk(f: Fixtures):
    return full_disk(
        f,
        "full_disk_synth",
        lambda out: urhead("synth", "--out", out / "s", "--resolution", 64, *SUBJECT_ARGS),
    )


@case
def reenact_full_disk(f: Fixtures):
    """The MP4 (~3 kB) is smaller than one tmpfs page, so the disk is made to fill halfway
    through it with a file-size limit (``RLIMIT_FSIZE``; Python ignores ``SIGXFSZ``, so a
    write past it fails with ``EFBIG``) instead of a mount."""

    def argv_of(out):
        return urhead("reenact", f.avatar, "--driver", f.other_subject, "--out", out / "r.mp4")

    half = bytes_written(f, "full_disk_reenact", argv_of) // 2
    out = f.scratch("full_disk_reenact")
    limit = f"import resource; resource.setrlimit(resource.RLIMIT_FSIZE, ({half}, {half})); "
    argv = argv_of(out)
    argv = [
        sys.executable,
        "-c",
        limit + "import runpy,sys; sys.argv=['urhead',*sys.argv[1:]]; "
        "runpy.run_module('urhead', run_name='__main__')",
        *argv[3:],
    ]
    return Attempt(
        argv, names=str(out), check=half_written_unless_whole(out), broken_after_failure=out
    )


def read_only_folder(folder: Path):
    """Makes ``folder`` read-only for this process, root included (a read-only bind mount;
    permission bits do not stop root); returns the undo."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return lambda: folder.chmod(0o755)
    subprocess.run(["mount", "--bind", str(folder), str(folder)], check=True)
    subprocess.run(["mount", "-o", "remount,ro,bind", str(folder)], check=True)
    return lambda: subprocess.run(["umount", str(folder)], check=True)


@case
def render_read_only_out(f: Fixtures):
    out = f.scratch("read_only")
    return Attempt(
        urhead("render", f.avatar, "--out", out / "render"),
        names=str(out),
        cleanup=read_only_folder(out),
    )


@case
def fit_read_only_out(f: Fixtures):
    out = f.scratch("read_only_fit")
    return Attempt(
        urhead("fit", f.subject, "--out", out / "fit", *FIT_ARGS),
        names=str(out),
        cleanup=read_only_folder(out),
    )


@case
def fit_over_finished_fit(f: Fixtures):
    out = f.copy(f.avatar_fit, "rerun_finished")
    before = (out / "avatar" / "maps.npy").read_bytes()

    def check(proc):
        return "ok" if (out / "avatar" / "maps.npy").read_bytes() == before else "silent"

    return Attempt(
        urhead("fit", f.other_subject, "--out", out, *FIT_ARGS), names="--force", check=check
    )


@case
def stale_temporaries_of_dead_process(f: Fixtures):
    out = f.scratch("stale")
    dead = 2**22 + 12345  # above the default pid_max: no such process
    stale = [out / f".checkpoint.tmp-{dead}", out / f".avatar.tmp-{dead}"]
    for p in stale:
        p.mkdir()
        (p / "maps.npy").write_bytes(b"\0" * 1000)

    def check(proc):
        return "silent" if any(p.exists() for p in stale) else "ok"

    return Attempt(
        urhead("fit", f.subject, "--out", out, *FIT_ARGS), check=check, expect_success=True
    )


@case
def consistent_file_modes(f: Fixtures):
    out = f.scratch("modes")

    def check(proc):
        modes = {p.name: p.stat().st_mode & 0o777 for p in (out / "avatar").iterdir()}
        return "ok" if len(set(modes.values())) == 1 else "silent"

    return Attempt(
        urhead("fit", f.subject, "--out", out, *FIT_ARGS), check=check, expect_success=True
    )


@case
def synth_damaged_cache(f: Fixtures):
    s = f.copy(f.subject, "synth_cache")
    image = s / first_frame(s, "train")["file_path"]
    truncate_body(image)
    return Attempt(
        urhead("synth", "--out", s, "--resolution", 64, *SUBJECT_ARGS),
        names=image.name,
        check=lambda proc: "ok" if decodes(image) else "silent",
    )


@case
def npz_driver_not_zip(f: Fixtures):
    d = f.scratch("driver_not_zip")
    (d / "driver.npz").write_bytes(b"not a zip")
    return Attempt(
        urhead("reenact", f.avatar, "--driver", d / "driver.npz", "--out", d / "r.mp4"),
        names="driver.npz",
    )


@case
def eval_test_image_body_corrupt(f: Fixtures):
    s = f.copy(f.subject, "eval_corrupt")
    image = s / first_frame(s, "test")["file_path"]
    truncate_body(image)
    return Attempt(urhead("eval", f.avatar, "--subject", s, "--no-stlpips"), names=image.name)


# --- processes -----------------------------------------------------------------------


def concurrent_fits(f: Fixtures):
    out = f.scratch("concurrent")
    argv = urhead("fit", f.subject, "--out", out, *FIT_ARGS)
    procs = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    results = [(p, *p.communicate()) for p in procs]
    codes = sorted(p.returncode for p, *_ in results)
    if codes == [0, 0]:
        return "silent", "both fits into one --out exited 0"
    if any("Traceback" in err for *_, err in results):
        return "traceback", "a traceback"
    failed = next(err for p, _, err in results if p.returncode)
    return ("clean error" if codes[0] == 0 else "silent"), failed.strip().splitlines()[-1]


def ctrl_c(f: Fixtures):
    out = f.scratch("ctrl_c")
    argv = urhead("fit", f.subject, "--out", out, *FIT_ARGS[:-1], "--checkpoint-every", "5")
    argv[argv.index("20")] = "100000"
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # Interrupted once a checkpoint exists: the message must say how to continue from it.
    deadline = time.monotonic() + 300
    while not (out / "checkpoint").is_dir() and time.monotonic() < deadline:
        time.sleep(0.5)
    time.sleep(1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    message = [line for line in err.splitlines() if "interrupted" in line]
    if "Traceback" in err:
        return "traceback", f"{len(err.splitlines())} lines"
    if proc.returncode < 0:
        return "crash", f"signal {-proc.returncode}"
    ok = message and "--resume" in message[0]
    return ("clean error" if ok else "unnamed"), (message or ["(no message)"])[0]


SPECIAL = {"concurrent_fits": concurrent_fits, "ctrl_c": ctrl_c}


# --- running ------------------------------------------------------------------------


def classify(attempt: Attempt, proc) -> str:
    err = proc.stderr
    if proc.returncode < 0:
        return "crash"
    if "Traceback" in err:
        return "traceback"
    if proc.returncode == 0:
        verdict = attempt.check(proc) if attempt.check else None
        return verdict or ("ok" if attempt.expect_success else "silent")
    if attempt.expect_success:
        return "silent" if "error:" in err else "crash"
    if attempt.broken_after_failure and broken_outputs(attempt.broken_after_failure):
        return "half-written"
    if WORK_MARKER in err:
        return "late error"
    if attempt.names and attempt.names not in err:
        return "unnamed"
    return "clean error"


def message(proc) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    if proc.returncode < 0:
        return f"signal {-proc.returncode}"
    if "Traceback" in proc.stderr:
        return lines[-1][:100] if lines else ""
    errors = [line for line in lines if "error:" in line]
    if errors:
        return errors[-1][:100]
    out = [line for line in proc.stdout.splitlines() if line.strip()]
    return (out[-1] if out else "(exit 0)")[:100]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "urhead-attack")
    parser.add_argument("--only", default=None, help="comma-separated case names")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    fixtures = Fixtures(args.work)
    names = [*CASES, *SPECIAL]
    if args.only:
        names = [n for n in names if n in args.only.split(",")]
    counts = collections.Counter()
    env = {**os.environ, "PYTHONPATH": os.environ.get("PYTHONPATH", "")}
    for name in names:
        if name in SPECIAL:
            kind, text = SPECIAL[name](fixtures)
        else:
            attempt = CASES[name](fixtures)
            if attempt is None:
                print(f"{name:42s} skipped", flush=True)
                continue
            try:
                proc = subprocess.run(
                    attempt.argv,
                    capture_output=True,
                    text=True,
                    env={**env, **attempt.env},
                    timeout=600,
                    errors="replace",
                )
                kind, text = classify(attempt, proc), message(proc)
            finally:
                if attempt.cleanup:
                    attempt.cleanup()
        counts[kind] += 1
        print(f"{name:42s} {kind:12s} {text}", flush=True)
    print()
    print(", ".join(f"{k}: {v}" for k, v in sorted(counts.items())), f"(of {sum(counts.values())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
