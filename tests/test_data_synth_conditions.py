"""The conditions of synthetic subjects (light, hair, tracking noise): each option does what
it says, explicit options override the difficulty, and every resolved setting is in the
cache key."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from urhead.cli import build_parser
from urhead.data import load_subject
from urhead.data.synth.raytrace import raytrace
from urhead.data.synth.subject import (
    CONDITIONS,
    DIFFICULTIES,
    LIGHTS,
    SynthConfig,
    config_from_args,
    subject_camera,
    synthesize,
)
from urhead.head import load_head, procedural_head

TINY = SynthConfig(
    frames=2,
    resolution=64,
    seed=2,
    difficulty="easy",
    samples_per_side=1,
    edge_samples_per_side=1,
    test_last=1,
)


@pytest.fixture(scope="module")
def make(tmp_path_factory):
    """synthesize(TINY with ``changes``), each subject made once per module."""
    made = {}

    def subject(**changes):
        config = replace(TINY, **changes)
        key = config.cache_key()
        if key not in made:
            out = tmp_path_factory.mktemp("conditions") / key
            made[key] = load_subject(synthesize(out, config, progress=False))
        return made[key]

    return subject


def _frames(subject):
    return [*subject.train, *subject.test]


def _masks(subject):
    return torch.stack([f.mask for f in _frames(subject)]) > 0.5


def test_hard_is_the_default_subject_of_generator_version_2():
    assert DIFFICULTIES["hard"] == dict(
        max_yaw_deg=35.0,
        expression_scale=1.0,
        wrinkles=1.0,
        strands=2500,
        levels=2,
        light="key",
        hair="strands",
        tracking_noise=1.0,
    )
    hard = SynthConfig(difficulty="hard").resolved()
    assert (hard.light, hard.hair, hard.tracking_noise) == ("key", "strands", 1.0)


def test_the_default_is_a_plausible_capture_sharing_the_hard_performance():
    default = SynthConfig().resolved()
    assert (default.light, default.hair) == ("soft", "shell")
    assert 0 < default.tracking_noise < DIFFICULTIES["hard"]["tracking_noise"]
    shared = ("max_yaw_deg", "expression_scale", "wrinkles", "strands", "levels")
    assert all(DIFFICULTIES["default"][k] == DIFFICULTIES["hard"][k] for k in shared)


def test_explicit_conditions_override_the_difficulty():
    parse = build_parser().parse_args
    config = config_from_args(parse(["synth", "--out", "x", "--difficulty", "hard"]))
    assert config == SynthConfig(difficulty="hard").resolved()
    args = ["synth", "--out", "x", "--difficulty", "hard", "--light", "flat"]
    args += ["--hair", "none", "--tracking-noise", "0"]
    config = config_from_args(parse(args))
    assert (config.light, config.hair, config.tracking_noise) == ("flat", "none", 0.0)
    assert config.difficulty == "hard"
    partly = SynthConfig(difficulty="easy", hair="shell").resolved()
    assert (partly.light, partly.hair, partly.tracking_noise) == ("key", "shell", 0.5)


def test_cache_key_follows_the_resolved_conditions():
    base = SynthConfig(difficulty="hard")
    keys = {base.cache_key()}
    for change in ({"light": "soft"}, {"hair": "shell"}, {"tracking_noise": 0.5}):
        keys.add(replace(base, **change).cache_key())
    assert len(keys) == 4
    # Naming the difficulty's own value is the same subject.
    same = SynthConfig(difficulty="hard", light="key", hair="strands", tracking_noise=1)
    assert same.cache_key() == base.cache_key()
    assert set(CONDITIONS) <= set(vars(base.resolved()))


def test_bad_conditions_are_refused():
    for bad in ({"light": "sun"}, {"hair": "long"}, {"tracking_noise": -1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SynthConfig(**bad)


def test_zero_tracking_noise_writes_the_exact_parameters(make, tmp_path):
    subject = make(tracking_noise=0.0)
    truth = np.load(subject.root / "synthetic_ground_truth.npz")
    for frame in _frames(subject):
        t, flame = frame.timestep, frame.flame
        assert np.array_equal(flame["shape"], truth["shape"])
        assert np.array_equal(flame["expr"][0], truth["expr"][t])
        assert np.array_equal(flame["rotation"][0], truth["pose"][t, 0:3])
        assert np.array_equal(flame["jaw_pose"][0], truth["pose"][t, 6:9])
        assert np.array_equal(flame["translation"][0], truth["transl"][t])
    meta = json.loads((subject.root / "synthetic.json").read_text())
    assert meta["config"]["tracking_noise"] == 0.0
    assert meta["tracking_error"]["max_px"] == 0.0


def test_tracking_error_figures_grow_with_the_noise_scale(make):
    def error(scale):
        meta = json.loads((make(tracking_noise=scale).root / "synthetic.json").read_text())
        return meta["tracking_error"]

    small, large = error(0.5), error(1.0)
    assert 0 < small["mean_px"] < small["worst_frame_mean_px"] <= small["max_px"]
    # The noise is drawn once and scaled: the displacement is nearly proportional.
    assert large["mean_px"] == pytest.approx(2 * small["mean_px"], rel=0.1)
    assert large["mean_px_at_512"] == pytest.approx(large["mean_px"] * 512 / 64, rel=1e-3)


def _flame_silhouette(subject, frame) -> torch.Tensor:
    """The pixels the coarse FLAME mesh covers, skinned with the exact parameters."""
    head = load_head(subject.root / "head.npz")
    truth = np.load(subject.root / "synthetic_ground_truth.npz")
    t = frame.timestep
    verts = head.skin(
        shape=torch.from_numpy(truth["shape"]),
        expr=torch.from_numpy(truth["expr"][t]),
        pose=torch.from_numpy(truth["pose"][t]),
        transl=torch.from_numpy(truth["transl"][t]),
    ).verts[0]
    out = raytrace(verts.numpy(), head.faces, frame.camera, samples_per_side=1, shadows=False)
    return torch.from_numpy(out.alpha) > 0


def _off_surface_pixels(subject) -> int:
    """Foreground pixels more than a pixel away from the FLAME mesh's silhouette."""
    count = 0
    for frame in _frames(subject):
        flame = _flame_silhouette(subject, frame).float()[None, None]
        near = torch.nn.functional.max_pool2d(flame, 3, 1, 1)[0, 0] > 0
        count += int(((frame.mask > 0.5) & ~near).sum())
    return count


