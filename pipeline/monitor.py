"""Wall time and peak memory of one stage, measured while it runs."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from types import TracebackType

import psutil


@dataclass
class Usage:
    wall_s: float = 0.0
    start_rss_mb: float = 0.0
    peak_rss_mb: float = 0.0
    peak_cuda_mb: float = 0.0

    @property
    def rss_growth_mb(self) -> float:
        """Peak resident memory above what the process held when measuring started."""
        return self.peak_rss_mb - self.start_rss_mb


class ResourceMonitor:
    """Context manager sampling this process's resident memory (and CUDA memory when used).

    Resident memory is sampled every ``interval_s`` by a daemon thread, so the
    peak is exact up to spikes shorter than the interval.
    """

    def __init__(self, interval_s: float = 0.05) -> None:
        self.usage = Usage()
        self._interval = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._proc = psutil.Process()
        self._t0 = 0.0

    def _sample(self) -> None:
        while True:
            rss = self._proc.memory_info().rss / 2**20
            self.usage.peak_rss_mb = max(self.usage.peak_rss_mb, rss)
            if self._stop.wait(self._interval):
                return

    def __enter__(self) -> ResourceMonitor:
        self._t0 = time.perf_counter()
        self.usage.start_rss_mb = self.usage.peak_rss_mb = self._proc.memory_info().rss / 2**20
        cuda = _cuda()
        if cuda is not None:
            cuda.reset_peak_memory_stats()
        self._thread.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        self._thread.join()
        self.usage.peak_rss_mb = max(self.usage.peak_rss_mb, self._proc.memory_info().rss / 2**20)
        self.usage.wall_s = time.perf_counter() - self._t0
        cuda = _cuda()
        if cuda is not None:
            self.usage.peak_cuda_mb = cuda.max_memory_allocated() / 2**20


def _cuda():  # returns the torch.cuda module or None
    """torch.cuda if torch is already imported and CUDA is initialised; never imports torch itself."""
    import sys

    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return None
    return torch.cuda
