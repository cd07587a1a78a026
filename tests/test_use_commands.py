"""``urhead eval``, ``render`` and ``reenact`` on a small avatar: numbers agree with
:func:`evaluate_frames`, LPIPS plumbing with weight files on disk, videos are H.264 that
decodes back to the frames, orbits stay in the captured yaw range, and bad inputs fail
before anything is written."""

from __future__ import annotations

import itertools
import json
import shutil

import av
import cv2
import numpy as np
import pytest
import torch

from urhead.cli import main
from urhead.data import load_subject
from urhead.eval import RefineSettings, evaluate_frames
from urhead.eval.lpips import VARIANTS, load_lpips
from urhead.eval.metrics import frame_params
from urhead.model import load_avatar
from urhead.model.avatar import POSE_SIZE
from urhead.use.common import avatar_camera, bgr_uint8, open_avatar
from urhead.use.orbit import camera_up, default_orbit_angles, head_yaws
from urhead.use.panels import label_bar_height
from urhead.use.reenact import driven_params, load_driver
from use_avatar import make_use_avatar


@pytest.fixture(scope="module")
def use(tmp_path_factory):
    return make_use_avatar(tmp_path_factory.mktemp("use_commands"))


def read_video(path):
    """Decodes an MP4 with PyAV (FFmpeg), asserting it is H.264 in 4:2:0 (what browsers
    play); (H, W, 3) uint8 BGR frames."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        return [f.to_ndarray(format="bgr24") for f in container.decode(stream)]


def luma_psnr(a, b):
    """PSNR of the luma of two BGR images: what 4:2:0 video keeps at full resolution (its
    half-resolution chroma alone costs ~14 dB on these 64² noise-textured renders)."""
    ya, yb = (cv2.cvtColor(x, cv2.COLOR_BGR2YCrCb)[..., 0].astype(np.float64) for x in (a, b))
    return 10 * np.log10(255.0**2 / np.mean((ya - yb) ** 2))


def test_eval_matches_evaluate_frames(use, tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert main(["eval", str(use.avatar_dir), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "LPIPS-alex skipped" in printed and "PSNR in mask (dB)" in printed
    assert "PSNR full image (dB)" in printed and "off (--refine-flame)" in printed
    result = json.loads(out.read_text())
    subject = load_subject(use.subject_dir)
    reference = evaluate_frames(load_avatar(use.avatar_dir), list(subject.test))
    assert result["psnr"] == pytest.approx(reference.psnr, abs=1e-12)
    assert result["psnr_full"] == pytest.approx(reference.psnr_full, abs=1e-12)
    assert result["psnr_refined"] is None and result["psnr_refined_full"] is None
    assert result["ssim"] == pytest.approx(reference.ssim, abs=1e-12)
    assert result["psnr_mesh_only"] == pytest.approx(reference.psnr_mesh_only, abs=1e-12)
    assert result["per_frame"]["psnr"] == pytest.approx(list(reference.per_frame_psnr), abs=1e-12)
    assert result["lpips_alex"] is None and result["lpips_vgg"] is None
    timesteps = subject.test.timesteps
    pairs = sum(b == a + 1 for a, b in itertools.pairwise(timesteps))
    assert pairs > 0 and result["temporal_pairs"] == pairs
    # The documented substitute, from the renders directly: mean |Δ error| in both masks.
    avatar = load_avatar(use.avatar_dir)
    changes = []
    with torch.no_grad():
        for a, b in itertools.pairwise(subject.test):
            if b.timestep != a.timestep + 1:
                continue
            err = [
                avatar.render(avatar.params_from_flame(f.flame), f.camera).image.clamp(0, 1)
                - f.image
                for f in (a, b)
            ]
            mask = (a.mask * b.mask)[..., None].expand(-1, -1, 3)
            changes.append(float(((err[1] - err[0]).abs() * mask).sum() / mask.sum()))
    assert result["temporal_error_change_mean"] == pytest.approx(np.mean(changes), rel=1e-6)
    assert result["temporal_error_change_var"] == pytest.approx(
        np.var(changes), rel=1e-5, abs=1e-12
    )
    assert result["temporal_error_change_var"] >= 0
    assert result["render_fps"] > 0
    assert result["num_gaussians"] == 300


def test_eval_refine_flame_reports_refined_scores_like_evaluate_frames(use, tmp_path):
    out = tmp_path / "eval.json"
    argv = ["eval", str(use.avatar_dir), "--json", str(out), "--refine-flame"]
    assert main([*argv, "--refine-steps", "5"]) == 0
    result = json.loads(out.read_text())
    subject = load_subject(use.subject_dir)
    reference = evaluate_frames(
        load_avatar(use.avatar_dir), list(subject.test), refine=RefineSettings(steps=5)
    )
    assert result["refine_steps"] == 5
    for key in ("psnr_refined", "psnr_refined_full", "ssim_refined"):
        assert result[key] == pytest.approx(getattr(reference, key), abs=1e-9), key
    # Refinement keeps the state of lowest loss it scored (the tracked one included); the
    # loss is L1 + SSIM, not MSE, so PSNR may differ by a hair, never by more.
    assert result["psnr_refined_full"] >= result["psnr_full"] - 0.05
    assert len(result["per_frame"]["psnr_refined"]) == result["frames"]


def write_random_lpips_weights(folder, seed=0):
    """Weight files with the real files' names, keys and shapes, random values."""
    g = torch.Generator().manual_seed(seed)
    folder.mkdir()
    for variant, spec in VARIANTS.items():
        backbone = {}
        for idx, (cin, cout, k, _, _) in zip(spec["indices"], spec["convs"], strict=True):
            backbone[f"features.{idx}.weight"] = torch.randn(cout, cin, k, k, generator=g) * 0.05
            backbone[f"features.{idx}.bias"] = torch.randn(cout, generator=g) * 0.01
        name = "alexnet-owt-test.pth" if variant == "alex" else "vgg16-test.pth"
        torch.save(backbone, folder / name)
        linear = {
            f"lin{i}.model.1.weight": torch.rand(1, spec["convs"][tap][1], 1, 1, generator=g)
            for i, tap in enumerate(spec["taps"])
        }
        torch.save(linear, folder / spec["linear"])


