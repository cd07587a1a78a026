"""The background colour: ``--background`` parsing, detection from the pixels outside the
masks, a requested colour checked against the data, and fits, eval and render of VHAP
exports on white and black (mono and multi-view) with no data flags."""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, replace
from types import SimpleNamespace

import pytest
import torch

from urhead.cli import main
from urhead.data import DatasetError, load_subject
from urhead.data.background import (
    DEFAULT_BACKGROUND,
    colour_name,
    detect_background,
    parse_background,
    subject_background,
)
from urhead.data.synth.subject import GENERATOR_VERSION, SynthConfig
from urhead.errors import InvalidArgumentError
from vhap_fixtures import write_vhap_export

TINY_FIT = [
    "--preset", "quick", "--iterations", "2", "--uv-resolution", "32",
    "--initial-gaussians", "40", "--max-gaussians", "60", "--sample-every", "100",
    "--eval-frames", "1", "--color-init-frames", "1", "--quiet",
]  # fmt: skip


@pytest.mark.parametrize(
    "text, colour",
    [
        ("white", (1.0, 1.0, 1.0)),
        ("BLACK", (0.0, 0.0, 0.0)),
        ("255,0,51", (1.0, 0.0, 0.2)),
        (" 0 , 127.5 , 255 ", (0.0, 0.5, 1.0)),
    ],
)
def test_parse_background(text, colour):
    assert parse_background(text) == pytest.approx(colour)


@pytest.mark.parametrize("text", ["red", "256,0,0", "1,2", "-1,0,0", "1.2.3,0,0", ""])
def test_parse_background_rejects(text):
    with pytest.raises(InvalidArgumentError, match="--background must be white, black or R,G,B"):
        parse_background(text)


def test_colour_names():
    assert colour_name((1.0, 1.0, 1.0)) == "white" and colour_name(torch.zeros(3)) == "black"
    assert colour_name((0.2, 0.4, 1.0)) == "51,102,255"


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")

    def export(name, **kwargs):
        return write_vhap_export(root / name, num_vertices=None, **kwargs)

    return SimpleNamespace(
        white=export("white", num_timesteps=5),
        black=export("black", num_timesteps=5, background="black"),
        multi=export("multi", num_timesteps=4, cameras=(0, 1, 2), background="black"),
    )


@pytest.mark.parametrize("name, colour", [("white", (1.0, 1.0, 1.0)), ("black", (0.0, 0.0, 0.0))])
def test_detection_finds_the_exported_colour(exports, name, colour):
    subject = load_subject(getattr(exports, name))
    found = detect_background(subject.train)
    assert found.colour == colour and found.uniform == 1.0
    assert found.frames == len(subject.train) and found.pixels > 100 * found.frames
    assert torch.equal(subject_background(subject), torch.tensor(colour))


def test_a_requested_colour_the_data_contradicts_is_an_error(exports):
    subject = load_subject(exports.black)
    with pytest.raises(DatasetError, match=r"black: --background white contradicts the data: "
                       r"its background is black \(median of \d+ pixels"):  # fmt: skip
        subject_background(subject, "white")
    near = (3 / 255, 0.0, 0.02)  # within the tolerance: taken as given
    assert torch.allclose(subject_background(subject, near), torch.tensor(near))


def _frames(images, masks):
    return [SimpleNamespace(image=i, mask=m) for i, m in zip(images, masks, strict=True)]


def test_no_background_pixels_falls_back_with_a_log_line(caplog):
    subject = SimpleNamespace(
        root="full", train=_frames([torch.rand(8, 8, 3)] * 2, [torch.ones(8, 8)] * 2), test=[]
    )
    with caplog.at_level(logging.INFO, logger="urhead.data"):
        assert torch.equal(subject_background(subject), torch.tensor(DEFAULT_BACKGROUND))
    assert "no pixels outside the masks" in caplog.text and "default white" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="urhead.data"):
        assert torch.equal(subject_background(subject, "black"), torch.zeros(3))
    assert "no pixels outside the masks to check --background black" in caplog.text


