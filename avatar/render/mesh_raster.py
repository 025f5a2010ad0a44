"""Supersampled z-buffer rasterizer for triangle meshes (synthetic data only).

This renderer draws the *ground-truth* meshes of the synthetic capture; the
avatar's Gaussians are rendered elsewhere. It is vectorised PyTorch on the CPU,
deterministic, and bounded in memory by processing triangles in chunks
whose total number of candidate samples is capped.

Conventions
-----------
* Camera: pinhole, intrinsics ``K`` (3, 3) and extrinsics ``world_to_cam``
  (4, 4), OpenCV axes: x right, y down, z forward (into the scene). A camera
  space point ``(x, y, z)`` projects to ``u = fx x / z + cx``,
  ``v = fy y / z + cy``.
* Pixels: continuous image coordinates in which pixel ``(row i, col j)`` is the
  unit square ``[j, j + 1) x [i, i + 1)``, so its centre is at
  ``(j + 0.5, i + 0.5)`` ("integer + 0.5" convention). A centred principal
  point is therefore ``cx = W / 2``. With supersampling factor ``s`` each pixel
  holds an ``s x s`` grid of samples at ``(j + (a + 0.5) / s, i + (b + 0.5) / s)``.
* Coverage: a sample is covered when it lies inside a triangle (edges
  inclusive). Per-pixel outputs are box-filtered averages over the ``s^2``
  samples, so ``alpha`` is the fraction of covered samples, which converges to
  the exact area coverage with error O(1/s).
* Depth: camera-space z (metres, not ray length), perspective-correct.
* Near plane: triangles with any vertex at ``z <= near`` are culled (not
  clipped); they contribute nothing and cannot produce NaN/Inf.
* Attribute interpolation is perspective-correct: barycentrics ``b_i`` found in
  screen space are reweighted as ``b_i / z_i`` and renormalised.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor

#: Shader signature: (interpolated attributes (N, C), mesh labels (N,)) -> colours (N, 3).
Shader = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PinholeCamera:
    """A calibrated pinhole camera (OpenCV axes, pixel centres at integer + 0.5).

    Attributes:
        K: (3, 3) intrinsics in pixels.
        world_to_cam: (4, 4) rigid transform from world (metres) to camera space.
        width: image width in pixels.
        height: image height in pixels.
    """

    K: np.ndarray
    world_to_cam: np.ndarray
    width: int
    height: int

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points (..., 3) -> camera-space points (..., 3), same dtype."""
        m = torch.as_tensor(self.world_to_cam, dtype=points.dtype, device=points.device)
        return points @ m[:3, :3].T + m[:3, 3]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points (..., 3) to pixels.

        Returns:
            uv: (..., 2) continuous pixel coordinates (centre convention above);
                undefined (but finite) where ``z <= 0``.
            z: (...,) camera-space depth in metres.
        """
        pc = self.to_camera(points)
        z = pc[..., 2]
        k = torch.as_tensor(self.K, dtype=points.dtype, device=points.device)
        safe_z = torch.where(z > 0, z, torch.ones_like(z))
        u = k[0, 0] * pc[..., 0] / safe_z + k[0, 1] * pc[..., 1] / safe_z + k[0, 2]
        v = k[1, 1] * pc[..., 1] / safe_z + k[1, 2]
        return torch.stack([u, v], dim=-1), z


@dataclass(frozen=True)
class Mesh:
    """One triangle mesh of a scene.

    Attributes:
        vertices: (V, 3) world positions in metres.
        faces: (F, 3) vertex indices.
        attributes: (V, C) per-vertex features to interpolate (colour, normals,
            uv, ...); every mesh of one scene must have the same C.
        label: id written to the label image where this mesh is visible (>= 1;
            0 is the background).
    """

    vertices: ArrayLike
    faces: ArrayLike
    attributes: ArrayLike
    label: int


@dataclass
class SampleBuffer:
    """Visibility at supersampled resolution (Hs = s H, Ws = s W).

    Attributes:
        face: (Hs, Ws) int64 index of the visible triangle in the concatenated
            scene, -1 where no triangle covers the sample.
        bary: (Hs, Ws, 3) perspective-correct barycentrics of the visible
            triangle (zeros where uncovered).
        depth: (Hs, Ws) camera-space z in metres (0 where uncovered).
        labels: (Hs, Ws) int64 mesh label (0 where uncovered).
        supersample: the factor s.
    """

    face: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor
    labels: torch.Tensor
    supersample: int

    @property
    def covered(self) -> torch.Tensor:
        """(Hs, Ws) bool, True where a triangle covers the sample."""
        return self.face >= 0


@dataclass
class RenderOutput:
    """Per-pixel results of :func:`render` at the camera's resolution.

    Attributes:
        rgb: (H, W, 3) shaded colour (linear), composited over the background
            with box-filter antialiasing.
        alpha: (H, W) fraction of the pixel's samples that are covered, in [0, 1].
        depth: (H, W) nearest covered sample's camera z in metres, 0 if none.
        labels: (H, W) int64 majority label over the pixel's samples (background
            0 included in the vote; ties go to the smaller label).
        samples: the supersampled visibility the outputs were resolved from.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    labels: torch.Tensor
    samples: SampleBuffer


