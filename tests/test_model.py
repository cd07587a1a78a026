"""The avatar model: map layout, rendering and its gradients, construction helpers, the
avatar directory (round trip, bad input, atomic replacement) and UV sampling."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from urhead.camera import Camera
from urhead.head import procedural_head
from urhead.head.mesh import vertex_normals
from urhead.model import (
    Avatar,
    ErrorAccumulator,
    MapLayout,
    UvSurface,
    load_avatar,
    save_avatar,
    set_gaussians,
)
from urhead.model.initial_maps import fill_holes, initial_maps, texel_surface
from urhead.model.io import write_directory_atomically
from urhead.ops import TextureGather, nearest_covered_pixel


@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


def make_avatar(head, gaussians=True, sh_degree=1, resolution=32, count=200) -> Avatar:
    layout = MapLayout(sh_degree, gaussians)
    e = 10
    avatar = Avatar(
        head=head,
        layout=layout,
        maps=torch.zeros(1, 1, layout.channels),
        gaussian_uv=torch.zeros(0, 2),
        gaussian_face=torch.zeros(0, dtype=torch.int64),
        gaussian_bary=torch.zeros(0, 3),
        shape=torch.zeros(5),
        static_offset=None,
        timesteps=torch.tensor([3, 7]),
        frame_params=torch.zeros(2, e + 18),
        background=torch.ones(3),
    )
    t = avatar.tables()
    raster = texel_surface(head, resolution)
    avatar.maps = initial_maps(layout, resolution, t.lbs.v_template, t.faces, raster, None, 0.004)
    if gaussians:
        surface = UvSurface(head.uv_coords, head.uv_faces)
        set_gaussians(avatar, surface, surface.uniform(count, np.random.default_rng(0)))
    return avatar


def camera(size=48) -> Camera:
    return Camera.look_at(
        (0.0, 0.0, 0.7), (0.0, 0.0, 0.0), fov_y_degrees=26.0, width=size, height=size
    )


def test_layout_channels_and_split():
    full, mesh_only = MapLayout(3, True), MapLayout(0, False)
    assert full.channels == 56 and mesh_only.channels == 7
    samples = torch.arange(56.0).reshape(1, 56)
    parts = full.split(samples)
    assert parts.color.shape == (1, 48) and parts.normal.tolist() == [[48.0, 49.0, 50.0]]
    assert parts.displacement.item() == 51 and parts.opacity.item() == 52
    assert parts.scale.tolist() == [[53.0, 54.0, 55.0]]
    assert mesh_only.split(torch.zeros(2, 7)).opacity is None
    with pytest.raises(AttributeError):
        mesh_only.opacity  # noqa: B018
    rates = full.channel_rates(1.0, 2.0, 3.0, 4.0, 5.0)
    assert rates[:48].eq(1).all() and rates[51] == 3 and rates[52] == 4 and rates[53:].eq(5).all()


def test_render_gradients_reach_every_map_and_the_frame(head):
    avatar = make_avatar(head)
    avatar.maps.requires_grad_(True)
    params = avatar.frame(7)
    params = type(params)(*(p.clone().requires_grad_(True) for p in params))
    gather = TextureGather(avatar.maps)
    out = avatar.render(params, camera(), gather=gather, normals=True)
    assert out.image.shape == (48, 48, 3) and out.gaussians is not None
    assert out.mesh.normals.shape == (out.mesh.pixels.numel(), 3)
    (out.image.sum() + out.mesh.normals.sum()).backward()
    grad = gather.gradient().coalesce()
    per_channel = grad.values().abs().sum(0)
    layout = avatar.layout
    for name, channels in [
        ("C", per_channel[layout.color]),
        ("N", per_channel[layout.normal]),
        ("D", per_channel[layout.displacement : layout.displacement + 1]),
        ("O", per_channel[layout.opacity : layout.opacity + 1]),
        ("S", per_channel[layout.scale]),
    ]:
        assert torch.isfinite(channels).all() and channels.sum() > 0, name
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in params)
    assert avatar.maps.grad is None  # the gather took it


def test_gathered_and_autograd_map_gradients_agree(head):
    avatar = make_avatar(head)
    cam = camera()
    avatar.maps.requires_grad_(True)
    avatar.render(avatar.frame(3), cam).image.square().sum().backward()
    reference = avatar.maps.grad.coalesce().to_dense()
    avatar.maps.grad = None
    gather = TextureGather(avatar.maps)
    avatar.render(avatar.frame(3), cam, gather=gather).image.square().sum().backward()
    assert torch.allclose(gather.gradient().to_dense(), reference, atol=1e-5, rtol=1e-4)


def test_mesh_only_render_has_no_gaussian_layer(head):
    avatar = make_avatar(head, gaussians=False)
    with torch.no_grad():
        out = avatar.render(avatar.frame(3), camera())
    assert out.gaussians is None and torch.equal(out.image, out.mesh.image)
    covered = out.mesh.alpha > 0.99
    assert covered.any() and (~covered).any()
    assert torch.allclose(out.image[out.mesh.alpha == 0], torch.ones(3))


def test_unknown_timestep_is_a_key_error(head):
    avatar = make_avatar(head, gaussians=False)
    with pytest.raises(KeyError, match="timestep 4"):
        avatar.frame(4)


def test_avatar_directory_round_trip_and_errors(head, tmp_path):
    avatar = make_avatar(head)
    avatar.frame_params += torch.randn(
        avatar.frame_params.shape, generator=torch.Generator().manual_seed(1)
    )
    path = save_avatar(avatar, tmp_path / "a", extra={"note": "x"})
    loaded = load_avatar(path)
    for name in (
        "maps",
        "gaussian_uv",
        "gaussian_face",
        "gaussian_bary",
        "frame_params",
        "timesteps",
    ):
        assert torch.equal(getattr(loaded, name), getattr(avatar, name)), name
    assert loaded.layout == avatar.layout
    assert json.loads((path / "avatar.json").read_text())["note"] == "x"

    broken = tmp_path / "broken"
    shutil.copytree(path, broken)
    (broken / "gaussians.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"gaussians\.npz"):
        load_avatar(broken)
    shutil.copytree(path, broken, dirs_exist_ok=True)
    np.save(broken / "maps.npy", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match=r"maps\.npy"):
        load_avatar(broken)
    with pytest.raises(FileNotFoundError, match=r"avatar\.json"):
        load_avatar(tmp_path / "nothing")


def test_directory_write_is_all_or_nothing(tmp_path):
    target = tmp_path / "d"
    write_directory_atomically(target, lambda tmp: (tmp / "a.txt").write_text("old"))

    def fails(tmp):
        (tmp / "a.txt").write_text("new")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        write_directory_atomically(target, fails)
    assert (target / "a.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["d"]  # no temporary left behind


def test_fill_holes_keeps_observed_and_fills_from_nearby():
    values = torch.zeros(16, 16, 1)
    weight = torch.zeros(16, 16)
    values[2, 3] = 5.0
    weight[2, 3] = 1.0
    values[12, 12] = -1.0
    weight[12, 12] = 1.0
    out = fill_holes(values, weight)
    assert out[2, 3, 0] == 5 and out[12, 12, 0] == -1
    # holes take their neighbourhood, blending smoothly (no blocks) in between
    assert out[1, 2, 0] > 4.5 and out[13, 13, 0] < -0.5
    assert out.min() >= -1 and out.max() <= 5  # a convex blend of what was observed
    steps = (out[1:] - out[:-1]).abs().max()
    assert steps < 1.0


def test_vertex_normals_of_a_tetrahedron_point_outwards():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=torch.int32)
    n = vertex_normals(verts, faces)
    centre = verts.mean(0)
    assert ((verts - centre) * n).sum(-1).gt(0).all()
    assert torch.allclose(n.norm(dim=-1), torch.ones(4))


def test_error_driven_sampling_follows_the_error(head):
    surface = UvSurface(head.uv_coords, head.uv_faces)
    rng = np.random.default_rng(0)
    on_atlas = surface.uniform(4000, rng)
    acc = ErrorAccumulator(16)
    hot = on_atlas[(on_atlas[:, 0] < 0.5) & (on_atlas[:, 1] > 0.5)]
    for uv, error in ((on_atlas, 0.01), (hot, 10.0)):
        # A 1 × P frame whose every pixel is covered and sees one of the UV points.
        n = len(uv)
        target = torch.zeros(1, n, 3)
        image = target + torch.tensor([error, 0.0, 0.0])
        acc.add(image, target, torch.ones(1, n), torch.arange(n), torch.from_numpy(uv))
    drawn = acc.sample(500, surface, rng)
    assert 0 < len(drawn) <= 500
    inside = (drawn[:, 0] < 0.5) & (drawn[:, 1] > 0.5)
    assert inside.mean() > 0.9
    face, _ = surface.locate(drawn)
    assert (face >= 0).all()
    acc.reset()
    assert len(acc.sample(10, surface, rng)) == 0  # no error, nothing drawn


def test_nearest_covered_pixel_charges_misses_to_the_closest_covered_pixel():
    covered = torch.zeros(6, 7, dtype=torch.bool)
    covered[1, 1] = covered[4, 5] = True
    nearest = nearest_covered_pixel(covered).reshape(6, 7)
    assert nearest[1, 1] == 1 * 7 + 1 and nearest[4, 5] == 4 * 7 + 5
    assert nearest[0, 0] == 8 and nearest[5, 6] == 33


def test_offset_layout_adds_one_gaussian_channel_and_its_rate():
    layout = MapLayout(3, True, offsets=True)
    assert layout.channels == 57 and layout.offset == 56
    parts = layout.split(torch.arange(57.0).reshape(1, 57))
    assert parts.offset.tolist() == [56.0] and parts.scale.tolist() == [[53.0, 54.0, 55.0]]
    assert MapLayout(3, True).split(torch.zeros(1, 56)).offset is None
    with pytest.raises(ValueError, match="Gaussian branch"):
        MapLayout(3, False, offsets=True)
    with pytest.raises(AttributeError):
        MapLayout(3, True).offset  # noqa: B018
    rates = layout.channel_rates(1.0, 2.0, 3.0, 4.0, 5.0, offset=6.0, sh_rest=0.05)
    assert rates[:3].eq(1).all() and torch.allclose(rates[3:48], torch.tensor(0.05))
    assert rates[56] == 6 and rates[53:56].eq(5).all()


def test_offset_map_moves_gaussians_along_the_normal_only(head):
    avatar = make_avatar(head, count=50)
    offset_avatar = make_avatar(head, count=50)
    layout = MapLayout(1, True, offsets=True)
    maps = torch.cat([avatar.maps, torch.full((*avatar.maps.shape[:2], 1), 0.004)], -1)
    offset_avatar.layout, offset_avatar.maps = layout, maps
    cam = camera()
    with torch.no_grad():
        verts, rot = avatar.skin(avatar.frame(3))
        a = avatar.lift_gaussians(verts, rot, cam)
        b = offset_avatar.lift_gaussians(verts, rot, cam)
    step = b.means - a.means
    assert torch.allclose(step.norm(dim=-1), torch.full((50,), 0.004), atol=1e-6)
    w, x, y, z = a.quats.unbind(-1)  # the rotation's local z axis is the posed normal
    normal_z = torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)
    assert torch.allclose((step * normal_z).sum(-1), torch.full((50,), 0.004), atol=1e-6)
    assert torch.equal(a.scales, b.scales) and torch.equal(a.opacities, b.opacities)
    assert b.offset is not None and a.offset is None


def test_offset_avatar_round_trips_through_its_directory(head, tmp_path):
    avatar = make_avatar(head, count=20)
    avatar.layout = MapLayout(1, True, offsets=True)
    avatar.maps = torch.cat([avatar.maps, torch.rand(*avatar.maps.shape[:2], 1)], -1)
    loaded = load_avatar(save_avatar(avatar, tmp_path / "a"))
    assert loaded.layout == avatar.layout and torch.equal(loaded.maps, avatar.maps)


def test_sh_degree_argument_limits_the_bands_used(head):
    avatar = make_avatar(head, sh_degree=1, count=30)
    avatar.maps[..., 3:12] = 0.3  # only the degree-1 band
    cam = camera()
    with torch.no_grad():
        dc = avatar.render(avatar.frame(3), cam, sh_degree=0).image
        full = avatar.render(avatar.frame(3), cam).image
        avatar.maps[..., 3:12] = 0.0
        plain = avatar.render(avatar.frame(3), cam).image
    assert torch.equal(dc, plain) and not torch.equal(full, plain)


def test_shading_maps_scale_colour_with_the_surface_rotation(head):
    avatar = make_avatar(head, count=40)
    base = avatar.maps
    avatar.layout = MapLayout(1, True, shading=True)
    a = torch.zeros(*base.shape[:2], 9)
    a[..., 2] = 0.8  # gain 1 + 0.8·(R − I)_02: grows with a turn about y
    avatar.maps = torch.cat([base, a], -1)
    cam = camera()
    params = avatar.frame(3)
    turned = type(params)(*(p.clone() for p in params))
    turned.pose[1] = 0.3
    plain = make_avatar(head, count=40)
    with torch.no_grad():
        same = avatar.render(params, cam).image  # R = I: shading maps do nothing
        reference = plain.render(plain.frame(3), cam).image
        lit = avatar.render(turned, cam).image
        unlit = plain.render(turned, cam).image
    assert torch.allclose(same, reference, atol=1e-6)
    covered = (unlit - 1).abs().sum(-1) > 0.05  # head pixels, not background
    ratio = (lit[covered] / unlit[covered].clamp_min(1e-3)).mean()
    assert ratio == pytest.approx(1 + 0.8 * float(torch.sin(torch.tensor(0.3))), abs=0.03)


def test_silhouette_loss_is_the_coverage_error_and_moves_opacity_and_the_pose(head):
    """coverage = 1 − T·(1 − α_mesh) of the composite; the term is its mean absolute
    difference from the mask, zero against the avatar's own coverage, and its gradient
    reaches the opacity map and the frame's pose (through the antialiased silhouette)."""
    from types import SimpleNamespace

    from urhead.train.objective import coverage, silhouette_loss

    avatar = make_avatar(head)
    avatar.maps.requires_grad_(True)
    params = avatar.frame(7)
    params = type(params)(*(p.clone().requires_grad_(True) for p in params))
    gather = TextureGather(avatar.maps)
    out = avatar.render(params, camera(), gather=gather)
    cover = coverage(out)
    expected = 1 - out.gaussians.transmittance * (1 - out.mesh.alpha)
    assert torch.equal(cover, expected)
    assert 0 <= float(cover.detach().min()) <= float(cover.detach().max()) <= 1
    own = SimpleNamespace(mask=cover.detach())
    assert float(silhouette_loss(out, own).detach()) == 0
    empty = SimpleNamespace(mask=torch.zeros_like(cover))
    loss = silhouette_loss(out, empty)
    assert float(loss.detach()) == pytest.approx(float(cover.detach().mean()))
    loss.backward()
    opacity = gather.gradient().coalesce().values()[:, avatar.layout.opacity]
    assert opacity.abs().sum() > 0
    assert params.pose.grad is not None and params.pose.grad.abs().sum() > 0


