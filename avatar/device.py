"""Moving a run's data to the device it trains on, and back to the host where it is written.

The stages hand the core a torch device (``run.device``, resolved by the pipeline): the model and the data a training
loop reads (crops, meshes, conditioning, the refined parameters) move there once, before the loop; the samplers (frames,
cameras, PointNet++'s sample) draw on the CPU's generators and their numbers move, so a seed draws the same numbers on
every device (the density control's split noise alone draws on the device's generator); whatever is written goes
back through :func:`host`. On the CPU every move returns the very same tensor, so the CPU path computes
what it always did."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import fields, replace
from typing import Any, TypeVar

import numpy as np
import torch
from torch import Tensor

T = TypeVar("T")

#: What the frames and masks a training run reads may take of the device's free memory: the model, its optimiser
#: state and the activations of a step need the rest.
DEVICE_DATA_SHARE = 0.5


def to_device(data: T, device: torch.device | str) -> T:
    """A copy of the dataclass ``data`` with every tensor field on ``device`` (the fields themselves where they are
    there already; other fields shared)."""
    moved = {f.name: v.to(device) for f in fields(data) if isinstance(v := getattr(data, f.name), Tensor)}  # type: ignore[arg-type]
    return replace(data, **moved)  # type: ignore[type-var]


def host(tensor: Tensor) -> np.ndarray:
    """``tensor`` as a NumPy array on the host, without its graph (the tensor's own memory on the CPU)."""
    return tensor.detach().cpu().numpy()


def host_state(state: dict[str, Any]) -> dict[str, Any]:
    """A state dict with every tensor on the host (the same tensors on the CPU), so that a saved file loads
    anywhere and is byte for byte the CPU's."""
    return {k: v.cpu() if isinstance(v, Tensor) else v for k, v in state.items()}


def fits_on_device(need: int, device: torch.device | str, what: str, fix: str) -> None:
    """Raise MemoryError, naming ``what`` and ``fix``, when ``need`` bytes exceed :data:`DEVICE_DATA_SHARE` of the
    CUDA device's free memory (nothing to check on the CPU, whose data is in memory already)."""
    device = torch.device(device)
    if device.type != "cuda":
        return
    free, total = torch.cuda.mem_get_info(device)
    limit = int(DEVICE_DATA_SHARE * free)
    if need > limit:
        raise MemoryError(
            f"{what} take {need / 2**30:.2f} GiB, more than the {limit / 2**30:.2f} GiB (half of the "
            f"{free / 2**30:.2f} GiB free of {total / 2**30:.2f} GiB on {device}) that training may give them; {fix}"
        )


@contextlib.contextmanager
def precision(kind: str, device: torch.device | str) -> Iterator[None]:
    """Run the block in ``kind`` precision on ``device``: ``fp32`` as written; ``bf16`` with autocast (matrix
    products and convolutions in bfloat16, reductions and the rest in float32)."""
    if kind == "fp32":
        yield
        return
    if kind != "bf16":
        raise ValueError(f"precision={kind}: use fp32 or bf16")
    with torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16):
        yield