def test_hair_modes_add_geometry_off_the_flame_surface(make):
    none, shell, strands = (make(hair=h) for h in ("none", "shell", "strands"))
    areas = [int(_masks(s).sum()) for s in (none, shell, strands)]
    assert areas[0] < areas[1] <= areas[2]
    assert _off_surface_pixels(none) == 0
    assert 0 < _off_surface_pixels(shell) <= _off_surface_pixels(strands)
    # Only the hair differs: the exported parameters are the same.
    for a, b in zip(_frames(none), _frames(strands), strict=True):
        assert all(np.array_equal(a.flame[k], b.flame[k]) for k in a.flame)


def test_light_changes_the_shading_only(make):
    key, soft, flat = (make(light=name) for name in ("key", "soft", "flat"))
    assert torch.equal(_masks(key), _masks(flat)) and torch.equal(_masks(soft), _masks(flat))
    inside = _masks(flat) & (torch.stack([f.image for f in _frames(flat)]).mean(-1) > 0.05)

    def shading_spread(subject):
        """Spread of the log ratio to the flat image (which shows the albedo)."""
        ratio = torch.stack([f.image for f in _frames(subject)]).mean(-1)
        flat_lum = torch.stack([f.image for f in _frames(flat)]).mean(-1)
        return torch.log(ratio[inside].clamp_min(1e-3) / flat_lum[inside]).std()

    assert shading_spread(soft) < 0.7 * shading_spread(key)


@pytest.mark.parametrize("yaw_deg", [-30.0, 30.0])
def test_flat_light_shows_the_albedo_in_any_pose(yaw_deg):
    """A grey head under each light: flat gives one colour at every pixel, key and soft
    shade it (key the most)."""
    head = procedural_head(0)
    pose = torch.zeros(head.num_joints * 3)
    pose[1] = np.radians(yaw_deg)
    verts = head.skin(pose=pose).verts[0].numpy()
    camera = subject_camera(48)

    def render(name):
        out = raytrace(verts, head.faces, camera, light=LIGHTS[name], samples_per_side=1)
        return out.rgb[out.alpha == 1]

    # The default albedo (0.8) times the uniform ambient at every pixel.
    assert np.allclose(render("flat"), 0.8 * np.array(LIGHTS["flat"].ambient_up), atol=1e-5)
    assert render("key").std() > render("soft").std() > 0.02