def test_pixel_rays_are_kept_for_the_last_camera_only():
    from urhead.camera import Camera
    from urhead.model.avatar import PixelRays

    k = torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    camera = Camera(k, torch.eye(4), 8, 6)
    rays = PixelRays()
    first = rays(camera)
    assert first.shape == (48, 3)
    assert torch.allclose(first.norm(dim=-1), torch.ones(48))
    # Pixel (3, 2) has its centre half a pixel off the principal point (4, 3) each way.
    expected = torch.tensor([-0.05, -0.05, 1.0])
    assert torch.allclose(first[2 * 8 + 3], expected / expected.norm())
    assert rays(camera) is first
    smaller = rays(camera.resized(4, 3))
    assert smaller.shape == (12, 3)
    assert rays(camera) is not first and torch.equal(rays(camera), first)


def test_sampler_resamples_on_its_schedule_and_round_trips_its_state(head):
    from dataclasses import replace as with_options

    from urhead.config import FitConfig
    from urhead.model import GaussianSampler

    config = with_options(
        FitConfig(),
        iterations=20,
        uv_resolution=32,
        error_grid=8,
        sample_every=10,
        sample_cap=40,
        initial_gaussians=200,
        max_gaussians=230,
        prune_opacity=0.0,
    )
    avatar = make_avatar(head, count=200)
    sampler = GaussianSampler(config, head, avatar.num_gaussians)
    with torch.no_grad():
        render = avatar.render(avatar.frame(3), camera())
    frame = SimpleNamespace(image=torch.rand(48, 48, 3), mask=torch.ones(48, 48), camera=camera())
    sampler.observe(render, frame)
    assert sampler.accumulator.count.sum() > 0
    assert sampler.max_radius.shape == (200,) and sampler.max_radius.max() > 0

    restored = GaussianSampler(config, head, avatar.num_gaussians)
    restored.load_state(sampler.state())
    assert torch.equal(restored.accumulator.error, sampler.accumulator.error)
    assert torch.equal(restored.max_radius, sampler.max_radius)

    uv = avatar.gaussian_uv.clone()
    sampler.step_end(avatar, frame, 9)  # off the schedule: nothing moves
    assert torch.equal(avatar.gaussian_uv, uv)
    sampler.step_end(avatar, frame, 10)  # adds new ones where the error is, within budget
    grown = avatar.num_gaussians
    assert 200 < grown <= 230
    assert sampler.accumulator.count.sum() == 0 and sampler.max_radius.shape == (grown,)
    sampler.step_end(avatar, frame, 20)  # never after the last iteration
    assert avatar.num_gaussians == grown


