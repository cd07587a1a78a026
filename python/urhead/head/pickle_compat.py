"""Reading the FLAME model pickles safely, without chumpy.

FLAME 2020's ``generic_model.pkl`` is a Python 2 (latin-1, protocol 2) pickle holding
chumpy objects and a ``scipy.sparse.csc.csc_matrix`` under a module path modern scipy no
longer has. A chumpy object is pickled with its whole instance state — chumpy's
``__getstate__`` is the instance ``__dict__`` less ``_parents`` and ``_cache``: the array
``x``, ``_dirty_vars`` (a ``set``, written as ``__builtin__.set``), ``_itr``,
``_depends_on_deps`` (a dict), flags, and a subclass's own terms.

A pickle can run any callable it names, so :class:`FlameUnpickler` resolves only an
allow-list:

- data-only builtins: ``set``, ``frozenset``, ``complex`` and ``object`` (under Python 2's
  ``__builtin__`` or Python 3's ``builtins``); nothing that evaluates, imports or reaches
  attributes (``eval``, ``getattr``, ``__import__`` … stay refused);
- numpy's array, scalar and dtype reconstructors, ``copyreg``'s (``copy_reg``'s) object
  reconstructor, ``codecs.encode`` (bytes in protocol-2 pickles written by Python 3);
- a stub for every ``chumpy.*`` class, which only keeps the state it is given (the array
  is under ``x``), and a stub for scipy's compressed sparse classes under any path, rebuilt
  as a modern ``csc_matrix`` / ``csr_matrix`` once its parts are checked.

Anything else is refused with :class:`urhead.errors.UnsafePickleError` (a
:class:`pickle.UnpicklingError`).
"""

from __future__ import annotations

import codecs
import copyreg
import pickle

import numpy as np
import scipy.sparse

from urhead.errors import UnsafePickleError, reading

_RENAMED_MODULES = {"copy_reg": "copyreg", "__builtin__": "builtins"}
_DATA_BUILTINS = {"set": set, "frozenset": frozenset, "complex": complex, "object": object}
_NUMPY_CORE = ("numpy.core.multiarray", "numpy._core.multiarray")
_NUMPY_NUMERIC = ("numpy.core.numeric", "numpy._core.numeric")
_SPARSE_MODULES = {
    "scipy.sparse.csc",
    "scipy.sparse._csc",
    "scipy.sparse.csr",
    "scipy.sparse._csr",
    "scipy.sparse.compressed",
    "scipy.sparse._compressed",
}
_SPARSE_CLASSES = {"csc_matrix", "csr_matrix", "csc_array", "csr_array"}


class ChumpyStub:
    """Stands in for a chumpy class (``chumpy_class`` names it); keeps the pickled state.
    Only the array under ``x`` is ever used: a chumpy expression without one (a
    ``Select``, a product …) stays a stub, and reading it as an array is an error."""

    chumpy_class = "chumpy"

    def __init__(self, *args, **kwargs):
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {"x": state}

    @property
    def has_array(self) -> bool:
        return "x" in getattr(self, "state", {})  # unpickling skips __init__

    def to_array(self) -> np.ndarray:
        if not self.has_array:
            raise pickle.UnpicklingError(f"{self!r} holds no array 'x'")
        return np.asarray(to_plain(self.state["x"]))

    def __repr__(self) -> str:
        what = "with" if self.has_array else "without"
        return f"<{self.chumpy_class} {what} an array 'x'>"


class SparseStub:
    """Stands in for scipy's compressed sparse classes under any (old or new) path."""

    format = "csc"

    def __init__(self, *args, **kwargs):
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {}

    def to_scipy(self):
        """The checked parts as a modern scipy matrix (a pickle is untrusted input: the
        parts are validated before scipy sees them)."""
        s = getattr(self, "state", {})  # unpickling skips __init__
        shape = s.get("_shape", s.get("shape"))
        missing = [k for k in ("data", "indices", "indptr") if k not in s]
        if shape is None or missing:
            raise pickle.UnpicklingError(
                f"a sparse matrix in the pickle lacks {missing or ['_shape']}"
            )
        fmt = s.get("format", self.format)
        if fmt not in ("csc", "csr"):
            raise pickle.UnpicklingError(f"a sparse matrix in the pickle has format {fmt!r}")
        data, indices, indptr, shape = _checked_sparse_parts(
            s["data"], s["indices"], s["indptr"], shape, fmt
        )
        build = scipy.sparse.csr_matrix if fmt == "csr" else scipy.sparse.csc_matrix
        return build((data, indices, indptr), shape=shape)


