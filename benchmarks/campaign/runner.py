"""The campaign's runner: works through the queue's unfinished cells, one thread per run, at the lowest CPU priority,
and commits each finished cell's metrics to the result file as it completes.

Where things go (``--outputs``, default ``outputs/campaign/``, which git ignores):

- ``<setting>/``: the app's outputs folder of the setting's cells (``paths.outputs``), so the cells of one setting and
  subject share their capture, tracking and contact stages, and a cell cut off by a kill resumes from its last
  finished stage (the app's own cache) when the runner starts again;
- ``code/<commit>/``: a ``git worktree`` of the checkout's newest commit of code (:func:`code_head`: HEAD, passing
  over the runner's own commits of results) when the cell starts, removed once no cell runs it. Cells run
  committed code only: edits in progress in the checkout never reach a measurement, and each record names the commit
  it was trained at;
- ``logs/<cell>.log``: each cell's output; ``runner.log``: the runner's own lines (``start``);
- ``runner.lock``: held (flock) by the one runner of the folder, with its pid; ``state.json``: the cells in progress;
  ``failed.json``: cells whose run failed, with the commit and the log (a failed cell is tried again only at another
  commit).

Stopping (``stop``, SIGTERM or Ctrl-C) ends the cells in progress and exits: at most those cells are lost, no result
is half written (the result file is replaced atomically, and committed after).
"""

from __future__ import annotations

import dataclasses
import datetime
import fcntl
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.campaign.cells import Cell, Queue
from benchmarks.campaign.priority import current_priority, lowest_priority
from benchmarks.campaign.results import ResultFile, cell_metrics
from benchmarks.campaign.tables import render
from pipeline.device import cpu_name
from reporting.method_runs import read_run

REPO = Path(__file__).resolve().parents[2]
#: the stages a cell runs (the app's run.until): its method trained and evaluated, nothing after
UNTIL = "evaluate"
#: how long a cell waits for another cell holding a shared stage's lock (the app's run.lock_timeout_s)
LOCK_TIMEOUT_S = 7 * 24 * 3600


@dataclasses.dataclass
class Options:
    """How the runner runs: the queue, the result file, the outputs folder, where the code comes from (``code``:
    None for a worktree of the checkout's newest code per cell, else this folder's code as it is), the command that
    starts the app (``launcher``: run in the code folder), parallel cells (``jobs``) and whether to commit results."""

    queue: Queue
    results: Path
    outputs: Path
    code: Path | None = None
    launcher: tuple[str, ...] = (sys.executable, "-m", "pipeline.launch")
    jobs: int = 1
    commit: bool = True
    log: Callable[[str], None] = print


class Stopped(Exception):
    """The runner was asked to stop (SIGTERM, Ctrl-C)."""


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def code_commit(code: Path) -> str:
    """The short commit of the code folder ``code`` (``+dirty`` when it has uncommitted edits), ``unknown`` outside
    git."""
    try:
        sha = _git("rev-parse", "--short", "HEAD", cwd=code)
        dirty = _git("status", "--porcelain", "--untracked-files=no", cwd=code)
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")


#: what the campaign itself commits (its result files and their pages): never a reason to run a cell on new code
RESULT_PATHS = ("benchmarks/results", "docs/results")


def code_head(repo: Path = REPO) -> str:
    """The short commit of ``repo``'s newest commit that changed anything but :data:`RESULT_PATHS`: the runner's own
    commits of finished cells leave the code the next cell runs (and its worktree) as it is."""
    return _git("log", "-1", "--format=%h", "HEAD", "--", ".", *(f":!{p}" for p in RESULT_PATHS), cwd=repo)


