"""The result of rendering Gaussians, shared by every backend."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        rgb: (H, W, 3) colour, background blended with the final transmittance.
        alpha: (H, W) accumulated opacity ``1 - final transmittance``.
        depth: (H, W) alpha-weighted camera-space z, ``sum_k w_k z_k`` (expected depth times
            alpha; divide by ``alpha`` for the surface depth).
        means2d: (N, 2) projected centres in OpenCV pixel coordinates. With the torch backend it
            retains its gradient: after ``backward()``, ``means2d.grad`` is ``dL/dmeans2d``;
            ``grad2d()`` works for every backend.
        radii: (N,) int32 pixel radius, 0 for Gaussians that are culled or not visible.
        grad_holder: the graph tensor whose ``.grad`` is ``dL/dmeans2d``, any shape holding
            (N, 2) values: ``means2d`` itself for the torch backend, gsplat's own
            ``meta["means2d"]`` (1, N, 2) for gsplat. Read it through ``grad2d``.
    """

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    grad_holder: Tensor = field(repr=False)

    def grad2d(self) -> Tensor:
        """(N, 2) ``dL/dmeans2d`` in pixels after ``backward()`` (zeros before, or without grad)."""
        grad = self.grad_holder.grad
        if grad is None:
            return torch.zeros_like(self.means2d)
        return grad.reshape(self.means2d.shape).to(self.means2d.device)

    def grad2d_norm(self) -> Tensor:
        """(N,) norm of ``grad2d()``: the per-view screen-space positional gradient that 3DGS
        density control accumulates (3DGS measures it in NDC units, i.e. scaled by (W/2, H/2))."""
        return self.grad2d().norm(dim=-1)
