"""gsplat's ``rasterization`` on the CPU: its pure-PyTorch reference with the CUDA-only pieces replaced.

gsplat ships ``gsplat.rendering._rasterization``, "a version of rasterization() that relies on PyTorch's
autograd", built on ``gsplat.cuda._torch_impl`` (projection, tile intersection, alpha compositing). Three
of its calls still need CUDA or another package, and :func:`gsplat_on_cpu` swaps each for a PyTorch
equivalent for the duration of a ``with`` block:

* ``isect_tiles`` / ``isect_offset_encode`` (the CUDA wrappers): gsplat's own torch version
  ``_isect_offset_encode``, and :func:`isect_tiles`, its ``_isect_tiles`` without the Python loop over every
  (Gaussian, tile) pair (too slow for ten thousand Gaussians; checked against it) and with a stable sort;
* ``rasterize_to_indices_in_range`` (CUDA kernel ``rasterize_to_indices_3dgs``): :func:`indices_in_range`
  below, a line-by-line transcription of that kernel (pixel centre ``(j + 0.5, i + 0.5)``, ``alpha =
  min(0.999, o exp(-sigma))``, skip ``sigma < 0`` or ``alpha < 1/255``, stop before the Gaussian that takes
  the transmittance to ``<= 1e-4``), listing the intersections pixel by pixel, nearest first;
* ``nerfacc.render_weight_from_alpha`` / ``accumulate_along_rays`` (imported by ``_torch_impl.accumulate``):
  :class:`_NerfaccOnCpu`, their packed-ray definitions (weights ``w_k = alpha_k prod_{l<k} (1 - alpha_l)``
  per ray, then per-ray sums).

``gsplat.rasterization`` itself is replaced by ``_rasterization`` (which takes the same arguments except
``packed``, ignored: the unpacked layout is what it computes), so the adapter
``avatar.render.gaussians.backend_gsplat.render_gsplat`` runs unchanged.

The torch reference bounds every Gaussian at 3.33 sigma; the CUDA projection (gsplat 1.5) at the
opacity-aware extent ``min(3.33, sqrt(2 ln(255 o)))`` sigma and culls ``o < 1/255``, as the project's own
backends: :func:`opacity_aware_radii` recomputes the returned radii by the CUDA rule (the images do not change:
pixels between the two boxes have ``alpha < 1/255`` and are skipped either way). What this stand-in cannot
show is the CUDA kernels' own rounding (``__expf``, fast math): the CUDA-marked tests compare those on a GPU.
"""

from __future__ import annotations

import contextlib
import sys
import types
from collections.abc import Iterator

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's include/Common.h
TRANSMITTANCE_STOP = 1e-4  # rasterize_to_indices_3dgs: a pixel is done once T would drop to <= this
MAX_ALPHA = 0.999


def indices_in_range(
    range_start: int,
    range_end: int,
    transmittances: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """PyTorch transcription of gsplat's ``rasterize_to_indices_in_range`` (same arguments and returns).

    Args:
        transmittances: (I, H, W) each pixel's transmittance before batch ``range_start``.
        means2d, conics, opacities: (I, N, 2), (I, N, 3), (I, N) in gsplat's pixel frame.
        isect_offsets: (I, TH, TW) first intersection of each tile; flatten_ids: (n_isects,) in [0, I N).

    Returns:
        gaussian_ids, pixel_ids, image_ids: (M,) int64 each, the contributing (Gaussian, pixel) pairs of the
        batches ``[range_start, range_end)`` of 256 intersections per tile, pixel by pixel (row-major,
        image-major), nearest Gaussian first: the order the CUDA kernel writes them in.
    """
    num_images, num_gaussians = means2d.shape[0], means2d.shape[1]
    tile_h, tile_w = isect_offsets.shape[-2:]
    block = tile_size * tile_size
    offsets = torch.cat([isect_offsets.flatten().long(), torch.tensor([flatten_ids.numel()])])
    flat_means, flat_conics = means2d.reshape(-1, 2), conics.reshape(-1, 3)
    flat_opacities = opacities.reshape(-1)
    rows = []
    for image in range(num_images):
        for tile in range(tile_h * tile_w):
            start, end = int(offsets[image * tile_h * tile_w + tile]), int(offsets[image * tile_h * tile_w + tile + 1])
            first, last = start + block * range_start, min(end, start + block * range_end)
            if first >= last:
                continue
            ty, tx = divmod(tile, tile_w)
            ii, jj = torch.meshgrid(
                torch.arange(ty * tile_size, min((ty + 1) * tile_size, image_height)),
                torch.arange(tx * tile_size, min((tx + 1) * tile_size, image_width)),
                indexing="ij",
            )
            ii, jj = ii.flatten(), jj.flatten()
            ids = flatten_ids[first:last].long()  # (K,) nearest first
            dx = flat_means[ids, 0][None, :] - (jj.to(means2d.dtype)[:, None] + 0.5)  # (P, K)
            dy = flat_means[ids, 1][None, :] - (ii.to(means2d.dtype)[:, None] + 0.5)
            c = flat_conics[ids]
            sigma = 0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) + c[:, 1] * dx * dy
            alpha = torch.clamp_max(flat_opacities[ids] * torch.exp(-sigma), MAX_ALPHA)
            contributes = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
            factors = torch.where(contributes, 1.0 - alpha, torch.ones_like(alpha))
            trans = transmittances[image, ii, jj][:, None] * torch.cumprod(factors, dim=1)  # T after each
            stops = contributes & (trans <= TRANSMITTANCE_STOP)
            first_stop = torch.where(stops.any(1), stops.float().argmax(1), torch.full_like(ii, ids.numel()))
            keep = contributes & (torch.arange(ids.numel())[None, :] < first_stop[:, None])
            pixel, k = keep.nonzero(as_tuple=True)
            pixel_id = ii[pixel] * image_width + jj[pixel]
            rows.append(torch.stack([torch.full_like(pixel_id, image), pixel_id, k, ids[k] % num_gaussians], 1))
    if not rows:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty, empty
    table = torch.cat(rows)
    pixel_key = table[:, 0] * (image_height * image_width) + table[:, 1]
    table = table[torch.argsort(pixel_key * (int(table[:, 2].max()) + 1) + table[:, 2])]
    return table[:, 3], table[:, 1], table[:, 0]


