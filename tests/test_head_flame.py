"""FLAME loading: the 2020 (chumpy + old scipy path) and 2023 pickle styles, the OBJ UV
layout, the teeth extension and mouth plate, masks, and the convert-flame command."""

from __future__ import annotations

import io
import pickle
import pickletools

import numpy as np
import pytest
import scipy.sparse
import torch

from flame_fixtures import (
    chumpy_class,
    chumpy_object,
    flame_like_mesh,
    flame_like_model,
    pickle_with_stand_ins,
    write_flame2020_pickle,
    write_flame2023_pickle,
    write_template_obj,
)
from urhead.cli import main
from urhead.errors import InvalidArgumentError, ShapeError
from urhead.head import TeethConfig, add_teeth, load_flame, load_head
from urhead.head.pickle_compat import ChumpyStub, FlameUnpickler, load_flame_pickle
from urhead.head.teeth import ROW_ORDER, teeth_rest_geometry
from urhead.ops._reference import axis_angle_to_matrix


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("flame")
    model = flame_like_model()
    write_flame2020_pickle(d / "generic_model.pkl", model)
    write_flame2023_pickle(d / "flame2023.pkl", model)
    write_template_obj(d / "head_template_mesh.obj")
    return d, model


@pytest.mark.parametrize("name", ["generic_model.pkl", "flame2023.pkl"])
def test_pickle_round_trip_without_chumpy(files, name):
    d, model = files
    raw = load_flame_pickle(d / name)
    for key in ("v_template", "shapedirs", "posedirs", "weights", "kintree_table"):
        np.testing.assert_array_equal(raw[key], model[key])
    np.testing.assert_array_equal(raw["J_regressor"].toarray(), model["J_regressor"].toarray())
    assert raw["bs_style"] == "lbs"


def _globals_and_opcodes(blob: bytes) -> tuple[set, set]:
    names, ops = set(), set()
    for op, arg, _ in pickletools.genops(blob):
        ops.add(op.name)
        if op.name == "GLOBAL":
            names.add(arg)
    return names, ops


def test_2020_pickle_is_written_the_way_python2_chumpy_writes_it(files):
    d, _ = files
    blob = (d / "generic_model.pkl").read_bytes()
    names, ops = _globals_and_opcodes(blob)
    assert blob[:2] == b"\x80\x02"  # protocol 2
    assert {
        "chumpy.ch Ch",
        "scipy.sparse.csc csc_matrix",
        "__builtin__ set",
        "numpy.core.multiarray _reconstruct",
    } <= names
    assert "_codecs encode" not in names and "BINUNICODE" not in ops  # Python 2 str only
    assert {"SHORT_BINSTRING", "BINSTRING", "NEWOBJ", "BUILD", "NEWFALSE"} <= ops


def test_chumpy_state_is_read_whole():
    """Everything chumpy pickles of a Ch (a set, a dict, None, bools) comes through."""
    Ch = chumpy_class()
    obj = chumpy_object(Ch, x=np.arange(3.0))
    obj._depends_on_deps = {"r": {"deps": ["x"], "value": None, "out_of_date": True}}
    blob = pickle_with_stand_ins({"ch": obj}, [Ch])
    stub = FlameUnpickler(io.BytesIO(blob)).load()["ch"]
    assert isinstance(stub, ChumpyStub) and stub.chumpy_class == "chumpy.ch.Ch"
    assert stub.state["_dirty_vars"] == {"x"}
    assert stub.state["_itr"] is None
    assert stub.state["_depends_on_deps"] == {
        "r": {"deps": ["x"], "value": None, "out_of_date": True}
    }
    assert stub.state["_make_dense"] is False and stub.state["_make_sparse"] is False
    assert "_parents" not in stub.state and "_cache" not in stub.state
    np.testing.assert_array_equal(stub.to_array(), np.arange(3.0))


