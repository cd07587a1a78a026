"""Leaving out what a scene does not need: the scene analysis tells a closed mouth, still
eyes and a surface with nothing off it from their opposites; a head without the mouth's
faces and atlas rows renders what the full one does wherever they are not seen; a fit
leaves each part out only where the scene lacks it, says why in avatar.json, and --keep
forces it back."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from urhead.camera import Camera
from urhead.cli import build_parser
from urhead.config import FitConfig
from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.errors import InvalidArgumentError
from urhead.head import procedural_head
from urhead.head.leave_out import leave_out_faces, region_faces
from urhead.model import load_avatar
from urhead.model.avatar import Avatar
from urhead.model.initial_maps import initial_maps, texel_surface
from urhead.model.map_layout import MapLayout
from urhead.ops import rasterize, texture
from urhead.train.command import fit_config
from urhead.train.scene import (
    EYE_MOTION_RAD,
    MOUTH_REGIONS,
    SceneMeasures,
    analyse_scene,
    choose_parts,
)
from urhead.train.trainer import Trainer

LACKING = SynthConfig(
    frames=40,
    resolution=128,
    seed=3,
    samples_per_side=1,
    edge_samples_per_side=1,
    test_last=4,
    mouth="closed",
    gaze="fixed",
    hair="none",
)
"""A subject without the three parts: closed mouth, still eyes, nothing off the surface."""
HAVING = replace(LACKING, mouth="talking", gaze="moving", hair="shell")
"""The same subject with all three."""

SMALL_FIT = FitConfig(
    iterations=20,
    uv_resolution=64,
    initial_gaussians=300,
    max_gaussians=450,
    sample_every=10,
    sample_cap=60,
    error_grid=32,
    color_init_frames=2,
    eval_every_seconds=1e9,
    eval_frames=1,
    checkpoint_every=1000,
    refine_steps=0,
    refine_full_steps=0,
    gaussian_offset=True,
)


@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


@pytest.fixture(scope="module")
def subjects(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    return {
        name: load_subject(synthesize(root / name, config, progress=False))
        for name, config in (("lacking", LACKING), ("having", HAVING))
    }


@pytest.fixture(scope="module")
def measures(subjects, head):
    return {
        name: analyse_scene(subject.train, head, subject.has_normals)
        for name, subject in subjects.items()
    }


def test_analysis_tells_each_part_from_its_absence(measures):
    lacking, having = measures["lacking"], measures["having"]
    assert lacking.mouth_frames == 0 and having.mouth_frames > 0
    assert having.mouth_pixels_max > 4 * lacking.mouth_pixels_max
    assert lacking.eye_spread < EYE_MOTION_RAD < having.eye_spread
    assert 5 * lacking.off_surface_fraction < having.off_surface_fraction
    assert lacking.has_normals and having.has_normals
    for m in (lacking, having):
        assert m.frames_analysed == len(LACKING_TRAIN_ROWS)


LACKING_TRAIN_ROWS = range(LACKING.frames - LACKING.test_last)


def test_parts_follow_the_scene_and_keep(measures):
    lacking = choose_parts(measures["lacking"], SMALL_FIT)
    having = choose_parts(measures["having"], SMALL_FIT)
    for part in ("mouth", "eyes"):
        assert not lacking[part].used and having[part].used
        assert lacking[part].reason and having[part].reason
    # The offset map E is kept without content off the surface too (it also fits the
    # silhouette the tracked surface misses); the analysis reports the share it measured.
    assert lacking["offsets"].used and having["offsets"].used
    assert "beyond the mesh's reach" in lacking["offsets"].reason
    kept = choose_parts(measures["lacking"], replace(SMALL_FIT, keep="mouth"))
    assert kept["mouth"].used and not kept["eyes"].used
    assert "--keep mouth" in kept["mouth"].reason
    assert all(
        choose_parts(measures["lacking"], replace(SMALL_FIT, keep="all"))[p].used
        for p in ("mouth", "eyes")
    )
    # A part the configuration switches off stays off, whatever the scene.
    off = choose_parts(measures["having"], replace(SMALL_FIT, gaussian_offset=False))
    assert not off["offsets"].used
    no_normals = replace(measures["having"], has_normals=False)
    assert not choose_parts(no_normals, SMALL_FIT)["normals"].used


def test_keep_is_a_generated_option_and_checked():
    parser = build_parser()
    args = parser.parse_args(["fit", "subject", "--out", "x", "--keep", "mouth,eyes"])
    assert fit_config(args).keep == "mouth,eyes"
    with pytest.raises(InvalidArgumentError, match="teeth"):
        FitConfig(keep="mouth,teeth")
    with pytest.raises(InvalidArgumentError, match="offsets"):  # never left out: nothing to keep
        FitConfig(keep="offsets")


def test_measures_round_trip_through_a_checkpoint_dict(measures):
    m = measures["having"]
    from dataclasses import asdict

    assert SceneMeasures.from_dict(json.loads(json.dumps(asdict(m)))) == m


def test_kept_head_samples_the_full_atlas_texels(head):
    """The window of rows holds, for every point of a kept face, what the full atlas
    holds there: the maps are the same texels, only cropped."""
    resolution = 64
    dropped = region_faces(head, MOUTH_REGIONS)
    kept = leave_out_faces(head, dropped, resolution)
    assert (
        kept.head.num_faces
        == head.num_faces - int(dropped.sum())
        == (head.num_faces - kept.faces_left_out)
    )
    assert kept.head.num_vertices == head.num_vertices
    height, width = kept.map_size
    assert width == resolution and resolution - height >= 5  # the mouth band is gone
    maps = torch.rand(resolution, resolution, 5, generator=torch.Generator().manual_seed(0))
    window = maps[kept.first_row : kept.first_row + height].contiguous()
    rng = np.random.default_rng(0)
    bary = rng.dirichlet(np.ones(3), size=kept.head.num_faces)
    full_uv = np.einsum("fk,fkc->fc", bary, head.uv_coords[head.uv_faces[~dropped]])
    kept_uv = np.einsum("fk,fkc->fc", bary, kept.head.uv_coords[kept.head.uv_faces])
    expected = texture(maps, torch.from_numpy(full_uv).float())
    got = texture(window, torch.from_numpy(kept_uv).float())
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=0)


def test_a_head_without_the_mouth_renders_the_same_closed_mouth(head):
    """With the mouth closed, the head without the mouth's faces and rows renders what the
    full head does, but at the few pixels those faces were seen (between the lips)."""
    resolution = 64
    dropped = region_faces(head, MOUTH_REGIONS)
    kept = leave_out_faces(head, dropped, resolution)
    layout = MapLayout(1, gaussians=False)
    full = _mesh_avatar(head, layout, resolution)
    generator = torch.Generator().manual_seed(1)
    full.maps[..., layout.color] += 0.2 * torch.rand(*full.maps.shape[:2], 12, generator=generator)
    small = replace(full, head=kept.head)
    small.maps = full.maps[kept.first_row : kept.first_row + kept.map_size[0]].contiguous()
    cam = Camera.look_at(
        (0.0, 0.0, 0.6), (0.0, -0.03, 0.0), fov_y_degrees=20.0, width=96, height=96
    )
    params = full.split_params(full.frame_params[0])
    a = full.render(params, cam, gaussians=False).image
    b = small.render(params, cam, gaussians=False).image
    verts, _ = full.skin(params)
    tri = rasterize(verts, full.tables().faces, cam).tri_id
    seen = (tri >= 0) & torch.from_numpy(dropped)[tri.clamp_min(0).long()]
    near = torch.nn.functional.max_pool2d(seen[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert (tri >= 0).sum() > 1000 and int(near.sum()) < 40
    torch.testing.assert_close(b[~near], a[~near], atol=1e-5, rtol=0)


def _mesh_avatar(head, layout: MapLayout, resolution: int) -> Avatar:
    avatar = Avatar(
        head=head,
        layout=layout,
        maps=torch.zeros(1, 1, layout.channels),
        gaussian_uv=torch.zeros(0, 2),
        gaussian_face=torch.zeros(0, dtype=torch.int64),
        gaussian_bary=torch.zeros(0, 3),
        shape=torch.zeros(5),
        static_offset=None,
        timesteps=torch.tensor([0]),
        frame_params=torch.zeros(1, 10 + 18),
        background=torch.ones(3),
    )
    t = avatar.tables()
    raster = texel_surface(head, resolution)
    avatar.maps = initial_maps(layout, resolution, t.lbs.v_template, t.faces, raster, None, 0.004)
    return avatar


def _fit(subject, head, config, out):
    Trainer(subject, head, config, out, progress=False).run()
    avatar = load_avatar(out / "avatar")
    scene = json.loads((out / "avatar" / "avatar.json").read_text())["scene"]
    return avatar, scene


def _eye_rows(avatar):
    start = avatar.num_expr + 9
    return avatar.frame_params[:, start : start + 6]


def test_fit_leaves_out_what_the_scene_lacks_and_keep_forces_it_back(subjects, head, tmp_path):
    avatar, scene = _fit(subjects["lacking"], head, SMALL_FIT, tmp_path / "lean")
    assert {p for p, c in scene["parts"].items() if not c["used"]} >= {"mouth", "eyes"}
    assert avatar.maps.shape[0] < avatar.maps.shape[1] == SMALL_FIT.uv_resolution
    assert avatar.head.num_faces < head.num_faces
    assert avatar.layout.offsets
    assert torch.equal(_eye_rows(avatar), _eye_rows(avatar)[:1].expand_as(_eye_rows(avatar)))
    full, scene = _fit(subjects["lacking"], head, replace(SMALL_FIT, keep="all"), tmp_path / "kept")
    assert all(scene["parts"][p]["used"] for p in ("mouth", "eyes"))
    assert tuple(full.maps.shape[:2]) == (SMALL_FIT.uv_resolution,) * 2
    assert full.head.num_faces == head.num_faces and full.layout.offsets
    assert _eye_rows(full).std(0).max() > 0


def test_a_scene_that_has_each_part_keeps_it(subjects, head, tmp_path):
    avatar, scene = _fit(subjects["having"], head, SMALL_FIT, tmp_path / "fit")
    assert all(scene["parts"][p]["used"] for p in ("mouth", "eyes", "offsets"))
    assert tuple(avatar.maps.shape[:2]) == (SMALL_FIT.uv_resolution,) * 2
    assert avatar.head.num_faces == head.num_faces and avatar.layout.offsets
    assert _eye_rows(avatar).std(0).max() > 0
