"""Where the stages that train and render compute: ``run.device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``) and
``run.precision`` (``fp32``, ``bf16``), resolved once per run on the machine that runs it, before any stage.

The CPU in fp32 is the reference: on it a device stage's cache key is what it always was. Anywhere else the device's
kind (``cuda``, not its number: the cards of one machine share their artifacts) and the precision enter the key of
every stage that computes on the device (:attr:`pipeline.stage.Stage.device`), so results of another kind are another
cache entry and never mixed, and the manifest records the kind and the model (:func:`device_record`)."""

from __future__ import annotations

import platform
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"
PRECISIONS = ("fp32", "bf16")
_DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")


def device_syntax_problem(spec: object) -> str | None:
    """Why ``run.device=spec`` is not a device setting, or None (availability is :func:`resolve_device`'s)."""
    if isinstance(spec, str) and _DEVICE.fullmatch(spec):
        return None
    return f"run.device={spec}: use one of {DEVICE_CHOICES}"


def precision_problem(spec: object) -> str | None:
    """Why ``run.precision=spec`` is not a precision, or None."""
    if spec in PRECISIONS:
        return None
    return (
        f"run.precision={spec}: use fp32 (the reference) or bf16 (the networks' products in bfloat16, "
        "docs/how-to/gpu.md)"
    )


class DeviceUnavailable(ValueError):
    """``run.device`` names a device this machine does not have."""


def cuda_count() -> int:
    """How many CUDA devices this process sees (0 with torch's CPU build or without a driver)."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def resolve_device(spec: str, count: int | None = None) -> str:
    """The torch device a run computes on for ``run.device=spec`` on this machine (``count``: its CUDA devices,
    default what torch sees): ``auto`` is ``cuda:0`` where there is one, else ``cpu``; ``cuda`` is ``cuda:0``.
    A CUDA device this machine does not have is :class:`DeviceUnavailable`, naming the key and the fix."""
    problem = device_syntax_problem(spec)
    if problem is not None:
        raise DeviceUnavailable(problem)
    count = cuda_count() if count is None else count
    if spec == "auto":
        return "cuda:0" if count > 0 else "cpu"
    if spec == "cpu":
        return "cpu"
    index = int(spec.partition(":")[2] or 0)
    if count == 0:
        raise DeviceUnavailable(
            f"run.device={spec}: this machine has no CUDA device that torch can use (torch "
            f"{_torch_build()}); run with run.device=cpu or run.device=auto, or install torch's CUDA build "
            "(README, 'On a GPU')"
        )
    if index >= count:
        raise DeviceUnavailable(
            f"run.device={spec}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}; "
            f"choose one of them or run.device=auto"
        )
    return f"cuda:{index}"


def _torch_build() -> str:
    import torch

    cuda = torch.version.cuda
    return f"{torch.__version__}, CUDA {cuda}" if cuda else f"{torch.__version__}, CPU build"


def device_kind(device: str) -> str:
    """``cpu`` or ``cuda`` of a resolved device (``cuda:1`` -> ``cuda``)."""
    return device.partition(":")[0]


def device_name(device: str) -> str:
    """The model of a resolved device: the GPU's name, or the CPU's (``/proc/cpuinfo``)."""
    if device_kind(device) == "cuda":
        import torch

        return torch.cuda.get_device_name(int(device.partition(":")[2] or 0))
    return cpu_name()


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@dataclass(frozen=True)
class Compute:
    """A run's resolved device and precision.

    Attributes:
        device: a torch device string, ``cpu`` or ``cuda:N``.
        precision: ``fp32`` or ``bf16``.
    """

    device: str = "cpu"
    precision: str = "fp32"

    @property
    def kind(self) -> str:
        return device_kind(self.device)

    def key_entries(self, networks: bool = True) -> dict[str, str]:
        """What enters a device stage's cache key beyond its config keys: the device's kind where it is not the CPU,
        and for a stage that runs networks (``networks``) the precision where it is not fp32; nothing on the
        reference (the CPU in fp32), so its keys stay what they were."""
        entries = {"run.device": self.kind} if self.kind != "cpu" else {}
        return entries | ({"run.precision": self.precision} if networks and self.precision != "fp32" else {})

    def reset_peak_memory(self) -> None:
        """Start counting the device's peak memory afresh (on CUDA; the CPU's is the monitor's peak RSS)."""
        if self.kind == "cuda":
            import torch

            torch.cuda.reset_peak_memory_stats(self.device)

    def record(self, networks: bool = True) -> dict[str, Any]:
        """The manifest's record of where a device stage computed: kind, model and precision (fp32 for a stage that
        runs no networks, ``networks``), and on CUDA the peak memory torch allocated on the device since
        :meth:`reset_peak_memory` (MiB)."""
        used = self.precision if networks else "fp32"
        record: dict[str, Any] = {"kind": self.kind, "name": device_name(self.device), "precision": used}
        if self.kind == "cuda":
            import torch

            record["peak_memory_mb"] = torch.cuda.max_memory_allocated(self.device) / 2**20
        return record


def resolve_compute(device: str, precision: str) -> Compute:
    """The :class:`Compute` of ``run.device`` and ``run.precision`` on this machine."""
    problem = precision_problem(precision)
    if problem is not None:
        raise DeviceUnavailable(problem)
    return Compute(resolve_device(device), precision)
