"""PointNet++ geometry encoder (Qi et al. 2017, single-scale grouping, classification-style), in pure torch.

The paper's global geometry feature F in R^1024 is computed over one small point set (sampled Gaussians
of the hand and of the deforming face region; 0 to ~8000 points), so everything here works on a single
unbatched set: points (N, 3) in, a vector (feature_dim,) out. No compiled kernels: farthest point
sampling is one python loop over the samples with O(N) tensor ops each, the ball query runs on
(chunk, N) distance blocks of bounded size.

Design choices:

* **No BatchNorm.** The reference uses 1x1 convolutions with BatchNorm over a batch of clouds. Here
  there is one set per call, so the batch statistics would be those of the neighbourhoods of this
  one set (train and eval would then differ, and a set of one or two identical points gives a zero
  variance). The shared MLPs are ``Linear -> LayerNorm -> ReLU`` per layer instead: LayerNorm
  normalises each point's feature vector on its own, so it behaves the same for any set size,
  in training and in evaluation.
* **Coordinate normalisation.** The encoder divides its input by ``scale`` (the caller passes points
  in metres relative to the head and e.g. ``scale=0.1``, so the hand/face region is of unit size;
  the radii are in those units). Each set abstraction then groups neighbour coordinates relative to
  their centre divided by the ball radius, so the first layer of every local MLP sees values in
  [-1, 1] whatever the level.
* **Empty set.** Every shared MLP ends in a ReLU, so a max-pool over points is >= 0 and the max over
  the empty set is naturally 0. The encoder adds a learned offset ``empty`` (feature_dim,) to the
  pooled vector: an empty input returns exactly ``empty`` (finite, differentiable), and since the
  offset is added for every input, it receives a gradient for non-empty inputs too.
* **Order of the input points.** The encoder's output does not depend on the order of its input
  points, exactly (bitwise), ties included. Two steps of PointNet++ depend on the order: FPS starts
  from a given index and breaks ties by index, and the ball query keeps the *first* K points (in index
  order) inside each ball, so choosing the FPS start order-independently is not enough once balls
  hold more than K points. The encoder therefore first puts the points into a canonical order
  (``canonical_order``: sorted by a hash of their coordinates, ties broken by the coordinates), which
  depends only on the set of values; every later step is a deterministic function of that order.
  The hash keeps the order spatially scrambled, so the first K points of a ball are spread over it
  (a lexicographic sort would keep only its -x side). FPS then starts at the point farthest from the
  centroid (``fps_start``, a point on the convex hull, as FPS itself would pick next).
* **Degenerate sets.** With fewer points than centres every point is a centre (M = min(M, N));
  repeated points never make FPS pick an index twice; a centre with no point in its ball (which
  cannot happen when centres are points of the set) takes its nearest point.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from avatar.geometry.gather import gather_rows

#: Largest (chunk x N) distance block the ball query builds at once (~64 MB of float32).
BALL_QUERY_CHUNK_ELEMENTS = 1 << 24

#: The classic single-scale-grouping widths (PointNet++ SSG classification); the last width is the
#: encoder's ``feature_dim``.
CLASSIC_WIDTHS: tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]] = (
    (64, 64, 128),
    (128, 128, 256),
    (256, 512, 1024),
)


def canonical_order(points: torch.Tensor) -> torch.Tensor:
    """(N,) int64 permutation putting points (N, 3) into an order that depends only on their values.

    The points are sorted by an integer hash of their float32 coordinate bits (ties broken
    lexicographically by coordinates), so the result is the same set in the same order for any
    permutation of the input, and consecutive points are spatially unrelated."""
    p = points.detach().to(torch.float32).contiguous()
    n = p.shape[0]
    order = torch.arange(n, device=p.device)
    if n < 2:
        return order
    bits = p.view(torch.int32).to(torch.int64) + (1 << 31)  # in [0, 2^32)
    key = (bits[:, 0] * 73856093) ^ (bits[:, 1] * 19349663) ^ (bits[:, 2] * 83492791)
    key = key & 0xFFFFFFFF
    for _ in range(2):  # integer finaliser: every input bit affects every key bit
        key = ((key >> 16) ^ key) * 0x45D9F3B & 0xFFFFFFFF
    key = (key >> 16) ^ key
    for column in (p[:, 2], p[:, 1], p[:, 0], key):  # stable sorts: the last key is the primary one
        order = order[torch.sort(column[order], stable=True).indices]
    return order


def fps_start(points: torch.Tensor) -> int:
    """Index of the point (N >= 1, 3) farthest from the centroid: an order-independent FPS start.

    Computed in float64; exact ties go to the lowest index."""
    return int(fps_start_index(points))


def fps_start_index(points: torch.Tensor) -> torch.Tensor:
    """:func:`fps_start` as a 0-d int64 tensor on the points' device (not read on the host)."""
    p = points.detach().to(torch.float64)
    d2 = ((p - p.mean(dim=0)) ** 2).sum(dim=1)
    return torch.argmax(d2)