def test_lpips_from_local_weights(use, tmp_path):
    weights = tmp_path / "lpips"
    write_random_lpips_weights(weights)
    nets, notes = load_lpips(weights)
    assert sorted(nets) == ["alex", "vgg"] and notes == []
    g = torch.Generator().manual_seed(1)
    a = torch.rand(64, 64, 3, generator=g)
    b = (a + 0.2 * torch.randn(64, 64, 3, generator=g)).clamp(0, 1)
    mask = torch.zeros(64, 64)
    mask[16:48, 16:48] = 1
    for net in nets.values():
        assert net(a, a, mask) == 0.0
        assert net(a, b, mask) > 0
        d = net.distance_map(a, b)
        assert net(a, b, mask) == pytest.approx(float(d[16:48, 16:48].mean()), rel=1e-5)
    out = tmp_path / "eval.json"
    assert (
        main(["eval", str(use.avatar_dir), "--json", str(out), "--lpips-weights", str(weights)])
        == 0
    )
    result = json.loads(out.read_text())
    assert result["lpips_alex"] > 0 and result["lpips_vgg"] > 0
    assert result["temporal_lpips_alex_mean"] is not None
    assert result["lpips_skipped"] == []


def test_lpips_rejects_a_wrong_weight_file(tmp_path):
    weights = tmp_path / "lpips"
    write_random_lpips_weights(weights)
    torch.save({"lin0.model.1.weight": torch.zeros(1, 3, 1, 1)}, weights / "alex.pth")
    with pytest.raises(ValueError, match=r"alex\.pth"):
        load_lpips(weights)


