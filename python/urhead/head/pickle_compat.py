"""Reading the FLAME model pickles safely, without chumpy.

FLAME 2020's ``generic_model.pkl`` is a Python 2 (latin-1) pickle holding chumpy ``Ch``
objects and a ``scipy.sparse.csc.csc_matrix`` under a module path modern scipy no longer
has; ``flame2023.pkl`` holds plain arrays and a sparse matrix. A pickle can run any
callable it names, so :class:`FlameUnpickler` resolves only an allow-list: numpy's array
and dtype reconstructors, ``copyreg``'s object reconstructor, ``codecs.encode`` (bytes
in protocol-2 pickles written by Python 3), a stub for every chumpy class
(its array is in its state under ``x``) and a stub for scipy's compressed sparse classes
that is rebuilt as a modern ``scipy.sparse.csc_matrix`` / ``csr_matrix``. Anything else is
refused with :class:`pickle.UnpicklingError`.
"""

from __future__ import annotations

import codecs
import copyreg
import pickle

import numpy as np
import scipy.sparse

_RENAMED_MODULES = {"copy_reg": "copyreg", "__builtin__": "builtins"}
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
    """Stands in for any chumpy class; keeps the pickled state (``x`` is the array)."""

    def __init__(self, *args, **kwargs):
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {"x": state}

    def to_array(self) -> np.ndarray:
        state = getattr(self, "state", {})  # unpickling skips __init__
        if "x" not in state:
            raise pickle.UnpicklingError("a chumpy object in the pickle has no array 'x'")
        return np.asarray(to_plain(state["x"]))


class SparseStub:
    """Stands in for scipy's compressed sparse classes under any (old or new) path."""

    format = "csc"

    def __init__(self, *args, **kwargs):
        self.state = {}

    def __setstate__(self, state):
        self.state = state if isinstance(state, dict) else {}

    def to_scipy(self):
        s = getattr(self, "state", {})  # unpickling skips __init__
        shape = s.get("_shape", s.get("shape"))
        missing = [k for k in ("data", "indices", "indptr") if k not in s]
        if shape is None or missing:
            raise pickle.UnpicklingError(
                f"a sparse matrix in the pickle lacks {missing or ['_shape']}"
            )
        parts = (np.asarray(s["data"]), np.asarray(s["indices"]), np.asarray(s["indptr"]))
        shape = tuple(int(d) for d in shape)
        fmt = s.get("format", self.format)
        if fmt == "csr":
            return scipy.sparse.csr_matrix(parts, shape=shape)
        return scipy.sparse.csc_matrix(parts, shape=shape)


def _sparse_stub(fmt: str) -> type:
    return type(f"SparseStub_{fmt}", (SparseStub,), {"format": fmt})


class FlameUnpickler(pickle.Unpickler):
    """A latin-1 unpickler that resolves only the classes a FLAME pickle needs."""

    def __init__(self, file):
        super().__init__(file, encoding="latin1")

    def find_class(self, module, name):
        module = _RENAMED_MODULES.get(module, module)
        if module.split(".")[0] == "chumpy":
            return ChumpyStub
        if module in _SPARSE_MODULES and name in _SPARSE_CLASSES:
            return _sparse_stub(name[:3])
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
        if module == "builtins" and name == "object":
            return object
        if module == "_codecs" and name == "encode":  # bytes in Python 3 protocol-2 pickles
            return codecs.encode
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a FLAME pickle")


def load_flame_pickle(path) -> dict:
    """The FLAME pickle at ``path`` as a dict of plain numpy arrays and scipy sparse
    matrices (chumpy objects replaced by their arrays)."""
    with open(path, "rb") as f:
        raw = FlameUnpickler(f).load()
    if not isinstance(raw, dict):
        raise pickle.UnpicklingError(f"{path}: expected a dict, got {type(raw).__name__}")
    return {str(k): to_plain(v) for k, v in raw.items()}


def to_plain(value):
    """Chumpy stubs → arrays, sparse stubs → scipy matrices; other values unchanged."""
    if isinstance(value, ChumpyStub):
        return value.to_array()
    if isinstance(value, SparseStub):
        return value.to_scipy()
    return value