def _segments(ray_indices: Tensor, n_rays: int) -> tuple[Tensor, Tensor]:
    """(M,) sorted ray ids -> each entry's position within its ray (M,) and the longest ray's length."""
    counts = torch.bincount(ray_indices, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    position = torch.arange(ray_indices.numel()) - starts[ray_indices]
    return position, int(counts.max()) if counts.numel() else 0


class _NerfaccOnCpu(types.ModuleType):
    """The two ``nerfacc`` functions ``gsplat.cuda._torch_impl.accumulate`` imports, for packed rays
    (entries of one ray contiguous and in compositing order), in PyTorch."""

    def __init__(self) -> None:
        super().__init__("nerfacc")

    @staticmethod
    def render_weight_from_alpha(alphas: Tensor, ray_indices: Tensor, n_rays: int) -> tuple[Tensor, Tensor]:
        """alphas (M,) -> weights ``alpha_k T_k`` (M,) and transmittances ``T_k = prod_{l<k} (1 - alpha_l)``."""
        position, longest = _segments(ray_indices, n_rays)
        grid = alphas.new_ones(n_rays, longest + 1)
        grid = grid.index_put((ray_indices, position + 1), 1.0 - alphas)
        trans = torch.cumprod(grid, dim=1)[ray_indices, position]
        return alphas * trans, trans

    @staticmethod
    def accumulate_along_rays(weights: Tensor, values: Tensor | None, ray_indices: Tensor, n_rays: int) -> Tensor:
        """Per-ray sums of ``weights`` (M,) times ``values`` (M, C) -> (n_rays, C); values None: (n_rays, 1)."""
        src = weights[:, None] if values is None else weights[:, None] * values
        return src.new_zeros(n_rays, src.shape[1]).index_add(0, ray_indices, src)


def opacity_aware_radii(
    radii: Tensor,
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
) -> Tensor:
    """The CUDA projection's radii: per axis ``ceil(extent sqrt(cov_aa + eps2d))`` of gsplat's own 2D
    covariance (its torch functions), ``extent = min(3.33, sqrt(2 ln(o / (1/255))))``, 0 where ``o < 1/255``
    or the reference culled.

    Args:
        radii: (C, N, 2) the reference's (3.33 sigma for every Gaussian, 0 where culled); means, quats, scales,
            opacities: (N, 3), (N, 4), (N, 3), (N,); viewmats, Ks: (C, 4, 4), (C, 3, 3).
    """
    from gsplat.cuda._torch_impl import _persp_proj, _quat_scale_to_covar_preci, _world_to_cam

    covars, _ = _quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    means_c, covars_c = _world_to_cam(means, covars, viewmats)
    _, covars2d = _persp_proj(means_c, covars_c, Ks, width, height)
    cov_diag = covars2d.diagonal(dim1=-2, dim2=-1) + eps2d  # (C, N, 2)
    extent = torch.sqrt(2.0 * torch.log(opacities.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp_max(3.33)
    aware = torch.ceil(extent[:, None] * torch.sqrt(cov_diag)).clamp_max(2**31 - 1).to(radii.dtype)
    keep = (radii > 0).all(-1, keepdim=True) & (opacities >= ALPHA_THRESHOLD)[:, None]
    return torch.where(keep, aware, torch.zeros_like(aware))


def isect_tiles(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    tile_size: int,
    tile_width: int,
    tile_height: int,
    sort: bool = True,
    **_unpacked_only: object,
) -> tuple[Tensor, Tensor, Tensor]:
    """gsplat's ``_torch_impl._isect_tiles`` without its Python loop over Gaussians and tiles (the same tile
    boxes, keys and layout; a test checks it against gsplat's), sorted stably as the CUDA path's radix sort:
    Gaussians at equal depth keep their index order (the reference's ``torch.sort`` does not promise it).

    Args:
        means2d: (I, N, 2); radii: (I, N, 2) int; depths: (I, N).

    Returns:
        tiles_per_gauss (I, N) int32, isect_ids (n_isects,) int64 ``image | tile | float32 depth bits``,
        flatten_ids (n_isects,) int32 indices into ``I N``.
    """
    num_images, n = means2d.shape[0], means2d.shape[-2]
    tile_means, tile_radii = means2d.reshape(-1, 2) / tile_size, radii.reshape(-1, 2) / tile_size
    limits = torch.tensor([tile_width, tile_height])
    lo = torch.minimum(torch.floor(tile_means - tile_radii).int().clamp_min(0), limits)
    hi = torch.minimum(torch.ceil(tile_means + tile_radii).int().clamp_min(0), limits)
    counts = (hi - lo).prod(-1) * (radii.reshape(-1, 2) > 0).all(-1)
    flatten_ids = torch.repeat_interleave(torch.arange(num_images * n), counts)
    within = torch.arange(flatten_ids.numel()) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    span_x = (hi - lo)[flatten_ids, 0]
    x, y = lo[flatten_ids, 0] + within % span_x.clamp_min(1), lo[flatten_ids, 1] + within // span_x.clamp_min(1)
    tile_bits = (tile_width * tile_height).bit_length()
    depth_bits = depths.reshape(-1).float().contiguous().view(torch.int32).long() & 0xFFFFFFFF
    image = flatten_ids // n
    isect_ids = ((image << tile_bits) | (y * tile_width + x).long()) << 32 | depth_bits[flatten_ids]
    if sort:
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return counts.reshape(radii.shape[:-1]).int(), isect_ids, flatten_ids.int()


def _isect_offset_encode(isect_ids: Tensor, n_images: int, tile_width: int, tile_height: int) -> Tensor:
    from gsplat.cuda._torch_impl import _isect_offset_encode as reference

    return reference(isect_ids, n_images, tile_width, tile_height)


def _rasterization(*, packed: bool = False, **kwargs: Tensor) -> tuple[Tensor, Tensor, dict]:
    """``_rasterization`` with ``rasterization``'s arguments. Where no Gaussian touches a pixel the
    reference's images hang off no graph, whereas the CUDA op's always do (with zero gradients): a zero
    term of every differentiable input keeps ``backward()`` working as on CUDA."""
    from gsplat.rendering import _rasterization as reference

    colors, alphas, meta = reference(**kwargs)
    with torch.no_grad():
        meta["radii"] = opacity_aware_radii(
            meta["radii"],
            *(kwargs[k].detach() for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks")),
            kwargs["width"],
            kwargs["height"],
        )
    zero = sum((kwargs[name] * 0).sum() for name in ("means", "quats", "scales", "opacities", "colors"))
    return colors + zero, alphas + zero, meta


@contextlib.contextmanager
def gsplat_on_cpu() -> Iterator[None]:
    """Within the block, ``gsplat.rasterization`` is gsplat's PyTorch reference and runs on CPU tensors."""
    import gsplat
    import gsplat.cuda._wrapper as wrapper
    import gsplat.rendering as rendering

    patches = [
        (gsplat, "rasterization", _rasterization),
        (rendering, "isect_tiles", isect_tiles),
        (rendering, "isect_offset_encode", _isect_offset_encode),
        (wrapper, "rasterize_to_indices_in_range", indices_in_range),
    ]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    saved_nerfacc = sys.modules.get("nerfacc")
    try:
        for owner, name, value in patches:
            setattr(owner, name, value)
        sys.modules["nerfacc"] = _NerfaccOnCpu()
        yield
    finally:
        for owner, name, value in saved:
            setattr(owner, name, value)
        if saved_nerfacc is None:
            sys.modules.pop("nerfacc", None)
        else:
            sys.modules["nerfacc"] = saved_nerfacc
