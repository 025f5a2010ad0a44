"""The paper's delta MLPs: leaky ReLU, layer norm, a skip from the input to the middle layer, zero-initialised
output, and inputs split into a per-point and a per-frame part.

Every MLP of the dynamic hand (H_geo, H_app) and of the interaction module (I) maps, for each Gaussian, the
concatenation ``[point inputs, frame inputs]`` to one parameter delta. The frame inputs (poses, expression,
the hand-to-head transform, the 1024-d PointNet++ feature F) are the same for every Gaussian of a frame, so
the layers that read the input (the first layer and the skip into the middle layer) are split:
``W [p; f] + b = W_p p + (W_f f + b)``, and ``W_f f`` is computed once per frame instead of once per
Gaussian. This is the same function as the concatenated MLP (a test checks it), at a fraction of the cost
when F is wide.
"""

from __future__ import annotations

from torch import Tensor, nn


class SplitLinear(nn.Module):
    """``Linear`` on ``[point (N, P); frame (Fd,) broadcast]`` without materialising the concatenation."""

    def __init__(self, point_dim: int, frame_dim: int, out_dim: int) -> None:
        super().__init__()
        self.point = nn.Linear(point_dim, out_dim)
        self.frame = nn.Linear(frame_dim, out_dim, bias=False) if frame_dim > 0 else None

    def forward(self, point: Tensor, frame: Tensor) -> Tensor:
        """point (N, P), frame (Fd,) -> (N, out_dim)."""
        out = self.point(point)
        return out + self.frame(frame) if self.frame is not None else out


class DeltaMLP(nn.Module):
    """One MLP per Gaussian parameter (paper, Implementation): ``depth`` hidden layers of ``width`` units,
    each Linear -> LayerNorm -> LeakyReLU; the input is fed again into hidden layer ``depth // 2`` (the
    skip connection to the middle layer, as in NeRF); a final Linear to ``out_dim`` whose weight and bias
    start at zero, so the delta is exactly 0 before training and the model renders the warm-up result.
    """

    def __init__(self, point_dim: int, frame_dim: int, out_dim: int, width: int = 256, depth: int = 4,
                 negative_slope: float = 0.01) -> None:
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"DeltaMLP needs depth >= 1 and width >= 1, got depth={depth}, width={width}")
        self.skip_at = depth // 2 if depth >= 2 else -1
        self.input_layer = SplitLinear(point_dim, frame_dim, width)
        self.hidden = nn.ModuleList(nn.Linear(width, width) for _ in range(depth - 1))
        self.skip = SplitLinear(point_dim, frame_dim, width) if self.skip_at > 0 else None
        self.norms = nn.ModuleList(nn.LayerNorm(width) for _ in range(depth))
        self.act = nn.LeakyReLU(negative_slope)
        self.output = nn.Linear(width, out_dim)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    def forward(self, point: Tensor, frame: Tensor) -> Tensor:
        """point (N, P) per-Gaussian inputs, frame (Fd,) per-frame inputs -> (N, out_dim) deltas."""
        h = self.act(self.norms[0](self.input_layer(point, frame)))
        for i, layer in enumerate(self.hidden, start=1):
            z = layer(h)
            if i == self.skip_at:
                z = z + self.skip(point, frame)  # == Linear([h; input]) split in two
            h = self.act(self.norms[i](z))
        return self.output(h)


class DeltaHeads(nn.Module):
    """Several :class:`DeltaMLP` on the same inputs, one per output parameter (e.g. mu: 3, s: 3, q: 4)."""

    def __init__(self, outputs: dict[str, int], point_dim: int, frame_dim: int, width: int, depth: int) -> None:
        super().__init__()
        self.heads = nn.ModuleDict({name: DeltaMLP(point_dim, frame_dim, dim, width, depth)
                                    for name, dim in outputs.items()})

    def forward(self, point: Tensor, frame: Tensor) -> dict[str, Tensor]:
        """point (N, P), frame (Fd,) -> {name: (N, dim)}."""
        return {name: head(point, frame) for name, head in self.heads.items()}