def test_render_frames_and_orbit(use, tmp_path):
    out = tmp_path / "render"
    assert main(["render", str(use.avatar_dir), "--out", str(out)]) == 0
    subject = load_subject(use.subject_dir)
    video = read_video(out / "render.mp4")
    assert len(video) == len(subject.test)
    bar = label_bar_height(64)
    assert video[0].shape == (bar + 64, 4 * 64, 3)
    pngs = sorted(p.name for p in (out / "frames").iterdir())
    assert pngs == [f"{t:05d}.png" for t in subject.test.timesteps]
    rows = [cv2.imread(str(out / "frames" / name)) for name in pngs]
    truth = (subject.test[0].image.numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
    assert np.array_equal(rows[0][bar:, :64], truth)  # ground truth on the left
    assert rows[0][:bar].min() < 128 and rows[0][:bar].max() == 255  # black labels on white
    for png, decoded in zip(rows, video, strict=True):  # the video is the frames
        assert luma_psnr(png, decoded) > 30  # observed 33.8–35.3 dB
    # Rendered a few at a time, every frame is the avatar as rendered alone.
    opened = open_avatar(use.avatar_dir)
    with torch.no_grad():
        for frame, row in zip(subject.test, rows, strict=True):
            params = frame_params(opened.avatar, frame)
            image = opened.avatar.render(params, frame.camera).image.clamp(0, 1)
            assert np.array_equal(row[bar:, 64:128], bgr_uint8(image))

    assert (
        main(
            ["render", str(use.avatar_dir), "--out", str(out), "--orbit", "0", "--orbit-steps", "6"]
        )
        == 0
    )
    orbit = read_video(out / "orbit_00000.mp4")
    assert len(orbit) == 6 and orbit[0].shape == (bar + 64, 2 * 64, 3)
    views = [cv2.imread(str(out / "orbit_00000" / f"{i:03d}.png")) for i in range(6)]
    # The first view is the frame's own camera: the avatar as rendered there.
    avatar = load_avatar(use.avatar_dir)
    with torch.no_grad():
        image = avatar.render(avatar.frame(0), subject.train[0].camera).image.clamp(0, 1)
    # Equal up to the PNG's 8-bit rounding: a value on a rounding tie (x·255 = k + 0.5)
    # may round either way after a 1-ulp difference in the camera's arithmetic.
    expected = image.numpy()[..., ::-1].astype(np.float64) * 255
    assert np.abs(views[0][bar:, :64] - expected).max() <= 0.5 + 1e-3
    assert not np.array_equal(views[0][bar:], views[3][bar:])  # the view turns


def test_default_orbit_stays_in_the_captured_yaw_range(use):
    opened = open_avatar(use.avatar_dir)
    avatar = opened.avatar
    camera = avatar_camera(opened, None)
    e = avatar.num_expr
    up = camera_up(camera)
    yaws = head_yaws(avatar.frame_params[:, e:], up)
    assert yaws.max() - yaws.min() > np.radians(10)  # the fixture's head turns
    for t in (0, 1, 5):
        params = avatar.frame(t)
        here = head_yaws(params.pose[None], up)[0]
        angles = default_orbit_angles(avatar, params, camera, 24)
        assert angles[0] == 0  # starts at the frame's own view
        seen = here - angles  # turning the camera by a shows the head turned by −a
        assert seen.min() >= yaws.min() - 1e-9 and seen.max() <= yaws.max() + 1e-9
        # ... and sweeps the whole range (to a step of the path)
        step = 2 * (yaws.max() - yaws.min()) / 24
        assert seen.min() <= yaws.min() + step and seen.max() >= yaws.max() - step


def test_orbit_of_a_held_out_frame_uses_its_tracked_parameters(use, tmp_path):
    subject = load_subject(use.subject_dir)
    t = subject.test.timesteps[0]
    out = tmp_path / "render"
    argv = ["render", str(use.avatar_dir), "--out", str(out), "--orbit", str(t)]
    assert main([*argv, "--orbit-steps", "2"]) == 0
    view = cv2.imread(str(out / f"orbit_{t:05d}" / "000.png"))
    avatar = load_avatar(use.avatar_dir)
    frame = subject.test[0]
    with torch.no_grad():
        image = avatar.render(avatar.params_from_flame(frame.flame), frame.camera).image
    expected = (image.clamp(0, 1).numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
    assert np.array_equal(view[label_bar_height(64) :, :64], expected)


def test_reenact_from_subject_and_npz(use, tmp_path):
    out = tmp_path / "reenact.mp4"
    assert (
        main(["reenact", str(use.avatar_dir), "--driver", str(use.subject_dir), "--out", str(out)])
        == 0
    )
    video = read_video(out)
    assert len(video) == 10 and video[0].shape == (64, 64, 3)
    avatar = load_avatar(use.avatar_dir)
    camera = avatar_camera(open_avatar(use.avatar_dir), None)
    with torch.no_grad():
        first = avatar.render(driven_params(avatar, load_driver(use.subject_dir))[0], camera)
    expected = (first.image.clamp(0, 1).numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
    assert luma_psnr(video[0], expected) > 30  # H.264 at CRF 18: close to the render

    driver = load_driver(use.subject_dir)
    npz = tmp_path / "driver.npz"
    keys = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
    stacked = {k: driver[k][:4] for k in keys}
    stacked["translation"] = stacked["translation"] + np.float32([0.3, -0.1, 2.0])  # far away
    stacked["shape"] = np.ones((4, 300), np.float32)  # another identity: ignored
    np.savez(npz, **stacked)
    out2 = tmp_path / "reenact_npz.mp4"
    assert main(["reenact", str(use.avatar_dir), "--driver", str(npz), "--out", str(out2)]) == 0
    assert len(read_video(out2)) == 4

    params = driven_params(avatar, load_driver(npz))
    e = avatar.num_expr
    transl = torch.stack([p.transl for p in params])
    target = avatar.frame_params[:, e + POSE_SIZE :].mean(0)
    assert torch.allclose(transl.mean(0), target, atol=1e-6)  # re-centred on the avatar
    step = torch.from_numpy(stacked["translation"][1] - stacked["translation"][0])
    assert torch.allclose(transl[1] - transl[0], step, atol=1e-6)  # the motion is kept
    for i, p in enumerate(params):
        assert torch.equal(p.expr, torch.from_numpy(stacked["expr"][i][:e]))
        assert torch.equal(p.pose[6:9], torch.from_numpy(stacked["jaw_pose"][i]))


@pytest.mark.parametrize(
    "command, message",
    [
        (["eval", "{missing}"], "no such directory"),
        (["eval", "{avatar}", "--subject", "{missing}"], "no such directory"),
        (["eval", "{avatar}", "--subject", "{avatar}"], "transforms"),
        (["render", "{avatar}", "--out", "{out}", "--subject", "{missing}"], "no such directory"),
        (["render", "{avatar}", "--out", "{out}", "--orbit", "77"], "not a frame"),
        (["reenact", "{avatar}", "--driver", "{missing}", "--out", "{out}/r.mp4"], "no such"),
        (["reenact", "{avatar}", "--driver", "{bad_npz}", "--out", "{out}/r.mp4"], "missing keys"),
        (["reenact", "{avatar}", "--driver", "{subject}", "--out", "{out}/r.avi"], ".mp4"),
    ],
)
def test_bad_inputs_fail_before_writing(use, tmp_path, capsys, command, message):
    bad_npz = tmp_path / "bad.npz"
    np.savez(bad_npz, expr=np.zeros((2, 10), np.float32))
    names = {
        "avatar": use.avatar_dir,
        "subject": use.subject_dir,
        "missing": tmp_path / "missing",
        "out": tmp_path / "out",
        "bad_npz": bad_npz,
    }
    before = sorted(p.name for p in use.avatar_dir.iterdir())
    assert main([c.format(**names) for c in command]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert sorted(p.name for p in use.avatar_dir.iterdir()) == before


def test_eval_json_to_standard_output(use, capsys):
    assert main(["eval", str(use.avatar_dir), "--json", "-"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)  # standard output is the JSON alone
    assert result["frames"] == 3 and result["psnr"] > 0
    assert "PSNR in mask (dB)" in captured.err  # the table goes to standard error
    assert not (use.avatar_dir / "eval_test.json").exists()


def test_an_avatar_moved_with_its_subject_finds_it(use, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(use.avatar_dir, moved / "avatar")
    shutil.copytree(use.subject_dir, moved / "subject")
    meta_path = moved / "avatar" / "avatar.json"
    meta = json.loads(meta_path.read_text())
    meta["subject"] = str(tmp_path / "gone")  # the absolute path no longer exists
    meta_path.write_text(json.dumps(meta))
    assert main(["eval", str(moved / "avatar"), "--json", "-"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["subject"] == str(moved / "avatar" / meta["subject_relative"])
    assert (moved / "avatar" / meta["subject_relative"]).resolve() == (moved / "subject")