def _checked_sparse_parts(data, indices, indptr, shape, fmt: str):
    def bad(what: str):
        return pickle.UnpicklingError(f"a {fmt} sparse matrix in the pickle {what}")

    try:
        rows, cols = (int(d) for d in shape)
    except (TypeError, ValueError):
        raise bad(f"has the shape {shape!r}") from None
    if rows < 0 or cols < 0:
        raise bad(f"has the shape {shape!r}")
    data, indices, indptr = np.asarray(data), np.asarray(indices), np.asarray(indptr)
    if data.ndim != 1 or data.dtype.kind not in "fiub":
        raise bad(f"has data of shape {data.shape} and dtype {data.dtype}")
    for name, a in (("indices", indices), ("indptr", indptr)):
        if a.ndim != 1 or a.dtype.kind not in "iu":
            raise bad(f"has {name} of shape {a.shape} and dtype {a.dtype}")
    major, minor = (cols, rows) if fmt == "csc" else (rows, cols)
    if indptr.shape[0] != major + 1 or indptr[0] != 0:
        raise bad(f"has indptr of length {indptr.shape[0]} starting at {indptr[:1]}")
    if np.any(np.diff(indptr.astype(np.int64)) < 0):
        raise bad("has an indptr that decreases")
    if not indptr[-1] == len(indices) == len(data):
        raise bad(f"has {len(data)} values, {len(indices)} indices, indptr ending at {indptr[-1]}")
    if indices.size and (indices.min() < 0 or indices.max() >= minor):
        raise bad(f"has indices outside [0, {minor})")
    return data, indices.astype(np.int64), indptr.astype(np.int64), (rows, cols)


def _chumpy_stub(module: str, name: str) -> type:
    return type(f"ChumpyStub_{name}", (ChumpyStub,), {"chumpy_class": f"{module}.{name}"})


def _sparse_stub(fmt: str) -> type:
    return type(f"SparseStub_{fmt}", (SparseStub,), {"format": fmt})


class FlameUnpickler(pickle.Unpickler):
    """A latin-1 unpickler that resolves only the classes a FLAME pickle needs."""

    def __init__(self, file):
        super().__init__(file, encoding="latin1")

    def find_class(self, module, name):
        module = _RENAMED_MODULES.get(module, module)
        if module.split(".")[0] == "chumpy":
            return _chumpy_stub(module, name)
        if module in _SPARSE_MODULES and name in _SPARSE_CLASSES:
            return _sparse_stub(name[:3])
        if module == "builtins" and name in _DATA_BUILTINS:
            return _DATA_BUILTINS[name]
        if module in _NUMPY_CORE and name in ("_reconstruct", "scalar"):
            from numpy._core import multiarray

            return getattr(multiarray, name)
        if module in _NUMPY_NUMERIC and name == "_frombuffer":  # protocol-5 arrays
            from numpy._core import numeric

            return numeric._frombuffer
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module.startswith("numpy") and name == "dtype":
            return np.dtype
        if module == "copyreg" and name == "_reconstructor":
            return copyreg._reconstructor
        if module == "_codecs" and name == "encode":  # bytes in Python 3 protocol-2 pickles
            return codecs.encode
        raise UnsafePickleError(f"refusing to load {module}.{name} from a FLAME pickle")


def load_flame_pickle(path) -> dict:
    """The FLAME pickle at ``path`` as a dict of plain numpy arrays and scipy sparse
    matrices (chumpy objects replaced by their arrays; a chumpy expression without an
    array stays a :class:`ChumpyStub`)."""
    with reading(path, "FLAME pickle"):
        with open(path, "rb") as f:
            raw = FlameUnpickler(f).load()
        if not isinstance(raw, dict):
            raise pickle.UnpicklingError(f"expected a dict, got {type(raw).__name__}")
        return {str(k): to_plain(v) for k, v in raw.items()}


def to_plain(value):
    """Chumpy stubs with an array → the array, sparse stubs → scipy matrices; other values
    (chumpy expressions without an array included) unchanged."""
    if isinstance(value, ChumpyStub) and value.has_array:
        return value.to_array()
    if isinstance(value, SparseStub):
        return value.to_scipy()
    return value