@pytest.mark.parametrize(
    "value, protocol, fix_imports, global_name",
    [
        ({"a", "b"}, 2, True, "__builtin__ set"),  # Python 2's name under protocol 2
        ({"a", "b"}, 2, False, "builtins set"),
        (frozenset({1, 2}), 2, True, "__builtin__ frozenset"),
        (complex(1, 2), 2, True, "__builtin__ complex"),
        ({"a", "b"}, 4, True, None),  # protocol 4: an opcode, no global
        (frozenset({1, 2}), 4, True, None),
    ],
)
def test_data_only_builtins_load(value, protocol, fix_imports, global_name):
    blob = pickle.dumps({"v": value}, protocol=protocol, fix_imports=fix_imports)
    names, _ = _globals_and_opcodes(blob)
    assert names == ({global_name} if global_name else set())
    assert FlameUnpickler(io.BytesIO(blob)).load() == {"v": value}


def _calling_pickle(module: str, name: str, argument: str) -> bytes:
    """A protocol-2 pickle that calls ``module.name(argument)`` when loaded."""
    arg = argument.encode()
    return (
        b"\x80\x02c" + module.encode() + b"\n" + name.encode() + b"\n"
        + b"X" + len(arg).to_bytes(4, "little") + arg
        + b"\x85R."
    )  # fmt: skip


@pytest.mark.parametrize(
    "module, name, shown",
    [
        ("os", "system", "os.system"),
        ("posix", "system", "posix.system"),
        ("builtins", "eval", "builtins.eval"),
        ("__builtin__", "eval", "builtins.eval"),
        ("__builtin__", "getattr", "builtins.getattr"),
        ("__builtin__", "__import__", "builtins.__import__"),
        ("builtins", "exec", "builtins.exec"),
        ("subprocess", "call", "subprocess.call"),
        ("copy_reg", "_reduce_ex", "copyreg._reduce_ex"),
        ("numpy", "load", "numpy.load"),
    ],
)
def test_code_running_globals_are_refused(tmp_path, module, name, shown):
    marker = tmp_path / "ran"
    command = f"open({str(marker)!r}, 'w')" if name in ("eval", "exec") else f"touch {marker}"
    path = tmp_path / "evil.pkl"
    path.write_bytes(_calling_pickle(module, name, command))
    # An UnpicklingError naming the file, and a ValueError: the CLI's one-line error.
    with pytest.raises(pickle.UnpicklingError, match=rf"evil\.pkl: refusing to load {shown}\b"):
        load_flame_pickle(path)
    with pytest.raises(ValueError):
        load_flame_pickle(path)
    assert not marker.exists()
    with pytest.raises(pickle.UnpicklingError, match=r"builtins\.print"):
        FlameUnpickler(io.BytesIO(pickle.dumps({"x": print}, protocol=2))).load()


def test_protocol1_chumpy_object_via_copy_reg_reconstructor():
    Ch = chumpy_class()
    blob = pickle_with_stand_ins(
        {"x": chumpy_object(Ch, x=np.ones(2))}, [Ch], python2=False, protocol=1
    )
    names, _ = _globals_and_opcodes(blob)
    assert {"copy_reg _reconstructor", "__builtin__ object"} <= names
    loaded = FlameUnpickler(io.BytesIO(blob)).load()["x"]
    np.testing.assert_array_equal(loaded.to_array(), np.ones(2))
    assert loaded.state["_dirty_vars"] == {"x"}


def test_chumpy_expression_without_an_array(files, tmp_path):
    """A derived chumpy object (no ``x``) is kept as a stub where FLAME does not need it
    and named where it does."""
    _, model = files
    Ch, Select = chumpy_class(), chumpy_class("chumpy.reordering", "Select")
    base = chumpy_object(Ch, x=np.asarray(model["v_template"]))
    derived = chumpy_object(Select, a=base, idxs=np.arange(6), preferred_shape=(2, 3))
    path = tmp_path / "extra.pkl"
    path.write_bytes(pickle_with_stand_ins(dict(model, J=derived), [Ch, Select]))
    raw = load_flame_pickle(path)
    assert isinstance(raw["J"], ChumpyStub) and raw["J"].chumpy_class == "chumpy.reordering.Select"
    assert load_flame(path, teeth=False).num_vertices == 5023
    path.write_bytes(pickle_with_stand_ins(dict(model, v_template=derived), [Ch, Select]))
    with pytest.raises(InvalidArgumentError, match=r"'v_template' is a chumpy\.reordering\.Select"):
        load_flame(path, teeth=False)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda s: s.update(indptr=s["indptr"][::-1].copy()), "indptr"),
        (lambda s: s.update(indices=s["indices"] + 10_000), "indices outside"),
        (lambda s: s.update(data=s["data"][:-1]), "values"),
        (lambda s: s.update(_shape=(5, -1)), "shape"),
    ],
)
def test_corrupt_sparse_parts_are_refused_before_scipy_sees_them(change, message):
    from urhead.head.pickle_compat import SparseStub

    reg = scipy.sparse.csc_matrix(np.eye(5, 7))
    stub = SparseStub()
    state = {"_shape": reg.shape, "data": reg.data, "indices": reg.indices, "indptr": reg.indptr}
    change(state)
    stub.__setstate__(state)
    with pytest.raises(pickle.UnpicklingError, match=message):
        stub.to_scipy()