def farthest_point_sample(points: torch.Tensor, num_samples: int, start: int = 0) -> torch.Tensor:
    """Iterative farthest point sampling of points (N, 3), starting at index ``start``.

    Returns (M,) int64 indices, M = min(num_samples, N): each next index maximises the distance to the
    already chosen points (first index on exact ties, as ``torch.argmax``). Indices never repeat: once
    every point left coincides with a chosen one, the rest are the unchosen indices in ascending order.
    Deterministic. One loop over the samples, a few O(N) ops on coordinate columns each."""
    n = points.shape[0]
    m = max(0, min(num_samples, n))
    if m == 0:
        return torch.empty(0, dtype=torch.int64, device=points.device)
    if not 0 <= start < n:
        raise IndexError(f"start={start} out of range for {n} points")
    p = points.detach()
    columns = p.T.contiguous()  # (3, N): contiguous per-coordinate ops are ~3x faster than over (N, 3)
    rows = p.tolist()
    min_d2 = torch.full((n,), float("inf"), dtype=p.dtype, device=p.device)
    d2, t = torch.empty_like(min_d2), torch.empty_like(min_d2)
    chosen = [start]
    while len(chosen) < m:
        for k, c in enumerate(rows[chosen[-1]]):  # d2 = |p - p_last|^2, in place
            torch.sub(columns[k], c, out=t)
            if k == 0:
                torch.square(t, out=d2)
            else:
                d2.addcmul_(t, t)
        torch.minimum(min_d2, d2, out=min_d2)
        best, index = torch.max(min_d2, dim=0)
        if not float(best) > 0:  # only repeats of chosen points are left
            unchosen = torch.ones(n, dtype=torch.bool, device=p.device)
            unchosen[chosen] = False
            chosen += unchosen.nonzero()[: m - len(chosen), 0].tolist()
            break
        chosen.append(int(index))
    return torch.tensor(chosen, dtype=torch.int64, device=points.device)


def farthest_point_sample_on_device(points: torch.Tensor, num_samples: int, start: torch.Tensor) -> torch.Tensor:
    """:func:`farthest_point_sample` of finite points (N >= 1, 3) without reading a value on the host, for a GPU,
    where every such read waits for the device: the same indices, bit for bit (the same float32 operations in the
    same order; ``start`` a 0-d int64 tensor, e.g. :func:`fps_start_index`).

    Instead of asking whether only repeats are left, a chosen point's distance is set to -1 once chosen: while
    unchosen points lie farther than 0 the maximum is among them as before, and once all of them sit on chosen
    points (distance 0) the first of them in index order is the maximum, which is the ascending order the host
    version takes."""
    n = points.shape[0]
    m = max(0, min(num_samples, n))
    out = torch.empty(m, dtype=torch.int64, device=points.device)
    if m == 0:
        return out
    columns = points.detach().T.contiguous()  # (3, N)
    min_d2 = torch.full((n,), float("inf"), dtype=columns.dtype, device=columns.device)
    d2, t = torch.empty_like(min_d2), torch.empty_like(min_d2)
    index = start.reshape(1).to(device=points.device, dtype=torch.int64)
    out[:1] = index
    for i in range(1, m):
        last = columns.index_select(1, index)  # (3, 1): the newest chosen point
        for k in range(3):  # d2 = |p - p_last|^2, in place, as the host version
            torch.sub(columns[k], last[k], out=t)
            if k == 0:
                torch.square(t, out=d2)
            else:
                d2.addcmul_(t, t)
        torch.minimum(min_d2, d2, out=min_d2)
        min_d2.index_fill_(0, index, -1.0)
        index = torch.argmax(min_d2).reshape(1)
        out[i : i + 1] = index
    return out