def test_sampler_prunes_a_runaway_gaussian_seen_in_a_rejected_step(head):
    """A texel whose scale ran away puts a screen-filling Gaussian in the render; the guard
    rolls the maps back but not the Gaussian set, so the sampler drops it at once."""
    from dataclasses import replace as with_options

    from urhead.config import FitConfig
    from urhead.model import GaussianSampler

    config = with_options(FitConfig(), uv_resolution=32, initial_gaussians=200, max_gaussians=230)
    avatar = make_avatar(head, count=200)
    sampler = GaussianSampler(config, head, avatar.num_gaussians)
    frame = SimpleNamespace(image=torch.rand(48, 48, 3), mask=torch.ones(48, 48), camera=camera())
    with torch.no_grad():
        before = avatar.render(avatar.frame(3), camera())
    visible = torch.nonzero(before.gaussians.radii.amax(-1) > 0)[:, 0]
    assert len(visible) > 10
    assert sampler.prune_oversized(avatar, before, frame) == 0  # none too large: no change
    assert avatar.num_gaussians == 200

    sampler.max_radius = torch.arange(200, dtype=torch.int32)  # tags to follow the reorder
    runaway = int(visible[len(visible) // 2])
    u, v = avatar.gaussian_uv[runaway].tolist()
    r = avatar.maps.shape[0]
    with torch.no_grad():
        row, col = int((1 - v) * r), int(u * r)
        avatar.maps[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2, avatar.layout.scale] = 0.0
        render = avatar.render(avatar.frame(3), camera())  # σ = 1 m: fills the screen
    limit = config.prune_screen_fraction * 48
    oversized = render.gaussians.radii.amax(-1) > limit
    assert oversized[runaway]
    original_uv = avatar.gaussian_uv.clone()
    pruned = sampler.prune_oversized(avatar, render, frame)
    assert pruned == int(oversized.sum()) >= 1
    assert avatar.num_gaussians == 200 - pruned
    # Each kept Gaussian keeps its own recorded radius (here: its old index).
    old_index = sampler.max_radius.long()
    assert torch.equal(avatar.gaussian_uv, original_uv[old_index])
    assert not oversized[old_index].any() and runaway not in old_index.tolist()


def test_frozen_maps_are_looked_up_once_per_uv_tensor_until_edited(head):
    from urhead.ops import texture

    avatar = make_avatar(head)
    uv = avatar.gaussian_uv
    first = avatar.lookup_fixed(uv)
    assert torch.equal(first, texture(avatar.maps, uv))
    assert avatar.lookup_fixed(uv) is first  # kept: a frozen avatar's rows do not change
    with torch.no_grad():
        before = avatar.render(avatar.frame(3), camera()).image
    avatar.maps.mul_(0.5)  # an in-place edit bumps the maps' version: every row is stale
    edited = avatar.lookup_fixed(uv)
    assert edited is not first and torch.equal(edited, texture(avatar.maps, uv))
    uv.add_(0.01)  # the UV points themselves edited
    assert torch.equal(avatar.lookup_fixed(uv), texture(avatar.maps, uv))
    avatar.maps = avatar.maps * 2  # other maps
    assert torch.equal(avatar.lookup_fixed(uv), texture(avatar.maps, uv))
    with torch.no_grad():
        after = avatar.render(avatar.frame(3), camera()).image
    assert not torch.equal(before, after)  # the render saw the edits


def test_maps_in_training_are_never_kept(head):
    avatar = make_avatar(head)
    avatar.maps.requires_grad_(True)
    uv = avatar.gaussian_uv
    rows = avatar.lookup_fixed(uv)
    assert rows.requires_grad and avatar.lookup_fixed(uv) is not rows
    gather = TextureGather(avatar.maps)
    assert avatar.lookup_fixed(uv, gather) is not avatar.lookup_fixed(uv, gather)
    with torch.no_grad():
        # Mid-fit scoring: no gradient asked, but the maps are still being trained (an
        # optimiser may write them without bumping their version), so nothing is kept.
        assert avatar.lookup_fixed(uv) is not avatar.lookup_fixed(uv)