@pytest.mark.parametrize("name", ["generic_model.pkl", "flame2023.pkl"])
def test_load_flame_matches_the_pickle(files, name):
    d, model = files
    head = load_flame(d / name, d / "head_template_mesh.obj", teeth=False)
    V = 5023
    assert (head.num_vertices, head.num_faces, head.num_joints) == (V, 9976, 5)
    assert (head.num_shape, head.num_expr) == (300, 100)
    np.testing.assert_allclose(head.v_template, model["v_template"], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(head.faces, model["f"])
    np.testing.assert_array_equal(head.parents, [-1, 0, 1, 1, 1])
    np.testing.assert_allclose(head.j_regressor, model["J_regressor"].toarray(), rtol=1e-6)
    # posedirs (V, 3, 36) → (36, V·3): column k of the pickle is row k here
    np.testing.assert_allclose(head.posedirs[7], model["posedirs"][:, :, 7].ravel(), rtol=1e-6)
    _, _, uv, uv_faces, _ = flame_like_mesh()
    np.testing.assert_allclose(head.uv_coords, uv, atol=1e-7)
    np.testing.assert_array_equal(head.uv_faces, uv_faces)


def test_load_flame_without_obj_has_no_uv(files):
    d, _ = files
    head = load_flame(d / "flame2023.pkl")
    assert not head.has_uv and head.uv_coords.shape == (0, 2) and head.vertex_uv.shape == (0, 2)
    assert head.num_vertices == 5143  # teeth geometry still there


def test_obj_with_other_faces_is_rejected(files, tmp_path):
    d, _ = files
    lines = (d / "head_template_mesh.obj").read_text().splitlines()
    first_face = next(i for i, line in enumerate(lines) if line.startswith("f "))
    del lines[first_face]
    bad = tmp_path / "other.obj"
    bad.write_text("\n".join(lines))
    with pytest.raises(InvalidArgumentError, match="faces differ"):
        load_flame(d / "flame2023.pkl", bad)


def test_bad_pickle_key_is_named(files, tmp_path):
    _, model = files
    broken = dict(model, weights=np.ones((10, 5)))
    path = tmp_path / "broken.pkl"
    write_flame2023_pickle(path, broken)
    with pytest.raises(ShapeError, match="'weights'"):
        load_flame(path)
    missing = {k: v for k, v in model.items() if k != "posedirs"}
    write_flame2023_pickle(path, missing)
    with pytest.raises(InvalidArgumentError, match="posedirs"):
        load_flame(path)


@pytest.mark.parametrize("plate", [False, True])
def test_teeth_counts(files, plate):
    d, _ = files
    base = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj", teeth=False)
    head = add_teeth(base, TeethConfig(mouth_plate=plate))
    assert head.num_vertices == 5143
    assert head.num_faces == 10144 + (28 if plate else 0)
    assert head.shapedirs.shape == (5143, 3, 400)
    assert head.posedirs.shape == (36, 5143 * 3)
    np.testing.assert_array_equal(head.j_regressor[:, 5023:], 0)
    np.testing.assert_array_equal(head.posedirs.reshape(36, -1, 3)[:, 5023:], 0)
    np.testing.assert_array_equal(head.shapedirs[5023:, :, 300:], 0)
    # the original part is untouched
    np.testing.assert_array_equal(head.v_template[:5023], base.v_template)
    np.testing.assert_array_equal(head.faces[:9976], base.faces)
    np.testing.assert_array_equal(head.uv_faces[:9976], base.uv_faces)


def test_teeth_geometry_follows_the_vhap_construction(files):
    _, model = files
    rows = teeth_rest_geometry(model["v_template"], TeethConfig())
    up = model["v_template"][list(TeethConfig().upper_lip_ids)]
    low = model["v_template"][list(TeethConfig().lower_lip_ids)]
    d = np.linalg.norm(up - low, axis=1).mean()
    mid_z = (up[:, 2] + low[:, 2]) / 2
    np.testing.assert_allclose(rows["upper_edge"][:, 2], mid_z - 1.5 * d)
    np.testing.assert_allclose(rows["upper_root"][:, 1] - rows["upper_edge"][:, 1], 2 * d)
    np.testing.assert_allclose(rows["upper_edge"][:, 1] - rows["lower_edge"][:, 1], 0.2 * d)
    np.testing.assert_allclose(rows["upper_edge"][:, 2] - rows["lower_edge"][:, 2], 0.4 * d)
    np.testing.assert_allclose(rows["lower_root"][:, 2] - rows["lower_root_back"][:, 2], d)
    assert len(ROW_ORDER) == 8


def _faces_outward(head, start, stop, direction):
    p = head.v_template[head.faces[start:stop]].astype(np.float64)
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(0)
    return n @ direction > 0


def test_teeth_faces_face_outwards_and_plate_faces_the_mouth(files):
    d, _ = files
    head = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj")
    z, y = np.array([0, 0, 1.0]), np.array([0, 1.0, 0])
    s = 9976
    assert _faces_outward(head, s, s + 28, z)  # upper front
    assert _faces_outward(head, s + 28, s + 56, -z)  # upper back
    assert _faces_outward(head, s + 56, s + 84, -y)  # upper biting edge
    assert _faces_outward(head, s + 84, s + 112, z)  # lower front
    assert _faces_outward(head, s + 140, s + 168, y)  # lower biting edge
    assert _faces_outward(head, s + 168, s + 196, z)  # mouth plate


def test_teeth_uv_bands_do_not_overlap(files):
    d, _ = files
    head = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj")
    tri = head.uv_coords[head.uv_faces].astype(np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert np.all(area[9976:] > 0)
    # rasterise at a fine resolution: no texel is covered by two teeth/plate triangles
    res = 2048
    hits = np.zeros((res, res), np.int32)
    for t in tri[9976:]:
        lo = np.floor(t.min(0) * res).astype(int)
        hi = np.ceil(t.max(0) * res).astype(int)
        uu, vv = np.meshgrid(np.arange(lo[0], hi[0]) + 0.5, np.arange(lo[1], hi[1]) + 0.5)
        p = np.stack([uu.ravel(), vv.ravel()], 1) / res
        a, b, c = t
        den = (b - a)[0] * (c - a)[1] - (c - a)[0] * (b - a)[1]
        l1 = ((p - a)[:, 0] * (c - a)[1] - (c - a)[0] * (p - a)[:, 1]) / den
        l2 = ((b - a)[0] * (p - a)[:, 1] - (p - a)[:, 0] * (b - a)[1]) / den
        inside = (l1 > 0) & (l2 > 0) & (l1 + l2 < 1)
        hits[vv.ravel()[inside].astype(int), uu.ravel()[inside].astype(int)] += 1
    assert hits.max() == 1 and hits.sum() > 1000
    # and none of them touches the head's own layout
    box = TeethConfig().uv_box
    head_tri = tri[:9976]
    assert head_tri[:, :, 1].max() < box[1]


def test_teeth_uv_box_overlapping_the_layout_is_rejected(files):
    d, _ = files
    base = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj", teeth=False)
    with pytest.raises(InvalidArgumentError, match="overlaps"):
        add_teeth(base, TeethConfig(uv_box=(0.3, 0.5, 0.6, 0.6)))


def test_teeth_skinning_upper_follows_neck_lower_follows_jaw(files):
    d, _ = files
    head = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj")
    upper = np.r_[5023:5038, 5053:5068, 5083:5113]
    lower = np.setdiff1d(np.arange(5023, 5143), upper)
    pose = torch.zeros(1, 15, dtype=torch.float64)
    pose[0, 3:6] = torch.tensor([0.1, 0.3, -0.05])  # neck
    pose[0, 6:9] = torch.tensor([0.35, 0.02, 0.0])  # jaw open
    out = head.skin(pose=pose)
    joints = out.joints[0].numpy()
    rest = head.v_template.astype(np.float64)
    rest_joints = head.j_regressor.astype(np.float64) @ rest
    r_neck = axis_angle_to_matrix(pose[0, 3:6]).numpy()
    r_jaw = r_neck @ axis_angle_to_matrix(pose[0, 6:9]).numpy()
    want_upper = (rest[upper] - rest_joints[1]) @ r_neck.T + joints[1]
    want_lower = (rest[lower] - rest_joints[2]) @ r_jaw.T + joints[2]
    np.testing.assert_allclose(out.verts[0, upper].numpy(), want_upper, atol=1e-6)
    np.testing.assert_allclose(out.verts[0, lower].numpy(), want_lower, atol=1e-6)
    # opening the jaw moves the lower teeth away from the upper ones
    gap_rest = rest[lower, 1].max() - rest[upper, 1].min()
    closed = head.skin(pose=torch.zeros(1, 15, dtype=torch.float64)).verts[0].numpy()
    jaw_only = torch.zeros(1, 15, dtype=torch.float64)
    jaw_only[0, 6] = 0.35
    opened = head.skin(pose=jaw_only).verts[0].numpy()
    assert gap_rest < 0
    assert np.all(opened[upper] == closed[upper])
    assert opened[lower, 1].mean() < closed[lower, 1].mean() - 0.005


def test_regions_estimated_and_from_masks(files, tmp_path):
    d, _ = files
    head = load_flame(d / "generic_model.pkl", teeth=True)
    eye_ids = np.arange(5023 - 342, 5023)
    assert np.all(head.vertex_region[eye_ids] == 4)
    assert np.all(head.vertex_region[5023:] == 7)
    masks = {
        "face": np.arange(0, 1000),
        "neck": np.arange(1000, 1200),
        "boundary": np.arange(1200, 1210),
        "lips": np.arange(500, 520),
        "left_ear": np.arange(2000, 2050),
        "right_ear": np.arange(2050, 2100),
        "left_eyeball": eye_ids[:171],
        "right_eyeball": eye_ids[171:],
    }
    path = tmp_path / "FLAME_masks.pkl"
    with open(path, "wb") as f:
        pickle.dump(masks, f, protocol=2)
    head = load_flame(d / "generic_model.pkl", masks_path=path, teeth=False)
    r = head.vertex_region
    assert np.all(r[:500] == 0) and np.all(r[500:520] == 5) and np.all(r[1000:1210] == 2)
    assert np.all(r[2000:2100] == 3) and np.all(r[eye_ids] == 4) and np.all(r[3000:3100] == 1)


def test_convert_flame_cli(files, tmp_path, capsys):
    d, _ = files
    out = tmp_path / "out" / "flame.npz"
    code = main(
        ["convert-flame", str(d / "generic_model.pkl"), "--obj", str(d / "head_template_mesh.obj"),
         "-o", str(out)]
    )  # fmt: skip
    assert code == 0 and "5143 vertices" in capsys.readouterr().out
    head = load_head(out)
    direct = load_flame(d / "generic_model.pkl", d / "head_template_mesh.obj")
    for name in ("v_template", "faces", "shapedirs", "uv_coords", "uv_faces", "vertex_uv"):
        np.testing.assert_array_equal(getattr(head, name), getattr(direct, name))
    assert main(["convert-flame", str(d / "flame2023.pkl"), "--no-teeth", "-o", str(out)]) == 0
    assert load_head(out).num_vertices == 5023
    assert main(["convert-flame", str(tmp_path / "missing.pkl"), "-o", str(out)]) == 1
    assert "missing.pkl" in capsys.readouterr().err
