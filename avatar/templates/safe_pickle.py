"""Read the official SMPL-family pickles without chumpy, and without running code.

The MANO / FLAME ``.pkl`` files are Python 2 pickles (read with
``encoding="latin1"``) holding numpy arrays, scipy sparse matrices and chumpy
``Ch`` objects. :class:`RestrictedUnpickler` resolves only an allow-list of
classes: numpy array reconstruction, scipy sparse matrices and every
``chumpy.*`` class, the last two replaced by inert stand-ins that keep the
pickled state; anything else (``os.system``, ``builtins.eval``, ...) raises
``pickle.UnpicklingError``. :func:`to_array` turns a loaded value into a numpy
array.
"""

from __future__ import annotations

import codecs
import copyreg
import pickle
from typing import Any, BinaryIO

import numpy as np
import scipy.sparse as sp

try:  # numpy >= 2 keeps the array machinery in numpy._core
    from numpy._core import multiarray as _multiarray
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]  # the same module, numpy 1.x path


class ChumpyStandIn:
    """Inert stand-in for any ``chumpy`` class: keeps its class name and pickled state."""

    chumpy_class = "Ch"

    def __setstate__(self, state: Any) -> None:
        self.__dict__["_state"] = state if isinstance(state, dict) else {"x": state}

    @property
    def state(self) -> dict[str, Any]:
        return self.__dict__.get("_state", {})


class SparseStandIn:
    """Inert stand-in for a pickled scipy sparse matrix (any scipy version's layout)."""

    sparse_format = "csc"

    def __setstate__(self, state: Any) -> None:
        self.__dict__["_state"] = state if isinstance(state, dict) else {}

    @property
    def state(self) -> dict[str, Any]:
        return self.__dict__.get("_state", {})


_SPARSE_FORMATS = {
    "csc_matrix": "csc",
    "csr_matrix": "csr",
    "coo_matrix": "coo",
    "csc_array": "csc",
    "csr_array": "csr",
    "coo_array": "coo",
}
_NUMPY = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): _multiarray._reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _multiarray._reconstruct,
    ("numpy.core.multiarray", "scalar"): _multiarray.scalar,
    ("numpy._core.multiarray", "scalar"): _multiarray.scalar,
}
_BUILTINS = {"set": set, "frozenset": frozenset, "object": object, "complex": complex, "slice": slice}
_stand_in_cache: dict[tuple[str, str], type] = {}


def _stand_in(base: type, attribute: str, value: str, key: tuple[str, str]) -> type:
    if key not in _stand_in_cache:
        _stand_in_cache[key] = type(key[1], (base,), {attribute: value, "__module__": __name__})
    return _stand_in_cache[key]


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only materialises arrays, sparse matrices and chumpy stand-ins."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _NUMPY:
            return _NUMPY[(module, name)]
        if module.split(".")[0] == "chumpy":
            return _stand_in(ChumpyStandIn, "chumpy_class", name, (module, name))
        if module.startswith("scipy.sparse") and name in _SPARSE_FORMATS:
            return _stand_in(SparseStandIn, "sparse_format", _SPARSE_FORMATS[name], (module, name))
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return copyreg._reconstructor  # type: ignore[attr-defined]  # private, not in typeshed's copyreg stub
        if module == "_codecs" and name == "encode":
            return codecs.encode
        if module in ("__builtin__", "builtins") and name in _BUILTINS:
            return _BUILTINS[name]
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}: not an array, sparse matrix or chumpy object")


def load(stream: BinaryIO) -> Any:
    """Unpickle a Python 2 or 3 pickle with :class:`RestrictedUnpickler` (latin1 strings)."""
    return RestrictedUnpickler(stream, encoding="latin1").load()


def _sparse_to_dense(obj: SparseStandIn) -> np.ndarray:
    s = obj.state
    shape = tuple(int(n) for n in s.get("_shape", s.get("shape", ())))
    if obj.sparse_format == "coo":
        rows, cols = s["coords"] if "coords" in s else (s["row"], s["col"])
        return sp.coo_matrix((s["data"], (rows, cols)), shape=shape).toarray()
    matrix_type = sp.csc_matrix if obj.sparse_format == "csc" else sp.csr_matrix
    return matrix_type((s["data"], s["indices"], s["indptr"]), shape=shape).toarray()


def _chumpy_to_array(obj: ChumpyStandIn) -> np.ndarray:
    s, kind = obj.state, obj.chumpy_class
    if "x" in s:
        return to_array(s["x"])
    if "a" not in s:
        raise ValueError(f"unsupported chumpy object {kind} (no value 'x' and no operand 'a')")
    a = to_array(s["a"])
    if kind == "Reshape":
        return a.reshape(s["newshape"])
    if kind == "transpose":
        return np.transpose(a, s.get("axes"))
    if kind == "Select":
        picked = a.ravel()[np.asarray(s["idxs"])]
        return picked.reshape(s["preferred_shape"]) if "preferred_shape" in s else picked
    raise ValueError(f"unsupported chumpy operation {kind}: re-save the model with plain arrays")


def to_array(value: Any) -> np.ndarray:
    """A loaded value (array, chumpy stand-in, sparse stand-in, nested list) -> numpy array."""
    if isinstance(value, ChumpyStandIn):
        return _chumpy_to_array(value)
    if isinstance(value, SparseStandIn):
        return _sparse_to_dense(value)
    if sp.issparse(value):
        return value.toarray()
    return np.asarray(value)