def _squared_distances(centres: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(M, N) squared distances between centres (M, 3) and points (N, 3), summed coordinate by
    coordinate (exact differences, no (M, N, 3) temporary)."""
    d2 = (centres[:, None, 0] - points[None, :, 0]) ** 2
    for k in (1, 2):
        d2 += (centres[:, None, k] - points[None, :, k]) ** 2
    return d2


def _ball_query_block(points: torch.Tensor, centres: torch.Tensor, radius: float, k: int) -> torch.Tensor:
    """``ball_query`` for one block of centres (M, 3): returns (M, K) int64."""
    n = points.shape[0]
    d2 = _squared_distances(centres, points)
    index = torch.arange(n, device=points.device)
    key = torch.where(d2 <= radius * radius, index, n)  # points outside the ball sort last
    first = torch.topk(key, min(k, n), dim=1, largest=False, sorted=True).values
    lead = first[:, 0]  # the first point found in each ball ...
    empty = lead == n
    if not empty.is_cpu or empty.any():  # ... or, for an empty ball, the nearest point (on a GPU unasked: no wait)
        lead = torch.where(empty, torch.argmin(d2, dim=1), lead)
    if first.shape[1] < k:
        first = torch.cat([first, first.new_full((first.shape[0], k - first.shape[1]), n)], dim=1)
    return torch.where(first < n, first, lead[:, None])


def ball_query(
    points: torch.Tensor,
    centres: torch.Tensor,
    radius: float,
    max_neighbours: int,
    chunk_elements: int | None = None,
) -> torch.Tensor:
    """Neighbours of every centre (M, 3) among points (N >= 1, 3) within ``radius`` (inclusive).

    Returns (M, K) int64, K = ``max_neighbours``: per centre, the first K point indices in index order
    with distance <= radius (as the reference CUDA kernel); unused slots repeat the first one found,
    and a centre with no point in its ball gets its nearest point in every slot. Centres are processed
    in chunks so that a (chunk, N) block has at most ``chunk_elements`` entries
    (default ``BALL_QUERY_CHUNK_ELEMENTS``)."""
    m, n = centres.shape[0], points.shape[0]
    if m > 0 and n == 0:
        raise ValueError("ball_query needs at least one point")
    limit = BALL_QUERY_CHUNK_ELEMENTS if chunk_elements is None else chunk_elements
    chunk = max(1, limit // max(n, 1))
    p, c = points.detach(), centres.detach().to(points.dtype)
    blocks = [_ball_query_block(p, c[s : s + chunk], radius, max_neighbours) for s in range(0, m, chunk)]
    if not blocks:
        return torch.empty(0, max_neighbours, dtype=torch.int64, device=points.device)
    return torch.cat(blocks)


class SharedMLP(nn.Sequential):
    """``Linear -> LayerNorm -> ReLU`` per width, applied to the last dimension: (..., C) -> (..., widths[-1])."""

    def __init__(self, in_features: int, widths: Sequence[int]) -> None:
        if not widths:
            raise ValueError("a shared MLP needs at least one layer")
        layers: list[nn.Module] = []
        for width in widths:
            layers += [nn.Linear(in_features, width), nn.LayerNorm(width), nn.ReLU()]
            in_features = width
        super().__init__(*layers)


def group(
    xyz: torch.Tensor,
    features: torch.Tensor | None,
    centres: torch.Tensor,
    neighbours: torch.Tensor,
    radius: float,
) -> torch.Tensor:
    """Grouped inputs (M, K, 3 + C) of a set abstraction: neighbour coordinates relative to their centre
    divided by ``radius``, then the neighbours' features.

    xyz (N, 3), features (N, C) or None (C = 0), centres (M, 3), neighbours (M, K) int64."""
    relative = (gather_rows(xyz, neighbours) - centres[:, None, :]) / radius
    if features is None:
        return relative
    return torch.cat([relative, gather_rows(features, neighbours)], dim=-1)


class SetAbstraction(nn.Module):
    """One single-scale-grouping set abstraction level: FPS centres, ball query, shared MLP, max-pool.

    ``forward(xyz (N, 3), features (N, C) | None) -> (new_xyz (M, 3), new_features (M, widths[-1]))``
    with M = min(num_centres, N), N >= 1; FPS starts at ``fps_start(xyz)``."""

    def __init__(
        self,
        num_centres: int,
        radius: float,
        max_neighbours: int,
        in_features: int,
        widths: Sequence[int],
    ) -> None:
        super().__init__()
        self.num_centres = num_centres
        self.radius = float(radius)
        self.max_neighbours = max_neighbours
        self.in_features = in_features
        self.mlp = SharedMLP(3 + in_features, widths)

    def forward(
        self,
        xyz: torch.Tensor,
        features: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if xyz.is_cpu:
            centre_index = farthest_point_sample(xyz, self.num_centres, start=fps_start(xyz))
        else:  # the same centres without reading the device's values on the host every sample
            centre_index = farthest_point_sample_on_device(xyz, self.num_centres, fps_start_index(xyz))
        centres = xyz[centre_index]
        neighbours = ball_query(xyz, centres, self.radius, self.max_neighbours)
        grouped = group(xyz, features, centres, neighbours, self.radius)
        return centres, self.mlp(grouped).amax(dim=1)

    def extra_repr(self) -> str:
        return (
            f"num_centres={self.num_centres}, radius={self.radius}, max_neighbours={self.max_neighbours}, "
            f"in_features={self.in_features}"
        )


class GlobalAbstraction(nn.Module):
    """All points as one group: shared MLP on ``[xyz, features]`` then max-pool.

    ``forward(xyz (N, 3), features (N, C) | None) -> (widths[-1],)``; N = 0 gives zeros (the max over
    the empty set of the non-negative ReLU outputs)."""

    def __init__(self, in_features: int, widths: Sequence[int]) -> None:
        super().__init__()
        self.mlp = SharedMLP(3 + in_features, widths)
        self.out_features = widths[-1]

    def forward(self, xyz: torch.Tensor, features: torch.Tensor | None = None) -> torch.Tensor:
        x = xyz if features is None else torch.cat([xyz, features], dim=-1)
        h = self.mlp(x)
        if h.shape[0] == 0:
            return h.new_zeros(self.out_features)
        return h.amax(dim=0)


def classic_widths(
    feature_dim: int = 1024,
    multiplier: float = 1.0,
) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """The classic SSG widths with every hidden width scaled by ``multiplier`` (at least 8) and the
    final one set to ``feature_dim``."""
    scaled = [tuple(max(8, round(w * multiplier)) for w in level) for level in CLASSIC_WIDTHS]
    scaled[2] = scaled[2][:-1] + (feature_dim,)
    return scaled[0], scaled[1], scaled[2]


class PointNet2Encoder(nn.Module):
    """PointNet++ SSG encoder of one point set: ``forward(points (N, 3)) -> (feature_dim,)``.

    Two set abstractions (``centres``, ``radii`` in units of ``points / scale``, ``neighbours``) and a
    global abstraction; ``widths`` gives the three shared MLPs (default ``classic_widths(feature_dim,
    width_multiplier)``; its very last width must be ``feature_dim``). The output is invariant to the
    order of the points, and an empty set gives the learned vector ``empty`` (see the module docstring)."""

    def __init__(
        self,
        feature_dim: int = 1024,
        centres: tuple[int, int] = (512, 128),
        radii: tuple[float, float] = (0.2, 0.4),
        neighbours: tuple[int, int] = (32, 64),
        widths: tuple[Sequence[int], Sequence[int], Sequence[int]] | None = None,
        scale: float = 1.0,
        width_multiplier: float = 1.0,
    ) -> None:
        super().__init__()
        if widths is None:
            widths = classic_widths(feature_dim, width_multiplier)
        if len(widths) != 3 or widths[2][-1] != feature_dim:
            raise ValueError(f"widths must be three MLPs, the last ending in feature_dim={feature_dim}: {widths}")
        if scale <= 0:
            raise ValueError(f"scale must be positive, got {scale}")
        self.feature_dim = feature_dim
        self.scale = float(scale)
        self.sa1 = SetAbstraction(centres[0], radii[0], neighbours[0], 0, widths[0])
        self.sa2 = SetAbstraction(centres[1], radii[1], neighbours[1], widths[0][-1], widths[1])
        self.glob = GlobalAbstraction(widths[1][-1], widths[2])
        #: Added to the pooled feature; the whole output of an empty set.
        self.empty = nn.Parameter(torch.zeros(feature_dim))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"expected points (N, 3), got {tuple(points.shape)}")
        if points.shape[0] == 0:
            return self.empty + 0.0  # a fresh tensor, still differentiable w.r.t. ``empty``
        xyz = points.to(self.empty.dtype) / self.scale
        xyz = xyz[canonical_order(xyz)]
        xyz1, f1 = self.sa1(xyz)
        xyz2, f2 = self.sa2(xyz1, f1)
        return self.glob(xyz2, f2) + self.empty
