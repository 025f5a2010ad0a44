"""Runs that wait for each other wait fairly: a writer is not starved by a stream of readers, and two methods
started together compute a stage they share once and train side by side (issue 36, item 9)."""

from __future__ import annotations

import fcntl
import os
import subprocess
import threading
import time
from pathlib import Path

from pipeline.locks import flock
from tests.conftest import REPO, TOY_OVERRIDES, cli_command, cli_env, wait_for

TOY = [*TOY_OVERRIDES, "run.progress=false"]


def test_a_waiting_writer_gets_the_lock_when_the_current_reader_leaves(tmp_path):
    """A reader that takes the lock again at once, stage after stage, used to keep a writer polling every 50 ms
    out for its whole chain (it never hit the microsecond gap); now the writer queues and the reader's next
    hold waits for it."""
    lock, hold_s, holds = tmp_path / "a.lock", 0.4, 10
    reader_holds: list[float] = []

    def reader() -> None:
        for _ in range(holds):
            with flock(lock, shared=True, timeout_s=30, what="the reader"):
                reader_holds.append(time.monotonic())
                time.sleep(hold_s)

    thread = threading.Thread(target=reader)
    thread.start()
    wait_for(lambda: len(reader_holds) >= 1)
    asked = time.monotonic()
    with flock(lock, shared=False, timeout_s=30, what="the writer"):
        waited = time.monotonic() - asked
        holds_before = len(reader_holds)
    thread.join()
    assert waited < 3 * hold_s, f"the writer waited {waited:.2f} s through {holds_before} reader holds"
    assert holds_before < holds, "the writer got the lock only after the reader's last hold"


def _queued(lock: Path) -> bool:
    """Whether a run waits in ``lock``'s turnstile now."""
    fd = os.open(lock.with_name(lock.name + ".queue"), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        cli_command(*args), cwd=REPO, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def _events(trace: Path) -> list[list[str]]:
    return [line.split() for line in trace.read_text().splitlines()]


def _waits_in_turnstile(pid: int, lock: Path) -> bool:
    """Whether process ``pid`` has ``lock``'s turnstile open (it waits there, or holds it)."""
    turnstile = str(lock.with_name(lock.name + ".queue"))
    try:
        return any(os.readlink(fd) == turnstile for fd in Path(f"/proc/{pid}/fd").iterdir())
    except OSError:  # a descriptor closed while listing
        return False


def test_a_forced_shared_stage_is_written_before_later_readers_of_it(tmp_path):
    """Readers overlapping one another (here two runs: b, then d, both reading a) used to hold a shared stage
    without a gap, so a run that must rewrite it waited until the last of them ended. Now a reader that comes
    after the waiting writer waits behind it. Reader b holds its stage until the writer and reader d both wait (not
    for a fixed time, which a loaded machine's start-up of the two runs can outlast)."""
    out, trace, release = tmp_path / "out", tmp_path / "trace.log", tmp_path / "release"
    base = [*TOY, f"paths.outputs={out}"] + [f"++stage.{s}.trace={trace}" for s in "abcd"]
    assert subprocess.run(cli_command(*base), cwd=REPO, env=cli_env(), capture_output=True).returncode == 0
    trace.unlink()
    lock = out / "synth_a" / ".locks" / "a.lock"
    reader_b = _start(*base, "run.only=b", "run.force=true", f"++stage.b.hold_until={release}")
    wait_for(lambda: trace.exists() and "b start" in trace.read_text())
    writer = _start(*base, "run.only=a", "run.force=true")
    wait_for(lambda: _queued(lock), timeout_s=120)
    reader_d = _start(*base, "run.only=d", "run.force=true")
    wait_for(lambda: _waits_in_turnstile(reader_d.pid, lock), timeout_s=120)
    release.touch()
    outputs = [p.communicate(timeout=180)[0] for p in (reader_b, writer, reader_d)]
    assert [p.returncode for p in (reader_b, writer, reader_d)] == [0, 0, 0], outputs
    order = [(e[0], e[1]) for e in _events(trace)]
    assert order == [("b", "start"), ("b", "end"), ("a", "start"), ("a", "end"), ("d", "start"), ("d", "end")], order


def test_two_methods_started_together_share_a_stage_once_and_train_side_by_side(tmp_path):
    """Two methods whose p has the same cache key, started at once: one computes p while the other waits for it
    and shares it (both used to compute it when they arrived together), then their own q run side by side."""
    out, trace = tmp_path / "out", tmp_path / "trace.log"
    base = [
        "pipeline.stages_module=tests.toy_methods",
        "stage=[]",
        "+stage.a.value=1",
        "+stage.cmp.methods=[m1,m2]",
        "+stage.cmp.seeds=[0]",
        "+method.p_value=1",
        "+method.sleep_s=3",
        f"+method.trace={trace}",
        f"paths.outputs={out}",
        "run.progress=false",
        "run.until=q",
    ]
    runs = [_start(*base, f"method.name={m}") for m in ("m1", "m2")]
    outputs = [p.communicate(timeout=180)[0] for p in runs]
    assert [p.returncode for p in runs] == [0, 0], outputs
    events = _events(trace)
    assert [e[:3] for e in events if e[0] == "p"] in ([["p", m, "start"], ["p", m, "end"]] for m in ("m1", "m2")), (
        events
    )  # p computed by one run only
    both = "\n".join(outputs)
    assert both.count("p          run") == 1 and both.count("p          shared") == 1, both
    assert "waits     for another method's run computing the same artifact" in both, both
    q = {(e[1], e[2]): float(e[3]) for e in events if e[0] == "q"}
    assert max(q["m1", "start"], q["m2", "start"]) < min(q["m1", "end"], q["m2", "end"]), q  # side by side
    assert os.path.samefile(
        out / "synth_a" / "methods" / "m1" / "p" / "p.txt", out / "synth_a" / "methods" / "m2" / "p" / "p.txt"
    )
