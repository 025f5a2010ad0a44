"""Per-vertex attachment stiffness of the face from its soft-tissue thickness (skin-to-skull distance).

Thin tissue over bone (forehead, nose bridge) is stiff; thick tissue (cheeks) is soft, as in DECAF:
``k_i = attach_stiffness * (reference_thickness / max(h_i, MIN_THICKNESS_M)) ** stiffness_power``.

Where the thickness comes from, in order (:func:`face_relative_stiffness`):

1. ``model.face_stiffness_path``: a ``.npy`` file with V skin thicknesses in metres, or a ``.npz``
   with ``thickness_m`` (V,) metres or ``stiffness`` (V,) attachment stiffness relative to
   ``attach_stiffness`` (1 = a vertex of reference thickness; 0 = free to move);
2. the template's ``inner_distance`` (the procedural head carries it);
3. the fallback: a uniform :data:`FALLBACK_THICKNESS_M` (the official FLAME has no skull), i.e. one
   stiffness everywhere. The report says which was used.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Uniform fallback thickness (metres): the median soft-tissue depth of the procedural face
#: (6 mm forehead, 8-9 mm nose and chin, 12-22 mm cheeks).
FALLBACK_THICKNESS_M = 0.010
#: Thinner tissue counts as this thin (bone right under the skin: stiff, but finite).
MIN_THICKNESS_M = 0.001


class StiffnessFileError(ValueError):
    """A face stiffness file that cannot be used (names the file and what is wrong)."""


def relative_stiffness(thickness: np.ndarray, reference_thickness: float, power: float) -> np.ndarray:
    """(V,) attachment stiffness relative to a vertex of reference thickness, from thickness (V,) metres."""
    return (reference_thickness / np.maximum(thickness, MIN_THICKNESS_M)) ** power


def _read_file(path: Path, num_vertices: int, reference_thickness: float, power: float) -> np.ndarray:
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise StiffnessFileError(f"{path}: cannot read the face stiffness file ({exc})") from exc
    if isinstance(data, np.lib.npyio.NpzFile):
        with data:
            if "stiffness" in data:
                values, relative = np.asarray(data["stiffness"], dtype=np.float64), True
            elif "thickness_m" in data:
                values, relative = np.asarray(data["thickness_m"], dtype=np.float64), False
            else:
                raise StiffnessFileError(
                    f"{path}: an .npz face stiffness file needs an array 'stiffness' or "
                    f"'thickness_m'; it has {sorted(data.files)}"
                )
    else:
        values, relative = np.asarray(data, dtype=np.float64), False
    if values.shape != (num_vertices,):
        raise StiffnessFileError(
            f"{path}: {values.shape} values, but the head model has {num_vertices} vertices; give one value per vertex"
        )
    if not np.isfinite(values).all() or (values < 0).any():
        raise StiffnessFileError(f"{path}: values must be finite and non-negative")
    return values if relative else relative_stiffness(values, reference_thickness, power)


def face_relative_stiffness(
    num_vertices: int,
    inner_distance: np.ndarray | None,
    path: str | Path | None,
    reference_thickness: float,
    power: float,
) -> tuple[np.ndarray, str]:
    """(V,) relative attachment stiffness and where it came from (``file:<name>``, ``template`` or
    ``fallback_uniform``); see the module docstring for the order."""
    if path:
        return _read_file(Path(path), num_vertices, reference_thickness, power), f"file:{Path(path).name}"
    if inner_distance is not None:
        return relative_stiffness(np.asarray(inner_distance), reference_thickness, power), "template"
    return relative_stiffness(
        np.full(num_vertices, FALLBACK_THICKNESS_M), reference_thickness, power
    ), "fallback_uniform"