@dataclass(frozen=True)
class Scene:
    """Meshes concatenated into one vertex/face list (what :func:`rasterize` drew)."""

    vertices: torch.Tensor  # (V, 3) float64 world
    faces: torch.Tensor  # (F, 3) int64
    attributes: torch.Tensor  # (V, C) float32
    face_labels: torch.Tensor  # (F,) int64


def _tensor(x: ArrayLike, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A tensor of ``dtype`` on ``device`` (numpy inputs are copied, so read-only
    arrays are fine)."""
    if isinstance(x, torch.Tensor):
        return x.to(dtype=dtype, device=device)
    return torch.tensor(np.asarray(x), dtype=dtype, device=device)


def _concat(meshes: Sequence[Mesh], device: torch.device) -> Scene:
    verts, faces, attrs, labels = [], [], [], []
    offset = 0
    for mesh in meshes:
        if mesh.label < 1:
            raise ValueError(f"mesh label must be >= 1 (0 is background), got {mesh.label}")
        v = _tensor(mesh.vertices, torch.float64, device).reshape(-1, 3)
        f = _tensor(mesh.faces, torch.int64, device).reshape(-1, 3)
        a = _tensor(mesh.attributes, torch.float32, device)
        a = a.reshape(v.shape[0], -1)
        verts.append(v)
        faces.append(f + offset)
        attrs.append(a)
        labels.append(torch.full((f.shape[0],), mesh.label, dtype=torch.int64, device=device))
        offset += v.shape[0]
    if not meshes:
        empty = torch.zeros((0, 3), device=device)
        return Scene(empty.double(), empty.long(), empty, torch.zeros(0, dtype=torch.int64))
    channels = {a.shape[1] for a in attrs}
    if len(channels) != 1:
        raise ValueError(f"all meshes need the same number of attribute channels, got {channels}")
    return Scene(torch.cat(verts), torch.cat(faces), torch.cat(attrs), torch.cat(labels))


@dataclass(frozen=True)
class _TriangleSetup:
    """Per-triangle screen-space data for the triangles that survive culling."""

    index: torch.Tensor  # (T,) int64 scene face index
    inv_z: torch.Tensor  # (T, 3) float32 1 / z of each vertex
    x0: torch.Tensor  # (T,) int64 first sample column of the bounding box
    y0: torch.Tensor  # (T,) int64 first sample row
    nx: torch.Tensor  # (T,) int64 bounding box width in samples
    ny: torch.Tensor  # (T,) int64 bounding box height in samples
    bary0: torch.Tensor  # (T, 3) float32 screen barycentrics at sample (x0, y0)
    dbdx: torch.Tensor  # (T, 3) float32 change per sample step in x
    dbdy: torch.Tensor  # (T, 3) float32 change per sample step in y


def _setup_triangles(scene: Scene, camera: PinholeCamera, s: int, near: float, cull_backfaces: bool) -> _TriangleSetup:
    """Project, cull and compute edge equations in supersampled pixel units."""
    pc = camera.to_camera(scene.vertices)  # (V, 3) float64
    uv, z = camera.project(scene.vertices)
    xy = uv * s  # supersampled pixel units; sample centres at integer + 0.5
    tri_xy = xy[scene.faces]  # (F, 3, 2)
    tri_z = z[scene.faces]  # (F, 3)
    area2 = (tri_xy[:, 1, 0] - tri_xy[:, 0, 0]) * (tri_xy[:, 2, 1] - tri_xy[:, 0, 1]) - (
        tri_xy[:, 2, 0] - tri_xy[:, 0, 0]
    ) * (tri_xy[:, 1, 1] - tri_xy[:, 0, 1])
    keep = (tri_z > near).all(dim=1) & (area2.abs() > 1e-9) & torch.isfinite(area2)
    if cull_backfaces:
        tri_pc = pc[scene.faces]
        normal = torch.linalg.cross(tri_pc[:, 1] - tri_pc[:, 0], tri_pc[:, 2] - tri_pc[:, 0])
        keep &= (normal * tri_pc[:, 0]).sum(dim=1) < 0
    hs, ws = camera.height * s, camera.width * s
    lo = tri_xy.amin(dim=1)
    hi = tri_xy.amax(dim=1)
    # Samples j with j + 0.5 in [lo, hi]  <=>  j in [ceil(lo - 0.5), floor(hi - 0.5)].
    x0 = torch.ceil(lo[:, 0] - 0.5).clamp(0, ws)
    x1 = torch.floor(hi[:, 0] - 0.5).clamp(-1, ws - 1)
    y0 = torch.ceil(lo[:, 1] - 0.5).clamp(0, hs)
    y1 = torch.floor(hi[:, 1] - 0.5).clamp(-1, hs - 1)
    keep &= (x1 >= x0) & (y1 >= y0)
    idx = torch.nonzero(keep).squeeze(1)
    p, a2 = tri_xy[idx], area2[idx]
    x0, x1, y0, y1 = x0[idx], x1[idx], y0[idx], y1[idx]
    # Barycentric b_k is the edge function of the edge opposite vertex k over 2*area.
    pa, pb = p[:, [1, 2, 0]], p[:, [2, 0, 1]]  # (T, 3, 2) edge endpoints
    dbdx = (pa[..., 1] - pb[..., 1]) / a2[:, None]
    dbdy = (pb[..., 0] - pa[..., 0]) / a2[:, None]
    ox, oy = x0 + 0.5, y0 + 0.5
    bary0 = (
        (pb[..., 0] - pa[..., 0]) * (oy[:, None] - pa[..., 1]) - (pb[..., 1] - pa[..., 1]) * (ox[:, None] - pa[..., 0])
    ) / a2[:, None]
    return _TriangleSetup(
        index=idx,
        inv_z=(1.0 / tri_z[idx]).float(),
        x0=x0.long(),
        y0=y0.long(),
        nx=(x1 - x0 + 1).long(),
        ny=(y1 - y0 + 1).long(),
        bary0=bary0.float(),
        dbdx=dbdx.float(),
        dbdy=dbdy.float(),
    )


def _chunks(counts: torch.Tensor, budget: int) -> list[tuple[int, int]]:
    """Split triangles into consecutive ranges by where their first sample falls
    in multiples of ``budget``: a range holds at most ``budget`` samples plus
    those of its last triangle (itself bounded by the image size)."""
    if counts.numel() == 0:
        return []
    bucket = (torch.cumsum(counts, 0) - counts) // budget
    _, sizes = torch.unique_consecutive(bucket, return_counts=True)
    ends = torch.cumsum(sizes, 0).tolist()
    return list(zip([0, *ends[:-1]], ends))


def rasterize(
    meshes: Sequence[Mesh],
    camera: PinholeCamera,
    supersample: int = 3,
    near: float = 1e-2,
    cull_backfaces: bool = False,
    max_samples_per_chunk: int = 1 << 20,
) -> tuple[SampleBuffer, Scene]:
    """Z-buffer visibility of the meshes at ``supersample`` times the resolution.

    Args:
        meshes: the scene; triangles of all meshes compete in one z-buffer.
        camera: where to look from.
        supersample: samples per pixel along each axis (s >= 1).
        near: near plane in metres; triangles with a vertex at z <= near are culled.
        cull_backfaces: drop triangles whose right-handed normal
            ``(v1 - v0) x (v2 - v0)`` points away from the camera.
        max_samples_per_chunk: about how many candidate (triangle, sample)
            pairs are held in memory at once (see :func:`_chunks`).

    Returns:
        The sample buffer and the concatenated scene (for attribute lookup).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    device = torch.device("cpu")
    scene = _concat(meshes, device)
    s = supersample
    hs, ws = camera.height * s, camera.width * s
    n_pix = hs * ws
    zbuf = torch.full((n_pix,), float("inf"))
    fbuf = torch.full((n_pix,), -1, dtype=torch.int64)
    bbuf = torch.zeros((n_pix, 3))
    if scene.faces.shape[0] > 0:
        tri = _setup_triangles(scene, camera, s, near, cull_backfaces)
        counts = tri.nx * tri.ny
        for start, stop in _chunks(counts, max_samples_per_chunk):
            _raster_chunk(tri, start, stop, counts[start:stop], ws, zbuf, fbuf, bbuf)
    covered = fbuf >= 0
    labels = torch.zeros(n_pix, dtype=torch.int64)
    if covered.any():
        labels[covered] = scene.face_labels[fbuf[covered]]
    buffer = SampleBuffer(
        face=fbuf.view(hs, ws),
        bary=bbuf.view(hs, ws, 3),
        depth=torch.where(covered, zbuf, torch.zeros_like(zbuf)).view(hs, ws),
        labels=labels.view(hs, ws),
        supersample=s,
    )
    return buffer, scene


def _raster_chunk(
    tri: _TriangleSetup,
    start: int,
    stop: int,
    counts: torch.Tensor,
    ws: int,
    zbuf: torch.Tensor,
    fbuf: torch.Tensor,
    bbuf: torch.Tensor,
) -> None:
    """Rasterize triangles [start, stop) of ``tri`` into the buffers in place."""
    total = int(counts.sum())
    if total == 0:
        return
    local_tri = torch.repeat_interleave(torch.arange(stop - start), counts)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(total) - first[local_tri]
    t = local_tri + start
    nx = tri.nx[t]
    dx, dy = k % nx, k // nx
    b = tri.bary0[t] + tri.dbdx[t] * dx[:, None].float() + tri.dbdy[t] * dy[:, None].float()
    inside = (b >= 0).all(dim=1)
    t, b = t[inside], b[inside]
    pix = (tri.y0[t] + dy[inside]) * ws + tri.x0[t] + dx[inside]
    # Perspective-correct: weights b_k / z_k, depth = 1 / sum(b_k / z_k).
    w = b * tri.inv_z[t]
    inv_depth = w.sum(dim=1)
    keep = inv_depth > 0
    t, w, pix, inv_depth = t[keep], w[keep], pix[keep], inv_depth[keep]
    z = 1.0 / inv_depth
    chunk_min = torch.full_like(zbuf, float("inf")).scatter_reduce(0, pix, z, "amin")
    # A fragment wins if it is the chunk's nearest at its sample and beats earlier chunks;
    # exact ties inside the chunk go to the highest fragment index (deterministic).
    cand = (z == chunk_min[pix]) & (z < zbuf[pix])
    frag = torch.nonzero(cand).squeeze(1)
    best = torch.full_like(fbuf, -1).scatter_reduce(0, pix[frag], frag, "amax")
    winners = best[best >= 0]
    wp = pix[winners]
    zbuf[wp] = z[winners]
    fbuf[wp] = tri.index[t[winners]]
    bbuf[wp] = w[winners] * z[winners, None]


def interpolate(buffer: SampleBuffer, scene: Scene) -> torch.Tensor:
    """Perspective-correct per-sample attributes of the covered samples.

    Returns:
        (N, C) float32 attributes, N = number of covered samples, in row-major
        sample order (matching ``buffer.covered`` as a boolean index).
    """
    mask = buffer.covered
    faces = scene.faces[buffer.face[mask]]  # (N, 3)
    bary = buffer.bary[mask]  # (N, 3)
    attrs = scene.attributes
    out = attrs[faces[:, 0]] * bary[:, 0:1]
    out.addcmul_(attrs[faces[:, 1]], bary[:, 1:2])
    out.addcmul_(attrs[faces[:, 2]], bary[:, 2:3])
    return out


def box_downsample(samples: torch.Tensor, s: int) -> torch.Tensor:
    """Average s x s blocks: (Hs, Ws, ...) -> (Hs / s, Ws / s, ...)."""
    hs, ws = samples.shape[:2]
    rest = samples.shape[2:]
    blocks = samples.reshape(hs // s, s, ws // s, s, *rest)
    return blocks.mean(dim=(1, 3))


def _majority_labels(labels: torch.Tensor, s: int, num_labels: int) -> torch.Tensor:
    """Per-pixel most frequent label among the s x s samples (ties -> smaller)."""
    hs, ws = labels.shape
    blocks = labels.reshape(hs // s, s, ws // s, s)
    counts = torch.stack([(blocks == k).sum(dim=(1, 3), dtype=torch.int32) for k in range(num_labels)], -1)
    return torch.argmax(counts, dim=-1)


def render(
    meshes: Sequence[Mesh],
    camera: PinholeCamera,
    supersample: int = 3,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    shader: Shader | None = None,
    near: float = 1e-2,
    cull_backfaces: bool = False,
    max_samples_per_chunk: int = 1 << 20,
) -> RenderOutput:
    """Render a scene with supersampling antialiasing.

    Args:
        meshes: the scene (see :class:`Mesh`).
        camera: the camera.
        supersample: samples per pixel along each axis.
        background: (3,) linear colour of uncovered samples.
        shader: maps interpolated attributes (N, C) and labels (N,) of covered
            samples to colours (N, 3); if None the first three attribute
            channels are the colour.
        near, cull_backfaces, max_samples_per_chunk: see :func:`rasterize`.

    Returns:
        Per-pixel colour, coverage, depth and labels (see :class:`RenderOutput`).
    """
    buffer, scene = rasterize(meshes, camera, supersample, near, cull_backfaces, max_samples_per_chunk)
    s = supersample
    mask = buffer.covered
    hs, ws = mask.shape
    colour = torch.empty((hs, ws, 3))
    colour[:] = torch.as_tensor(background, dtype=torch.float32)
    if mask.any():
        attrs = interpolate(buffer, scene)
        colour[mask] = attrs[:, :3] if shader is None else shader(attrs, buffer.labels[mask])
    depth = buffer.depth.masked_fill(~mask, float("inf"))
    depth = -torch.nn.functional.max_pool2d(-depth[None, None], s)[0, 0]
    depth = depth.masked_fill(torch.isinf(depth), 0.0)
    num_labels = int(scene.face_labels.max()) + 1 if scene.face_labels.numel() else 1
    return RenderOutput(
        rgb=box_downsample(colour, s),
        alpha=box_downsample(mask.float(), s),
        depth=depth,
        labels=_majority_labels(buffer.labels, s, num_labels),
        samples=buffer,
    )