class Runner:
    """One campaign runner (see the module's docstring); :meth:`run` until the queue is done or it is stopped."""

    def __init__(self, options: Options) -> None:
        self.o = options
        self.results = ResultFile(options.results)
        self.lock = threading.Lock()  # the result file, the state and git
        self.running: dict[Cell, subprocess.Popen[bytes]] = {}
        self.claimed: set[Cell] = set()
        self.in_use: dict[Path, int] = {}  # worktree -> cells running its code
        self.short: dict[str, str] = {}  # a pinned commit as the queue names it -> its short commit
        self.stopping = threading.Event()
        self.failed_path = options.outputs / "failed.json"
        self.failed: dict[str, dict[str, Any]] = (
            json.loads(self.failed_path.read_text()) if self.failed_path.is_file() else {}
        )

    # -- the queue -------------------------------------------------------------------------------------------------

    def pending(self) -> list[Cell]:
        """The queue's cells with no record, in queue order."""
        return [c for c in self.o.queue.cells if not self.results.finished(c, self.o.queue.quality)]

    def _next(self) -> Cell | None:
        """The first pending cell that no job runs and that did not fail at the commit it would run now."""
        with self.lock:
            for cell in self.pending():
                failed = self.failed.get(cell.key)
                if cell in self.claimed or (failed is not None and failed["commit"] == self._commit_of(cell)):
                    continue
                self.claimed.add(cell)
                return cell
        return None

    # -- one cell --------------------------------------------------------------------------------------------------

    def _pinned(self, cell: Cell) -> str | None:
        """The short commit ``cell``'s setting pins (a bisect's), or None: the newest code."""
        commit = self.o.queue.settings[cell.setting].commit
        if commit is not None and commit not in self.short:
            self.short[commit] = _git("rev-parse", "--short", f"{commit}^{{commit}}", cwd=REPO)
        return None if commit is None else self.short[commit]

    def _commit_of(self, cell: Cell) -> str:
        """The commit ``cell`` runs at now."""
        if self.o.code is not None:
            return code_commit(self.o.code)
        return self._pinned(cell) or code_head()

    def _code(self, cell: Cell) -> tuple[Path, str]:
        """(the folder whose code ``cell`` runs, its commit): the worktree of the commit its setting pins, else of
        :func:`code_head` (each made once)."""
        if self.o.code is not None:
            return self.o.code, code_commit(self.o.code)
        sha = self._commit_of(cell)
        tree = self.o.outputs / "code" / sha
        with self.lock:
            if not (tree / ".git").exists():
                tree.parent.mkdir(parents=True, exist_ok=True)
                _git("worktree", "add", "--detach", "--force", str(tree), sha, cwd=REPO)
            self.in_use[tree] = self.in_use.get(tree, 0) + 1
        return tree, sha

    def _release(self, tree: Path) -> None:
        """A cell is done with ``tree``: remove the worktrees that no cell runs any more, but the newest code's and
        those of the commits the queue pins."""
        if self.o.code is not None:
            return
        with self.lock:
            self.in_use[tree] -= 1
            kept = {code_head()} | {self._pinned(c) for c in self.pending()} - {None}
            for other in sorted((self.o.outputs / "code").glob("*")):
                if other.name not in kept and not self.in_use.get(other):
                    subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=REPO, capture_output=True)
                    self.in_use.pop(other, None)
            subprocess.run(["git", "worktree", "prune"], cwd=REPO, capture_output=True)

    def command(self, cell: Cell, code: Path) -> list[str]:
        """The app's command line of ``cell``."""
        setting = self.o.queue.settings[cell.setting]
        launcher = list(self.o.launcher)
        if launcher[1:] == ["-m", "pipeline.launch"] and not (code / "pipeline" / "launch.py").is_file():
            launcher[-1] = "pipeline.cli"  # a commit older than the light entry point (a bisect's)
        return [
            *launcher,
            f"paths.outputs={self.o.outputs / cell.setting}",
            f"subject={cell.subject}",
            f"quality={self.o.queue.quality}",
            f"method={cell.method}",
            f"seed={cell.seed}",
            f"run.until={UNTIL}",
            "run.progress=false",
            f"run.lock_timeout_s={LOCK_TIMEOUT_S}",
            *setting.overrides,
        ]

    def run_cell(self, cell: Cell, code: Path, commit: str) -> bool:
        """Train and evaluate ``cell`` with the code in ``code`` (at ``commit``), then record and commit its metrics;
        False when its run failed."""
        log_path = self.o.outputs / "logs" / (cell.key.replace("/", "_") + ".log")
        log_path.parent.mkdir(parents=True, exist_ok=True)
        command = self.command(cell, code)
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(code), "PYTHONUNBUFFERED": "1"}
        self._state()
        started, load = time.monotonic(), os.getloadavg()
        self.o.log(f"campaign: {cell.key} at {commit}: {shlex.join(command)}")
        with open(log_path, "wb") as log:
            log.write(f"$ {shlex.join(command)}\n".encode())
            log.flush()
            # its own process group to stop it by, in the runner's session: a session of its own would be an autogroup
            # of its own, at nice 0
            proc = subprocess.Popen(command, cwd=code, env=env, stdout=log, stderr=subprocess.STDOUT, process_group=0)
            with self.lock:
                self.running[cell] = proc
            if self.stopping.is_set():
                _end(proc)
            returncode = proc.wait()
            with self.lock:
                del self.running[cell]
        if self.stopping.is_set():
            raise Stopped
        if returncode != 0:
            self.o.log(f"campaign: {cell.key} failed (exit {returncode}); its log: {log_path}")
            with self.lock:
                self.failed[cell.key] = {"commit": commit, "exit": returncode, "log": str(log_path), "date": _now()}
                _write_json(self.failed_path, self.failed)
            return False
        record = self._record(cell, commit, time.monotonic() - started, load)
        self._publish(cell, record)
        return True

    def _record(self, cell: Cell, commit: str, wall_s: float, load: tuple[float, float, float]) -> dict[str, Any]:
        subject = self.o.outputs / cell.setting / cell.subject / "methods" / cell.run
        run = read_run(cell.method, cell.seed, {s: subject / s for s in ("warmup", "dynamic", "evaluate")})
        return {
            "setting": cell.setting,
            "subject": cell.subject,
            "method": cell.method,
            "seed": cell.seed,
            "quality": self.o.queue.quality,
            "overrides": list(self.o.queue.settings[cell.setting].overrides),
            "commit": commit,
            "date": _now(),
            "machine": {"cpu": cpu_name(), "cores": os.cpu_count()},
            "threads": 1,
            "wall_s": round(wall_s, 1),
            "load": {"start": [round(x, 2) for x in load], "end": [round(x, 2) for x in os.getloadavg()]},
            "train_steps": run.train_steps,
            "train_wall_s": round(run.train_wall_s, 1),
            "gaussians": run.gaussians,
            "metrics": cell_metrics(run),
        }

    def _publish(self, cell: Cell, record: dict[str, Any]) -> None:
        """Add the cell's record to the result file and its table page, and commit both."""
        with self.lock:
            self.results.add(record)
            self.results.save()
            page = self.o.results.with_suffix(".md")
            page.write_text(render(self.o.queue, self.results.rows()) + "\n")
            novel_view = ("novel_view", "full", "all")
            full = next(
                (m["psnr"] for m in record["metrics"] if (m["split"], m["region"], m["contact"]) == novel_view),
                float("nan"),
            )
            message = f"campaign: {cell.key} at {record['quality']} (code {record['commit']}): novel view {full:.2f} dB"
            self.o.log(message)
            written = [self.o.results, page, *write_docs_pages(self.o.results)]
            if self.o.commit:
                commit_files(written, message, self.o.log)

    def _state(self) -> None:
        with self.lock:
            _write_json(
                self.o.outputs / "state.json", {"pid": os.getpid(), "in_progress": sorted(c.key for c in self.claimed)}
            )

    # -- the loop --------------------------------------------------------------------------------------------------

    def work(self) -> None:
        """One job: cells until none is left or the runner stops."""
        while not self.stopping.is_set():
            cell = self._next()
            if cell is None:
                return
            code, commit = self._code(cell)
            try:
                self.run_cell(cell, code, commit)
            except Stopped:
                return
            finally:
                with self.lock:
                    self.claimed.discard(cell)
                self._release(code)
                self._state()

    def stop(self) -> None:
        """End the cells in progress (SIGTERM to their process groups) and take no new one."""
        self.stopping.set()
        with self.lock:
            for proc in self.running.values():
                _end(proc)

    def run(self) -> int:
        """Work through the queue with ``jobs`` cells at a time; 0 when no cell is left to run, 1 when some
        failed, 130 when stopped."""
        self.o.outputs.mkdir(parents=True, exist_ok=True)
        with hold_lock(self.o.outputs / "runner.lock"):
            priority = current_priority()
            self.o.log(
                f"campaign: {len(self.pending())} of {len(self.o.queue.cells)} cells to run, {self.o.jobs} at a time, "
                f"at {priority.describe()}"
            )
            jobs = [threading.Thread(target=self.work, daemon=True) for _ in range(self.o.jobs)]
            for job in jobs:
                job.start()
            for job in jobs:
                while job.is_alive():
                    job.join(timeout=0.5)
            _write_json(self.o.outputs / "state.json", {"pid": None, "in_progress": []})
        if self.stopping.is_set():
            self.o.log("campaign: stopped; the cells in progress were ended and will run again at the next start")
            return 130
        left = self.pending()
        self.o.log(f"campaign: done for now; {len(left)} cell(s) left" + (" (failed: see failed.json)" if left else ""))
        return 1 if left else 0