def test_a_background_of_many_colours_is_logged(caplog):
    image = torch.zeros(8, 8, 3)
    image[:, 5:] = 1.0  # 3/8 of the background white, the rest black
    subject = SimpleNamespace(root="mixed", train=_frames([image], [torch.zeros(8, 8)]), test=[])
    with caplog.at_level(logging.INFO, logger="urhead.data"):
        assert torch.equal(subject_background(subject), torch.zeros(3))
    assert "only 62% of the pixels outside the masks" in caplog.text


def test_black_export_is_fitted_and_scored_on_black(exports, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(exports.black), "--out", str(out), *TINY_FIT]) == 0
    meta = json.loads((out / "avatar" / "avatar.json").read_text())
    assert meta["background"] == [0.0, 0.0, 0.0]
    assert meta["metrics"]["background"] == [0.0, 0.0, 0.0]
    assert meta["config"]["background"] == "auto"
    capsys.readouterr()

    assert main(["eval", str(out / "avatar"), "--json", str(tmp_path / "e.json")]) == 0
    assert json.loads((tmp_path / "e.json").read_text())["background"] == [0.0, 0.0, 0.0]
    assert main(["eval", str(out / "avatar"), "--background", "white"]) == 1
    assert "--background white contradicts the data" in capsys.readouterr().err
    assert main(["render", str(out / "avatar"), "--out", str(tmp_path / "r"), "--orbit", "0",
                 "--orbit-steps", "2", "--background", "0,255,0"]) == 0  # fmt: skip

    refused = tmp_path / "refused"
    assert main(["fit", str(exports.black), "--out", str(refused), "--background", "white"]) == 1
    err = capsys.readouterr().err
    assert str(exports.black) in err and "contradicts the data" in err
    assert not refused.exists()


def test_eval_on_other_data_than_the_avatar_was_fitted_on_is_refused(exports, tmp_path, capsys):
    out = tmp_path / "fit"
    assert main(["fit", str(exports.white), "--out", str(out), *TINY_FIT]) == 0
    assert json.loads((out / "avatar" / "avatar.json").read_text())["background"] == [1.0] * 3
    capsys.readouterr()
    args = ["eval", str(out / "avatar"), "--subject", str(exports.black)]
    assert main(args) == 1
    assert "the avatar's recorded background white contradicts" in capsys.readouterr().err
    assert main([*args, "--background", "black", "--json", str(tmp_path / "e.json")]) == 0


def test_multiview_export_fits_on_train_and_scores_test(exports, tmp_path):
    out = tmp_path / "fit"
    assert main(["fit", str(exports.multi), "--out", str(out), *TINY_FIT]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    subject = load_subject(exports.multi)
    assert metrics["held_out_frames"] == len(subject.test) == 3  # every camera, last timestep
    assert metrics["background"] == [0.0, 0.0, 0.0]


def test_synth_background_option(tmp_path):
    tiny = SynthConfig(
        frames=4, resolution=32, difficulty="easy", samples_per_side=1, edge_samples_per_side=1
    )
    black = replace(tiny, background=(0.0, 0.0, 0.0))
    assert main(["synth", "--out", str(tmp_path / "b"), "--frames", "4", "--resolution", "32",
                 "--difficulty", "easy", "--samples", "1", "--edge-samples", "1",
                 "--background", "black", "--quiet"]) == 0  # fmt: skip
    subject = load_subject(tmp_path / "b")
    assert detect_background(subject.train).colour == (0.0, 0.0, 0.0)
    assert json.loads((tmp_path / "b" / "synthetic.json").read_text())["cache_key"] == (
        black.cache_key()
    )
    # a white (talking, metric) subject keeps the cache key it had before those fields existed
    later = ("background", "motion", "length_unit")
    fields = {k: v for k, v in asdict(tiny.resolved()).items() if k not in later}
    before = json.dumps({"generator_version": GENERATOR_VERSION, **fields}, sort_keys=True)
    assert tiny.cache_key() == hashlib.sha256(before.encode()).hexdigest()[:16]
