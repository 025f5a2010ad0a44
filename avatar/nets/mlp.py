"""The paper's delta MLPs: leaky ReLU, layer norm, a skip from the input to the middle layer, zero-initialised
output, and inputs split into a per-point and a per-frame part.

Every MLP of the dynamic hand (H_geo, H_app) and of the interaction module (I) maps, for each Gaussian, the
concatenation ``[point inputs, frame inputs]`` to one parameter delta. The frame inputs (poses, expression,
the hand-to-head transform, the 1024-d PointNet++ feature F) are the same for every Gaussian of a frame, so
the layers that read the input (the first layer and the skip into the middle layer) are split:
``W [p; f] + b = W_p p + (W_f f + b)``, and ``W_f f`` is computed once per frame instead of once per
Gaussian. This is the same function as the concatenated MLP (a test checks it), at a fraction of the cost
when F is wide.

On a CPU these networks are bound by memory traffic over (N, width) tensors as much as by the products, so
each layer makes as few passes as it can: the per-frame term is the bias of the point product (``addmm``),
the skip's product is the input of the middle layer's (no separate sums), the leaky ReLU works in place on
the layer norm's fresh output, and point inputs that need no gradient are multiplied apart from those that
do. Same function, to rounding (tests/representations/bound/test_delta_mlp.py); evaluating a module's heads as one
batched network (stacked weights, ``baddbmm``) measured no faster and was dropped
(docs/notes/2026-12-04-stage-two-speed.md).

A frozen network evaluated many times on the same points (a trained avatar tracking a motion) may multiply the point
inputs that never change (a Gaussian's position code, its point features) by the layers' columns once
(:meth:`DeltaMLP.fixed_product`, a :class:`FixedProduct`) and hand the products to every later call: each call then
multiplies only the remaining point inputs and the frame's. Same function, to rounding.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import cast

import torch
import torch.nn.functional as fn
from torch import Tensor, nn

PointInputs = Tensor | tuple[Tensor, ...]  # (N, P), or its column blocks (N, P_1), (N, P_2), ...


@dataclass(frozen=True)
class FixedProduct:
    """The leading point-input blocks of one :class:`DeltaMLP`, ``(N, P_fixed)`` in all, multiplied ahead of time by
    the columns that read them: for inputs that no call changes while the network is frozen.

    Attributes:
        input: (N, width) the blocks times the input layer's columns (no bias).
        skip: (N, width) the blocks times the skip's columns (no bias); None when the MLP has no skip.
        columns: P_fixed, how many point-input columns the blocks are (the call's point inputs are the rest).
    """

    input: Tensor
    skip: Tensor | None
    columns: int

    def rows(self, index: Tensor) -> FixedProduct:
        """The products of the points ``index`` (M,) selects, (M, width) each."""
        return FixedProduct(self.input[index], None if self.skip is None else self.skip[index], self.columns)


#: One :class:`FixedProduct` per MLP of a module's heads, in the order of :meth:`DeltaHeads.fixed_products`.
FixedProducts = tuple[FixedProduct, ...]


def _blocks(point: PointInputs) -> tuple[Tensor, ...]:
    return (point,) if isinstance(point, Tensor) else point


class SplitLinear(nn.Module):
    """``Linear`` on ``[point (N, P); frame (Fd,) broadcast]`` without materialising the concatenation.

    The point inputs may come in parts, ``(N, P_1), (N, P_2), ...`` with ``sum P_k = P``, each multiplied by its
    own columns of the weight: a part that needs no gradient (a fixed encoding) then costs none in the backward
    pass, where the concatenation would have its gradient computed whole and then cut."""

    def __init__(self, point_dim: int, frame_dim: int, out_dim: int) -> None:
        super().__init__()
        self.point = nn.Linear(point_dim, out_dim)
        self.frame = nn.Linear(frame_dim, out_dim, bias=False) if frame_dim > 0 else None

    def forward(
        self,
        point: PointInputs,
        frame: Tensor,
        shift: Tensor | None = None,
        fixed: Tensor | None = None,
        fixed_columns: int = 0,
    ) -> Tensor:
        """point (N, P) or its parts, frame (Fd,), shift (out_dim,) added too -> (N, out_dim). ``fixed`` (N, out_dim):
        the product of the leading ``fixed_columns`` point columns (:meth:`product`); ``point`` is then the rest (may
        be ``()``)."""
        bias = self.point.bias if shift is None else self.point.bias + shift
        if self.frame is not None:  # W_f f + b: once per frame, then the bias of one product
            bias = bias + self.frame(frame)
        if fixed is None:
            return self._accumulate(point, 0, None, bias)
        return self._accumulate(point, fixed_columns, fixed + bias, bias)

    def product(self, point: PointInputs) -> Tensor:
        """(N, out_dim): the leading point columns ``point`` (or their parts) times their columns of the weight, no
        bias (the ``fixed`` of :meth:`forward`)."""
        return self._accumulate(point, 0, None, None)

    def _accumulate(self, point: PointInputs, start: int, out: Tensor | None, bias: Tensor | None) -> Tensor:
        """``out`` (N, out_dim) plus each block of ``point`` times its weight columns from column ``start`` on; with
        ``out`` None the first block's product starts the sum, carrying ``bias`` where given (one ``addmm``)."""
        for part in _blocks(point):
            weight = self.point.weight[:, start : start + part.shape[1]]
            if out is not None:
                out = torch.addmm(out, part, weight.T)
            else:
                out = part @ weight.T if bias is None else torch.addmm(bias, part, weight.T)
            start += part.shape[1]
        if out is None:
            raise ValueError("SplitLinear needs at least one block of point inputs")
        return out


class DeltaMLP(nn.Module):
    """One MLP per Gaussian parameter (paper, Implementation): ``depth`` hidden layers of ``width`` units,
    each Linear -> LayerNorm -> LeakyReLU; the input is fed again into hidden layer ``depth // 2`` (the
    skip connection to the middle layer, as in NeRF); a final Linear to ``out_dim`` whose weight and bias
    start at zero, so the delta is exactly 0 before training and the model renders the warm-up result.
    """

    def __init__(
        self,
        point_dim: int,
        frame_dim: int,
        out_dim: int,
        width: int = 256,
        depth: int = 4,
        negative_slope: float = 0.01,
    ) -> None:
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

    def forward(self, point: PointInputs, frame: Tensor, fixed: FixedProduct | None = None) -> Tensor:
        """point (N, P) per-Gaussian inputs (or their parts, see :class:`SplitLinear`), frame (Fd,) per-frame
        inputs -> (N, out_dim) deltas. ``fixed``: the leading point blocks' products (:meth:`fixed_product`), of
        the same N points; ``point`` is then the remaining blocks (``()`` when none)."""
        first, skip, columns = (None, None, 0) if fixed is None else (fixed.input, fixed.skip, fixed.columns)
        h = self._activate(self.input_layer(point, frame, None, first, columns), 0)
        # cast: a ModuleList iterates as Module; these are the Linear layers built in __init__
        for i, layer in enumerate(cast(Iterable[nn.Linear], self.hidden), start=1):
            if i == self.skip_at:  # == Linear([h; input]) split in two; the skip's product carries the layer's bias
                assert self.skip is not None  # built whenever skip_at > 0
                z = torch.addmm(self.skip(point, frame, layer.bias, skip, columns), h, layer.weight.T)
            else:
                z = layer(h)
            h = self._activate(z, i)
        return self.output(h)

    def fixed_product(self, point: PointInputs) -> FixedProduct:
        """The leading point blocks ``point`` ((N, P_fixed) or its parts) times the input layer's and the skip's
        columns: what :meth:`forward` would multiply them by in every call."""
        columns = sum(part.shape[1] for part in _blocks(point))
        skip = None if self.skip is None else self.skip.product(point)
        return FixedProduct(self.input_layer.product(point), skip, columns)

    def _activate(self, z: Tensor, layer: int) -> Tensor:
        """LayerNorm ``layer``, then LeakyReLU in place on the fresh normalised tensor: (N, width) -> (N, width)."""
        return fn.leaky_relu_(self.norms[layer](z), self.act.negative_slope)


class DeltaHeads(nn.Module):
    """Several :class:`DeltaMLP` on the same inputs, one per output parameter (e.g. mu: 3, s: 3, q: 4)."""

    def __init__(self, outputs: dict[str, int], point_dim: int, frame_dim: int, width: int, depth: int) -> None:
        super().__init__()
        self.heads = nn.ModuleDict(
            {name: DeltaMLP(point_dim, frame_dim, dim, width, depth) for name, dim in outputs.items()}
        )

    def forward(self, point: PointInputs, frame: Tensor, fixed: FixedProducts | None = None) -> dict[str, Tensor]:
        """point (N, P) or its parts, frame (Fd,) -> {name: (N, dim)}; ``fixed``: :meth:`fixed_products` of the
        leading point blocks (``point`` then the rest)."""
        if fixed is None:
            return {name: head(point, frame) for name, head in self.heads.items()}
        return {name: head(point, frame, f) for (name, head), f in zip(self.heads.items(), fixed, strict=True)}

    def fixed_products(self, point: PointInputs) -> FixedProducts:
        """:meth:`DeltaMLP.fixed_product` of every head, in order."""
        return tuple(cast(DeltaMLP, head).fixed_product(point) for head in self.heads.values())

    def output_layers(self) -> list[nn.Linear]:
        """The zero-initialised last layers: zeroing them makes every delta exactly 0 (the selection's switch)."""
        return [cast(DeltaMLP, head).output for head in self.heads.values()]


class SharedDeltaHeads(nn.Module):
    """One :class:`DeltaMLP` trunk for several output parameters, with a linear head per parameter: the trunk's
    zero-initialised output layer maps to all of them at once (``sum(dims)`` columns, split in ``outputs``' order),
    which is a linear head per parameter on one shared hidden representation. Same inputs and the same zero deltas
    at the start as :class:`DeltaHeads`, at about ``1 / len(outputs)`` of its cost (``stage.dynamic.heads=shared``).
    """

    def __init__(self, outputs: dict[str, int], point_dim: int, frame_dim: int, width: int, depth: int) -> None:
        super().__init__()
        self.names, self.dims = list(outputs), list(outputs.values())
        self.trunk = DeltaMLP(point_dim, frame_dim, sum(self.dims), width, depth)

    def forward(self, point: PointInputs, frame: Tensor, fixed: FixedProducts | None = None) -> dict[str, Tensor]:
        """point (N, P) or its parts, frame (Fd,) -> {name: (N, dim)} (column blocks of one (N, sum(dims)));
        ``fixed``: :meth:`fixed_products` of the leading point blocks (``point`` then the rest)."""
        trunk = self.trunk(point, frame, None if fixed is None else fixed[0])
        return dict(zip(self.names, torch.split(trunk, self.dims, dim=1)))

    def fixed_products(self, point: PointInputs) -> FixedProducts:
        """The trunk's :meth:`DeltaMLP.fixed_product`."""
        return (self.trunk.fixed_product(point),)

    def output_layers(self) -> list[nn.Linear]:
        """The trunk's zero-initialised last layer, which holds every parameter's linear head."""
        return [self.trunk.output]


#: ``stage.dynamic.heads``: one MLP per Gaussian parameter (the paper's) or one shared trunk per module
HEAD_KINDS: dict[str, type[DeltaHeads] | type[SharedDeltaHeads]] = {
    "per_parameter": DeltaHeads,
    "shared": SharedDeltaHeads,
}


def delta_heads(
    kind: str, outputs: dict[str, int], point_dim: int, frame_dim: int, width: int, depth: int
) -> DeltaHeads | SharedDeltaHeads:
    """The heads of one module (H_geo, H_app or I) of the kind ``kind`` (a key of :data:`HEAD_KINDS`)."""
    if kind not in HEAD_KINDS:
        raise ValueError(f"heads={kind}: must be one of {', '.join(HEAD_KINDS)}")
    return HEAD_KINDS[kind](outputs, point_dim, frame_dim, width, depth)
