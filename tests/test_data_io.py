"""urhead.data: writer → reader round trip, the camera conversion, splits, the frame cache."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from urhead import Camera
from urhead.data import SubjectWriter, load_subject, opengl_c2w
from urhead.data.layout import decode_normals, encode_normals

W, H = 40, 30


def make_camera() -> Camera:
    """A camera 0.8 m in front of the origin, slightly rotated, with an off-centre
    principal point and different focal lengths."""
    cam = Camera.look_at((0.1, 0.05, 0.8), (0.0, 0.0, 0.0), width=W, height=H)
    k = torch.tensor([[70.0, 0, 17.25], [0, 75.0, 12.5], [0, 0, 1]])
    return Camera(k, cam.viewmat, W, H)


def random_flame(rng, num_verts=None) -> dict:
    p = {
        "translation": rng.normal(size=(1, 3)).astype(np.float32),
        "rotation": rng.normal(size=(1, 3)).astype(np.float32) * 0.1,
        "neck_pose": rng.normal(size=(1, 3)).astype(np.float32) * 0.1,
        "jaw_pose": rng.normal(size=(1, 3)).astype(np.float32) * 0.1,
        "eyes_pose": rng.normal(size=(1, 6)).astype(np.float32) * 0.1,
        "shape": rng.normal(size=(300,)).astype(np.float32),
        "expr": rng.normal(size=(1, 100)).astype(np.float32),
    }
    if num_verts:
        p["static_offset"] = rng.normal(size=(1, num_verts, 3)).astype(np.float32) * 1e-3
    return p


def random_normals(rng) -> np.ndarray:
    n = rng.normal(size=(H, W, 3)).astype(np.float32)
    n[..., 2] = -np.abs(n[..., 2])  # facing the camera
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[:3] = 0.0  # undefined rows
    return n


def write_subject(root, num_frames=6, normals=True, test_last=None, seed=0):
    rng = np.random.default_rng(seed)
    frames = []
    with SubjectWriter(root, make_camera(), test_last=test_last) as w:
        for t in range(num_frames):
            image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
            mask = rng.integers(0, 256, size=(H, W), dtype=np.uint8)
            flame = random_flame(rng, num_verts=7)
            n = random_normals(rng) if normals else None
            w.add_frame(t, image, mask, flame, normals=n)
            frames.append((image, mask, flame, n))
    return frames


def test_round_trip_reproduces_pixels_masks_flame_and_normals(tmp_path):
    root = tmp_path / "subject"
    written = write_subject(root, num_frames=10)
    subject = load_subject(root)
    assert (subject.width, subject.height) == (W, H)
    assert subject.has_normals
    # VHAP's split of one camera: the first ceil(0.7·T) timesteps train, the rest test,
    # val empty.
    assert subject.train.timesteps == list(range(7))
    assert subject.test.timesteps == [7, 8, 9]
    assert len(subject.val) == 0
    for frame in [*subject.train, *subject.test]:
        image, mask, flame, normals = written[frame.timestep]
        assert frame.image.dtype == torch.float32 and frame.image.shape == (H, W, 3)
        assert torch.equal(frame.image, torch.from_numpy(image.astype(np.float32) / 255))
        assert torch.equal(frame.mask, torch.from_numpy(mask.astype(np.float32) / 255))
        for key, value in flame.items():
            assert np.array_equal(frame.flame[key], value), key
        got = frame.normals.numpy()
        defined = np.any(normals != 0, axis=-1)
        assert np.array_equal(np.any(got != 0, axis=-1), defined)
        # 8-bit encoding: worst angular error of one quantisation step (~0.6°).
        cos = (got[defined] * normals[defined]).sum(-1)
        assert cos.min() > math.cos(math.radians(0.7))
    cam, ref = subject.train[0].camera, make_camera()
    assert torch.allclose(cam.K, ref.K) and torch.allclose(cam.viewmat, ref.viewmat, atol=1e-6)
    canonical = subject.canonical_flame
    assert np.array_equal(canonical["jaw_pose"], np.array([[0.3, 0, 0]], np.float32))
    assert canonical["static_offset"].shape == (1, 7, 3)
    stacked = subject.train.flame_params()
    assert stacked["expr"].shape == (7, 100) and stacked["shape"].shape == (7, 300)
    assert stacked["static_offset"].shape == (7, 7, 3)


def test_transforms_files_carry_every_key_of_the_layout(tmp_path):
    from urhead.data.layout import FRAME_KEYS, TOP_LEVEL_KEYS

    root = tmp_path / "s"
    write_subject(root, num_frames=4, normals=False)
    for name in ("transforms", "transforms_train", "transforms_val", "transforms_test"):
        meta = json.loads((root / f"{name}.json").read_text())
        assert set(TOP_LEVEL_KEYS) <= set(meta)
        for frame in meta["frames"]:
            assert set(FRAME_KEYS) <= set(frame)
            assert frame["camera_angle_x"] == pytest.approx(2 * math.atan(W / 2 / 70.0))
    assert not load_subject(root).has_normals
    assert load_subject(root).train[0].normals is None


def test_converted_camera_puts_a_point_on_the_pixel_an_opengl_projection_gives(tmp_path):
    """An independent OpenGL-convention projection of a world point (from the JSON's c2w and
    intrinsics) must agree with the reader's OpenCV camera, off-centre principal point
    included; the point is painted into the image at that pixel and found there."""
    root = tmp_path / "s"
    camera = make_camera()
    point = np.array([0.031, -0.017, 0.02])
    c2w_gl = opengl_c2w(camera)
    x, y, z = (np.linalg.inv(c2w_gl) @ np.r_[point, 1.0])[:3]  # OpenGL camera: looks down -z
    px, py = 70.0 * x / -z + 17.25, 12.5 - 75.0 * y / -z
    with SubjectWriter(root, camera, test_last=1) as w:
        for t in range(2):
            image = np.zeros((H, W, 3), np.uint8)
            image[int(py), int(px)] = 255
            w.add_frame(
                t, image, np.full((H, W), 255, np.uint8), random_flame(np.random.default_rng(t))
            )
    frame = load_subject(root).train[0]
    uv, depth = frame.camera.project(torch.tensor(point, dtype=torch.float64))
    assert uv.tolist() == pytest.approx([px, py], abs=1e-4)
    assert float(depth) == pytest.approx(-z, rel=1e-6)
    row, col = int(uv[1]), int(uv[0])
    assert frame.image[row, col].tolist() == [1.0, 1.0, 1.0]
    assert frame.image.sum() == 3.0


def test_test_last_splits_transforms_json_by_time(tmp_path):
    root = tmp_path / "s"
    write_subject(root, num_frames=8, normals=False)
    subject = load_subject(root, test_last=3)
    assert subject.train.timesteps == [0, 1, 2, 3, 4]
    assert subject.test.timesteps == [5, 6, 7]
    assert len(subject.val) == 0


def test_frames_are_cached_with_a_bound(tmp_path):
    root = tmp_path / "s"
    write_subject(root, num_frames=5, normals=False)
    subject = load_subject(root, test_last=1, cache_size=2)
    a = subject.train[0]
    assert subject.train[0] is a  # cached
    subject.train[1], subject.train[2]  # evicts frame 0 (least recently used)
    assert len(subject._cache) == 2
    again = subject.train[0]
    assert again is not a and torch.equal(again.image, a.image)
    assert [f.timestep for f in subject.train[1:3]] == [1, 2]


def test_frame_cache_is_bounded_in_bytes(tmp_path):
    root = tmp_path / "s"
    write_subject(root, num_frames=6, normals=False)
    one = load_subject(root, test_last=1, cache_size=1).train[0]
    frame_bytes = sum(t.numel() * t.element_size() for t in (one.image, one.mask))
    subject = load_subject(root, test_last=1, cache_bytes=3 * frame_bytes)
    frames = [subject.train[i] for i in range(5)]
    assert len(subject._cache) == 3  # the byte budget, not a count, evicted two
    assert subject.train[4] is frames[4] and subject.train[0] is not frames[0]
    everything = load_subject(root, test_last=1)  # the default budget holds them all
    first = [everything.train[i] for i in range(5)]
    assert all(everything.train[i] is first[i] for i in range(5))
    smaller = load_subject(root, test_last=1, cache_bytes=frame_bytes // 2)
    a = smaller.train[0]  # a frame larger than the budget is still returned, kept alone
    assert smaller.train[0] is a and len(smaller._cache) == 1
    smaller.train[1]
    assert len(smaller._cache) == 1
    with pytest.raises(ValueError, match="cache_bytes"):
        load_subject(root, test_last=1, cache_bytes=-1)
    with pytest.raises(ValueError, match="cache_size"):
        load_subject(root, test_last=1, cache_size=0)


def test_writer_is_atomic_and_refuses_to_clobber(tmp_path):
    root = tmp_path / "s"
    rng = np.random.default_rng(0)
    with pytest.raises(RuntimeError, match="boom"), SubjectWriter(root, make_camera()) as w:
        w.add_frame(0, np.zeros((H, W, 3)), np.ones((H, W)), random_flame(rng))
        raise RuntimeError("boom")
    assert not root.exists()
    assert list(tmp_path.iterdir()) == []  # the temporary folder is gone too
    write_subject(root, num_frames=3, normals=False)
    with pytest.raises(FileExistsError, match="already exists"):
        SubjectWriter(root, make_camera())
    write_subject_again = SubjectWriter(root, make_camera(), overwrite=True, test_last=1)
    with write_subject_again as w:
        for t in range(4):
            w.add_frame(t, np.zeros((H, W, 3)), np.ones((H, W)), random_flame(rng))
    assert len(load_subject(root).train) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_writer_rejects_inconsistent_frames(tmp_path):
    rng = np.random.default_rng(0)
    w = SubjectWriter(tmp_path / "s", make_camera())
    with pytest.raises(ValueError, match=r"image must be \(30, 40, 3\)"):
        w.add_frame(0, np.zeros((H, W)), np.ones((H, W)), random_flame(rng))
    bad = random_flame(rng)
    bad["expr"] = bad["expr"][0]
    with pytest.raises(ValueError, match=r"00000\.npz: 'expr' must have shape"):
        w.add_frame(0, np.zeros((H, W, 3)), np.ones((H, W)), bad)
    w.add_frame(0, np.zeros((H, W, 3)), np.ones((H, W)), random_flame(rng))
    with pytest.raises(ValueError, match="must exceed"):
        w.add_frame(0, np.zeros((H, W, 3)), np.ones((H, W)), random_flame(rng))
    with pytest.raises(ValueError, match="normals must be given for every frame"):
        w.add_frame(1, np.zeros((H, W, 3)), np.ones((H, W)), random_flame(rng), random_normals(rng))
    w.abort()
    assert not (tmp_path / "s").exists()


def test_normal_encoding_round_trip_and_sentinel():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(64, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[:4] = 0
    n[4] = (0, 0, -1)  # facing the camera → "blue" (128, 128, 255)
    rgb = encode_normals(n[None])[0]
    assert rgb[4].tolist() == [128, 128, 255]
    assert (rgb[:4] == 0).all() and (rgb[4:].any(-1)).all()
    back = decode_normals(rgb[None])[0]
    assert (back[:4] == 0).all()
    assert (back[4:] * n[4:]).sum(-1).min() > math.cos(math.radians(0.7))


def test_normal_decoding_is_the_plain_float32_decode_bit_for_bit():
    """The byte-table decode gives the bits of the direct one: bytes / 127.5 − 1, OpenGL →
    OpenCV axes, n / max(‖n‖, 1e-6), zero where all three bytes are 0 (every byte value in
    every channel, and pixels with some bytes 0)."""
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (257, 256, 3), dtype=np.uint8)
    for k in range(3):
        rgb[k, :, k] = np.arange(256)  # every byte value in channel k
    rgb[3:6] = 0
    rgb[6:9, :, 1:] = 0
    rgb[9:12, :, 0] = 0
    valid = rgb.any(-1, keepdims=True)
    n = (rgb.astype(np.float32) / 127.5 - 1.0) * np.array([1.0, -1.0, -1.0], np.float32)
    direct = np.where(valid, n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6), 0)
    decoded = decode_normals(rgb)
    assert decoded.dtype == np.float32
    assert np.array_equal(decoded.view(np.uint32), direct.astype(np.float32).view(np.uint32))
