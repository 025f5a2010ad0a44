"""The lowest CPU priority Linux offers a process, for work that must only use cores nobody else wants.

Three settings, each inherited by the children the process starts:

- **its autogroup's nice, 19** (``/proc/self/autogroup``). With ``kernel.sched_autogroup_enabled`` (the default of
  most distributions, and of these machines) the scheduler first shares the CPU between autogroups (one per
  session: a terminal, a ``setsid`` process) and only then between the processes of a group, by their nice values.
  A process's own nice therefore only orders it against its own session: measured here, a ``nice -n 15`` run took
  94 % of a core beside a nice-0 run started elsewhere (issue 68). The autogroup is the session's, so the caller
  must lead a session of its own (``setsid``; :func:`lowest_priority` refuses to renice a shared one, which would
  renice the user's terminal with it);
- **SCHED_IDLE**: within the group, the policy for tasks that run only when nothing else of the group is runnable;
- **its own nice, 19**, where SCHED_IDLE is refused.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

AUTOGROUP = Path("/proc/self/autogroup")
LOWEST_NICE = 19


@dataclass(frozen=True)
class Priority:
    """What the process runs at: its nice, whether its policy is SCHED_IDLE, its autogroup's line (e.g.
    ``/autogroup-100 nice 19``, or None without autogroups) and whether it leads its session."""

    nice: int
    idle_policy: bool
    autogroup: str | None
    session_leader: bool

    @property
    def lowest(self) -> bool:
        """Whether every setting of :func:`lowest_priority` holds (an autogroup, where the kernel has them, at 19)."""
        group_ok = self.autogroup is None or self.autogroup.endswith(f"nice {LOWEST_NICE}")
        return self.nice == LOWEST_NICE and self.idle_policy and group_ok

    def describe(self) -> str:
        policy = "SCHED_IDLE" if self.idle_policy else "SCHED_OTHER"
        group = self.autogroup or "no autogroups"
        return f"nice {self.nice}, {policy}, {group}"


def current_priority() -> Priority:
    """The calling process's :class:`Priority`."""
    try:
        autogroup: str | None = AUTOGROUP.read_text().strip()
    except OSError:
        autogroup = None
    return Priority(
        nice=os.getpriority(os.PRIO_PROCESS, 0),
        idle_policy=os.sched_getscheduler(0) == os.SCHED_IDLE,
        autogroup=autogroup,
        session_leader=os.getsid(0) == os.getpid(),
    )


def lowest_priority() -> Priority:
    """Put the calling process (and whatever it starts later) at the lowest priority: its own nice 19, SCHED_IDLE,
    and its autogroup's nice 19. The process must lead its own session (``os.setsid()`` first, or
    ``subprocess.Popen(start_new_session=True)``): RuntimeError otherwise, before anything is changed, since the
    autogroup's nice would also slow every other process of the caller's terminal. Returns the priority reached."""
    if os.getsid(0) != os.getpid():
        raise RuntimeError(
            "lowest_priority() must run in a process that leads its own session (setsid): renicing this "
            "session's autogroup would slow the terminal that started it too"
        )
    os.setpriority(os.PRIO_PROCESS, 0, LOWEST_NICE)
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:  # a kernel or sandbox that refuses it: the nice values still hold
        pass
    try:
        AUTOGROUP.write_text(str(LOWEST_NICE))
    except OSError:  # no autogroups (kernel.sched_autogroup_enabled=0 or not built): the nice values are the lever
        pass
    return current_priority()