def write_docs_pages(results: Path) -> list[Path]:
    """The documentation's page of the result file and the results index (benchmarks/render_results.py), rewritten
    where they changed, when the result file is the committed one (benchmarks/results/); the pages written."""
    from benchmarks.render_results import DOCS_RESULTS, results_pages

    if results.parent != REPO / "benchmarks" / "results":
        return []
    pages = results_pages()
    written = []
    for path in (DOCS_RESULTS / f"{results.stem}.md", DOCS_RESULTS / "index.md"):
        if not path.is_file() or path.read_text() != pages[path]:
            path.write_text(pages[path])
            written.append(path)
    return written


def _end(proc: subprocess.Popen[bytes]) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def _write_json(path: Path, data: Any) -> None:
    partial = path.with_name(f".{path.name}.partial")
    partial.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(partial, path)


class AlreadyRunning(RuntimeError):
    """Another runner holds the outputs folder's lock."""


class hold_lock:
    """Hold ``path``'s exclusive flock (with this process's pid written in it) for a ``with`` block;
    :class:`AlreadyRunning` naming the holder's pid when another process holds it."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self.fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(self.fd)
            raise AlreadyRunning(f"a campaign runner (pid {holder}) already works in {self.path.parent}") from None
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, f"{os.getpid()}\n".encode(), 0)

    def __exit__(self, *exc: object) -> None:
        os.ftruncate(self.fd, 0)
        os.close(self.fd)


def lock_holder(path: Path) -> int | None:
    """The pid of the runner holding ``path`` (a runner.lock), None when no process holds it."""
    if not path.is_file():
        return None
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        text = path.read_text().strip()
        return int(text) if text.isdigit() else -1
    finally:
        os.close(fd)
    return None


def commit_files(paths: list[Path], message: str, log: Callable[[str], None], attempts: int = 30) -> bool:
    """Commit ``paths`` (and only them: other staged or edited files are left as they are) in their repository,
    retrying while another git command holds the index; False (said in ``log``) when it could not."""
    repo = Path(_git("rev-parse", "--show-toplevel", cwd=paths[0].parent))
    names = [str(p.resolve().relative_to(repo)) for p in paths]
    for attempt in range(attempts):
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", "--", *names], cwd=repo, capture_output=True)
        unchanged = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", *names], cwd=repo, capture_output=True)
        if tracked.returncode == 0 and unchanged.returncode == 0:
            return True  # nothing new to commit
        added = subprocess.run(["git", "add", "--", *names], cwd=repo, capture_output=True, text=True)
        done = added.returncode == 0 and (
            subprocess.run(
                ["git", "commit", "-q", "-m", message, "--only", "--", *names], cwd=repo, capture_output=True, text=True
            ).returncode
            == 0
        )
        if done:
            return True
        time.sleep(min(2.0 * (attempt + 1), 20.0))  # another git command holds index.lock
    log(f"campaign: could not commit {', '.join(names)}; they are written, commit them by hand")
    return False


def lowest_priority_or_say(log: Callable[[str], None]) -> None:
    """:func:`benchmarks.campaign.priority.lowest_priority`, saying so when the process does not lead a session."""
    try:
        lowest_priority()
    except RuntimeError as err:
        log(f"campaign: {err}; running at {current_priority().describe()}")
