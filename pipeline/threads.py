"""How many CPU threads a run computes on (``run.threads``) and how its idle threads wait, so that runs which share
a machine share its cores instead of taking each other's time.

Torch's intra-op pool is GNU OpenMP (torch's own ``libgomp``), and the compiled rasterizer runs on the same pool
(``avatar/render/gaussians/extension.py``). Two things decide how a run behaves beside other work:

- **How idle threads wait** (:func:`wait_passively`). Unless ``OMP_WAIT_POLICY=PASSIVE``, a thread that waits for
  the next parallel region or at a barrier spins for a while before it sleeps, and a training step is many short
  parallel regions with Python in between, so the pool's other threads keep cores busy for most of the step. Alone
  on the machine that costs little; beside other jobs the spinning threads take the time slices of the threads that
  have work (on 2 cores beside two other smoke jobs, a smoke stage-two step took 21 s instead of 0.5 s:
  ``benchmarks/bench_sharing.py``). The runtime reads the variable once, when it loads (when torch is imported), so
  the ``interactavatar`` entry point sets it before it imports anything else; the processes a run starts (a local
  batch's jobs, the capture's workers, the jobs that SLURM starts with the submitting shell's environment) inherit
  it. A value the environment already has is kept.
- **How many threads** (:func:`choose_threads`). ``run.threads=auto`` takes ``OMP_NUM_THREADS`` where the
  environment sets one (the user, or a launcher that shares the cores out: joblib's workers, Ray's tasks), else the
  cores this process may use (its CPU affinity, within its cgroup's CPU quota: a container limited to 2 CPUs on a
  64-core host gets 2 threads, not 64). A batch that runs several jobs at once on this machine gives each job its
  share (:mod:`pipeline.batch`), so that the jobs' threads together do not exceed the cores. The machine's load is
  not read: the thread count changes the rounding of torch's sums, so a count that followed the load would make
  the bytes of a stage forced twice depend on what else ran meanwhile; and with idle threads asleep, fewer threads
  on a busy machine made a step slower, not faster (``bench_sharing --one-thread``).

The thread count is no part of a cache key; the manifest of a stage records it (``threads``).
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping, MutableMapping
from pathlib import Path

#: the environment variable through which GNU OpenMP learns how idle threads wait
WAIT_POLICY = "OMP_WAIT_POLICY"
#: the environment variable of a thread budget set from outside (the user, a launcher); torch reads it too
THREADS_ENV = "OMP_NUM_THREADS"
#: ``run.threads``: the choice from the machine
AUTO = "auto"
THREAD_CHOICES = "auto or a number of threads, e.g. run.threads=1"


def wait_passively(environ: MutableMapping[str, str] = os.environ) -> None:
    """Let idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE``) unless the environment already says how they
    wait. Effective only before torch is imported in this process, and in the processes started afterwards."""
    environ.setdefault(WAIT_POLICY, "PASSIVE")


def threads_problem(setting: object) -> str | None:
    """Why ``run.threads=setting`` is not a thread setting, or None."""
    if str(setting) == AUTO:
        return None
    try:
        if int(str(setting)) >= 1:
            return None
    except ValueError:
        pass
    return f"run.threads={setting}: use {THREAD_CHOICES}"


def env_threads(environ: Mapping[str, str] = os.environ) -> int | None:
    """The thread budget the environment sets (``OMP_NUM_THREADS``; of a nested list such as ``4,2``, the first
    level), or None where it sets none or nothing usable."""
    value = environ.get(THREADS_ENV, "").split(",")[0].strip()
    return int(value) if value.isdigit() and int(value) >= 1 else None


def quota_cores(quota: str, period: str) -> float | None:
    """A cgroup's CPU quota in cores, from its quota and period as the kernel writes them (v2 ``cpu.max``: ``max``
    or microseconds; v1 ``cpu.cfs_quota_us``: ``-1`` or microseconds); None when it has none."""
    try:
        q, p = int(quota), int(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def _folder_quota(folder: Path, v2: bool) -> float | None:
    """The CPU quota one cgroup folder sets, in cores (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us``), or None."""
    try:
        if v2:
            quota, period = (folder / "cpu.max").read_text().split()[:2]
        else:
            quota, period = (folder / "cpu.cfs_quota_us").read_text(), (folder / "cpu.cfs_period_us").read_text()
    except (OSError, ValueError):
        return None
    return quota_cores(quota.strip(), period.strip())


def cgroup_quota(proc_cgroup: Path = Path("/proc/self/cgroup"), root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """The CPU quota of this process's cgroup in cores, the smallest along its path up to the hierarchy's root
    (cgroup v2, or v1's ``cpu`` controller); None where none is set or none can be read."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    found: list[float] = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2: one hierarchy, mounted at the root or under unified/ beside v1's
            mounts, v2 = [root, root / "unified"], True
        elif "cpu" in controllers.split(","):
            mounts, v2 = [root / controllers, root / "cpu"], False
        else:
            continue
        for mount in mounts:
            folder = mount / path.strip("/")
            for level in [folder, *(p for p in folder.parents if p == mount or mount in p.parents)]:
                quota = _folder_quota(level, v2)
                if quota is not None:
                    found.append(quota)
    return min(found) if found else None


def usable_cores(affinity: int | None = None, quota: float | None = None) -> int:
    """The cores this process may use: its CPU affinity (``affinity``, default what the kernel says), within its
    cgroup's CPU quota (``quota`` in cores, default :func:`cgroup_quota`; rounded down: a quota of 1.5 cores keeps
    one thread busy without throttling), at least 1."""
    if affinity is None:
        affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if quota is None:
        quota = cgroup_quota()
    cores = affinity if quota is None else min(affinity, math.floor(quota))
    return max(1, cores)


def choose_threads(setting: object, cores: int, environ_threads: int | None = None, jobs: int = 1) -> int:
    """The thread count of ``run.threads=setting``: a number as given; ``auto`` the environment's count
    (``environ_threads``, :func:`env_threads`: a process's own, as OpenMP reads it) where it sets one, else
    ``cores`` (:func:`usable_cores`) shared by the ``jobs`` that a batch runs at once on this machine, at least 1.
    Raises ValueError for another setting."""
    problem = threads_problem(setting)
    if problem is not None:
        raise ValueError(problem)
    if str(setting) != AUTO:
        return int(str(setting))
    if environ_threads is not None:
        return environ_threads
    return max(1, cores // max(1, jobs))


def torch_threads() -> int | None:
    """The thread count torch computes on in this process, None where nothing has imported torch."""
    torch = sys.modules.get("torch")
    return None if torch is None else int(torch.get_num_threads())


def use_threads(setting: object) -> int:
    """Set torch's thread count (and so the compiled rasterizer's) to ``run.threads=setting`` on this machine
    (:func:`choose_threads`) and return it. A job calls it when it starts, once its stages are loaded; code that
    calls the runner in its own process (tests, benchmarks) keeps its own thread count. Where no stage has imported
    torch (a DAG that never uses it) there is no pool to size, and torch is not imported for it."""
    threads = choose_threads(setting, usable_cores(), env_threads())
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)
    return threads
