"""3DGS-standard PLY for Gaussians, the format common splat viewers open.

Binary little-endian vertex element with float32 properties, in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3``
where colours are degree-0 SH coefficients (``rgb = 0.5 + C0 * f_dc``), higher
SH bands are stored channel-major as in the reference implementation,
``opacity`` is a logit, ``scale_*`` are log-scales and ``rot_*`` a quaternion
(w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_schemas.tables import SchemaError
from data_schemas.writes import write_bytes

SH_C0 = 0.28209479177387814


@dataclass
class GaussianCloud:
    """Gaussians in the 3DGS parameterisation.

    Attributes:
        means: (N, 3) world positions.
        log_scales: (N, 3) log of the standard deviations along the local axes.
        quats: (N, 4) rotations (w, x, y, z), need not be normalised.
        opacity_logits: (N,) logit of the opacity.
        sh_dc: (N, 3) degree-0 SH coefficients.
        sh_rest: (N, K-1, 3) higher-band SH coefficients (K-1 may be 0).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.means)
        expected = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,), "sh_dc": (n, 3)}
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise SchemaError(f"GaussianCloud.{name}: expected shape {shape}, got {np.shape(getattr(self, name))}")
        if self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3:
            raise SchemaError(f"GaussianCloud.sh_rest: expected (N, K-1, 3), got {self.sh_rest.shape}")

    @classmethod
    def from_rgb(
        cls,
        means: np.ndarray,
        log_scales: np.ndarray,
        quats: np.ndarray,
        opacity_logits: np.ndarray,
        rgb: np.ndarray,
        sh_degree: int = 0,
    ) -> GaussianCloud:
        """Build from linear colours in [0, 1] (N, 3); higher SH bands of ``sh_degree`` are zero."""
        rest = np.zeros((len(means), (sh_degree + 1) ** 2 - 1, 3), np.float32)
        return cls(means, log_scales, quats, opacity_logits, (np.asarray(rgb) - 0.5) / SH_C0, rest)

    def rgb(self) -> np.ndarray:
        """Degree-0 colour (N, 3)."""
        return 0.5 + SH_C0 * self.sh_dc


def _property_names(n_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_gaussians_ply(path: str | Path, cloud: GaussianCloud) -> None:
    path = Path(path)
    n, n_rest = len(cloud.means), cloud.sh_rest.shape[1]
    rest = np.transpose(cloud.sh_rest, (0, 2, 1)).reshape(n, -1)  # channel-major, as the reference code
    columns = [
        cloud.means,
        np.zeros((n, 3)),
        cloud.sh_dc,
        rest,
        cloud.opacity_logits[:, None],
        cloud.log_scales,
        cloud.quats,
    ]
    data = np.concatenate([np.asarray(c, dtype=np.float32).reshape(n, -1) for c in columns], axis=1)
    if not np.isfinite(data).all():
        raise SchemaError(f"{path}: Gaussians contain NaN or Inf; refusing to write a broken PLY")
    names = _property_names(n_rest)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    write_bytes(path, header.encode("ascii") + np.ascontiguousarray(data, dtype="<f4").tobytes(), "Gaussian PLY")


def read_gaussians_ply(path: str | Path) -> GaussianCloud:
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: missing Gaussian PLY")
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise SchemaError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise SchemaError(f"{path}: expected binary_little_endian PLY")
    try:
        n = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    except (StopIteration, ValueError, IndexError) as exc:
        raise SchemaError(f"{path}: no vertex element in the header") from exc
    props = [line.split() for line in header if line.startswith("property")]
    if any(p[1] != "float" for p in props):
        raise SchemaError(f"{path}: every property must be float32 in a 3DGS PLY")
    names = [p[2] for p in props]
    n_rest = sum(name.startswith("f_rest_") for name in names) // 3
    if names != _property_names(n_rest):
        raise SchemaError(f"{path}: properties {names[:12]}... are not the 3DGS layout")
    body = raw[end + len(b"end_header\n") :]
    if len(body) != n * len(names) * 4:
        raise SchemaError(f"{path}: truncated: expected {n} vertices of {len(names)} floats")
    data = np.frombuffer(body, dtype="<f4").reshape(n, len(names)).astype(np.float32)
    col = {name: i for i, name in enumerate(names)}
    rest = data[:, col["f_dc_2"] + 1 : col["opacity"]].reshape(n, 3, n_rest).transpose(0, 2, 1)
    return GaussianCloud(
        means=data[:, 0:3],
        log_scales=data[:, col["scale_0"] : col["scale_2"] + 1],
        quats=data[:, col["rot_0"] : col["rot_3"] + 1],
        opacity_logits=data[:, col["opacity"]],
        sh_dc=data[:, col["f_dc_0"] : col["f_dc_2"] + 1],
        sh_rest=np.ascontiguousarray(rest),
    )
