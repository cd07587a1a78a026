"""The HeadModel container, its .npz format and UV-space tools."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flame_fixtures import flame_like_model, write_flame2020_pickle, write_template_obj
from urhead.errors import IndexRangeError, InvalidArgumentError, ShapeError
from urhead.head import (
    FORMAT_VERSION,
    REGION_NAMES,
    HeadModel,
    UvLookup,
    load_flame,
    load_head,
    save_head,
    seam_free_vertex_uv,
    texel_centers,
    triangle_id_map,
    uv_region_masks,
)
from urhead.ops._reference import lbs as reference_lbs


@pytest.fixture(scope="module")
def flame_head(tmp_path_factory):
    d = tmp_path_factory.mktemp("flame")
    write_flame2020_pickle(d / "generic_model.pkl", flame_like_model())
    write_template_obj(d / "head_template_mesh.obj")
    return load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj")


def _arrays(head: HeadModel) -> dict:
    return {name: getattr(head, name) for name in HeadModel.__dataclass_fields__}


def test_npz_round_trip_is_exact(flame_head, tmp_path):
    path = tmp_path / "head.npz"
    save_head(flame_head, path)
    again = load_head(path)
    for name, value in _arrays(flame_head).items():
        got = getattr(again, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and got.dtype in (np.float32, np.int32), name
        np.testing.assert_array_equal(got, value, err_msg=name)
    assert not list(tmp_path.glob("*.tmp"))  # atomic write left nothing behind
    with np.load(path) as z:
        assert int(z["format_version"]) == FORMAT_VERSION


def test_npz_accepts_a_csr_regressor(flame_head, tmp_path):
    path = tmp_path / "head.npz"
    save_head(flame_head, path)
    with np.load(path) as z:
        arrays = dict(z)
    dense = arrays.pop("j_regressor")
    rows, cols = np.nonzero(dense)
    indptr = np.searchsorted(rows, np.arange(dense.shape[0] + 1))
    arrays.update(
        j_regressor_data=dense[rows, cols],
        j_regressor_indices=cols.astype(np.int32),
        j_regressor_indptr=indptr.astype(np.int32),
        j_regressor_shape=np.array(dense.shape, np.int32),
    )
    np.savez(tmp_path / "csr.npz", **arrays)
    np.testing.assert_array_equal(load_head(tmp_path / "csr.npz").j_regressor, dense)


@pytest.mark.parametrize(
    ("key", "value", "error", "match"),
    [
        ("v_template", np.zeros((5, 2), np.float32), ShapeError, "v_template must be"),
        ("faces", None, IndexRangeError, "faces must index"),
        ("shapedirs", np.zeros((3, 3, 3), np.float32), ShapeError, "shapedirs must be"),
        ("lbs_weights", "halve", InvalidArgumentError, "lbs_weights rows must sum to 1"),
        ("parents", np.array([-1, 0, 2, 1, 1], np.int32), InvalidArgumentError, "parents"),
        ("uv_faces", "drop", ShapeError, "uv_faces must be"),
        ("format_version", np.int32(99), InvalidArgumentError, "format_version 99"),
        ("num_expr", None, InvalidArgumentError, "missing key 'num_expr'"),
        ("vertex_uv", "nan", ValueError, "vertex_uv"),
    ],
)
def test_bad_files_name_the_key(flame_head, tmp_path, key, value, error, match):
    path = tmp_path / "head.npz"
    save_head(flame_head, path)
    with np.load(path) as z:
        arrays = dict(z)
    if key == "faces":
        arrays["faces"] = arrays["faces"].copy()
        arrays["faces"][3, 1] = arrays["v_template"].shape[0]
    elif value is None:
        del arrays[key]
    elif isinstance(value, str):
        a = arrays[key].copy()
        if value == "halve":
            a *= 0.5
        elif value == "drop":
            a = a[:-1]
        else:
            a[2, 0] = np.nan
        arrays[key] = a
    else:
        arrays[key] = value
    np.savez(path, **arrays)
    with pytest.raises(error, match=match):
        load_head(path)


def test_structural_invariants(flame_head):
    h = flame_head
    assert h.v_template.dtype == np.float32 and h.faces.dtype == np.int32
    assert h.lbs_weights.min() >= 0
    np.testing.assert_allclose(h.lbs_weights.sum(1), 1, atol=1e-6)
    assert h.uv_coords.min() >= 0 and h.uv_coords.max() <= 1
    assert not h.v_template.flags.writeable
    # vertex_uv is the UV of each vertex's first occurrence
    first = {}
    for f, (tri, uvt) in enumerate(zip(h.faces, h.uv_faces, strict=True)):
        for v, t in zip(tri, uvt, strict=True):
            first.setdefault(int(v), int(t))
        if f > 200:
            break
    for v, t in first.items():
        np.testing.assert_array_equal(h.vertex_uv[v], h.uv_coords[t])


def test_seam_free_uv_takes_the_first_occurrence():
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    uv_faces = np.array([[0, 1, 2], [3, 4, 5]])  # vertices 1 and 2 also appear with UVs 4, 3
    uv = np.arange(12, dtype=np.float32).reshape(6, 2) / 12
    got = seam_free_vertex_uv(faces, uv_faces, uv, 4)
    np.testing.assert_array_equal(got, uv[[0, 1, 2, 5]])
    with pytest.raises(InvalidArgumentError, match="used by no face"):
        seam_free_vertex_uv(faces, uv_faces, uv, 5)


def test_uv_lookup_recovers_points_and_barycentrics(flame_head):
    h = flame_head
    rng = np.random.default_rng(3)
    lookup = UvLookup(h.uv_coords, h.uv_faces)
    faces = rng.integers(0, 9300, 4000)  # the head tube: its UV triangles do not overlap
    b = rng.dirichlet([2, 2, 2], 4000)
    corners = h.uv_coords[h.uv_faces[faces]].astype(np.float64)
    uv = np.einsum("nk,nkc->nc", b, corners)
    got_face, got_b = lookup.locate(uv)
    assert np.all(got_face >= 0)
    # the found triangle reproduces the point (it may be a neighbour on a shared edge)
    got_uv = np.einsum("nk,nkc->nc", got_b, h.uv_coords[h.uv_faces[got_face]].astype(np.float64))
    np.testing.assert_allclose(got_uv, uv, atol=1e-12)
    np.testing.assert_allclose(got_b.sum(1), 1, atol=1e-12)
    np.testing.assert_array_equal(got_face, faces)
    np.testing.assert_allclose(got_b, b, atol=1e-9)


def test_uv_lookup_outside_and_non_finite():
    uv = np.array([[0, 0], [1, 0], [0, 1]], np.float32)
    lookup = UvLookup(uv, np.array([[0, 1, 2]]))
    face, bary = lookup.locate(np.array([[0.9, 0.9], [np.nan, 0.1], [-1e-7, 0.5], [0.25, 0.25]]))
    np.testing.assert_array_equal(face, [-1, -1, -1, 0])
    np.testing.assert_array_equal(bary[:3], 0)
    np.testing.assert_allclose(bary[3], [0.5, 0.25, 0.25])


def test_texel_centers_follow_the_vt_convention():
    c = texel_centers((2, 4)).reshape(2, 4, 2)
    np.testing.assert_allclose(c[0, 0], [0.125, 0.75])  # row 0 is the top (v near 1)
    np.testing.assert_allclose(c[1, 3], [0.875, 0.25])


def test_region_masks(flame_head):
    ids = triangle_id_map(flame_head, 256)
    assert ids.shape == (256, 256) and ids.max() < flame_head.num_faces
    masks = uv_region_masks(flame_head, 256)
    assert set(masks) == set(REGION_NAMES)
    stacked = np.stack(list(masks.values()))
    assert stacked.sum(0).max() == 1  # one region per texel
    np.testing.assert_array_equal(stacked.any(0), ids >= 0)
    assert masks["teeth"][:12].any() and not masks["teeth"][40:].any()  # teeth box at the top


def test_head_without_uv_refuses_uv_operations(tmp_path):
    d = tmp_path
    write_flame2020_pickle(d / "m.pkl", flame_like_model())
    head = load_flame(d / "m.pkl", teeth=False)
    with pytest.raises(InvalidArgumentError, match="no UV layout"):
        uv_region_masks(head, 64)
    save_head(head, d / "h.npz")
    assert not load_head(d / "h.npz").has_uv


def test_skin_matches_the_reference(flame_head):
    h = flame_head
    rng = np.random.default_rng(0)
    shape = torch.tensor(rng.normal(size=(2, 20)))
    expr = torch.tensor(rng.normal(size=(2, 10)))
    pose = torch.tensor(rng.normal(0, 0.3, size=(2, 15)))
    transl = torch.tensor(rng.normal(0, 0.1, size=(2, 3)))
    out = h.skin(shape, expr, pose, transl)
    t = h.lbs_tables(torch.float64, 20, 10)
    ref = reference_lbs(torch.cat([shape, expr], 1), pose, transl=transl, **t)
    np.testing.assert_allclose(out.verts.numpy(), ref.verts.numpy(), atol=1e-10)
    np.testing.assert_array_equal(t["shapedirs"][:, :, 20:].numpy(), h.shapedirs[:, :, 300:310])
    assert h.skin().verts.shape == (1, h.num_vertices, 3)
    with pytest.raises(ShapeError, match="pose"):
        h.skin(pose=torch.zeros(1, 12))
