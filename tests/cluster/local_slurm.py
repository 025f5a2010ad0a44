"""A real single-node SLURM cluster on localhost, for the ``cluster`` tests (``make test-slurm``).

The daemons a real site runs, each started here in the foreground as a child of the test:
munge (authentication), MariaDB and slurmdbd (accounting: ``sacct``, which submitit polls for job
states, needs it), slurmctld and slurmd. Everything lives under one directory -- generated
``slurm.conf`` and ``slurmdbd.conf``, the munge key, the database, spool, state and logs -- every
daemon listens on 127.0.0.1 on ports found free at start, and clients find the cluster through
``SLURM_CONF`` (:meth:`LocalSlurm.env`), so nothing of the machine's own configuration is read or
changed. :meth:`LocalSlurm.stop` cancels the jobs, stops exactly the processes it started (by process
id) and removes the directory.
"""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

CLUSTER = "interactavatar-test"
PARTITION = "debug"
# The commands the cluster needs, and the Debian package of each.
COMMANDS = {
    "slurmctld": "slurm-wlm",
    "slurmd": "slurm-wlm",
    "sbatch": "slurm-wlm",
    "sacct": "slurm-wlm",
    "slurmdbd": "slurmdbd",
    "munged": "munge",
    "munge": "munge",
    "mariadbd": "mariadb-server",
    "mariadb-install-db": "mariadb-server",
    "mariadb": "mariadb-client",
}
_SBIN = os.pathsep.join(["/usr/local/sbin", "/usr/sbin", "/sbin"])


class ClusterError(RuntimeError):
    """The local cluster could not be installed or started (the message names the log to read)."""


def which(command: str) -> str | None:
    """``command``'s path, looking in the sbin directories too (daemons live there; PATH may lack them)."""
    return shutil.which(command, path=os.environ.get("PATH", "") + os.pathsep + _SBIN)


def ensure_installed() -> None:
    """Install the missing SLURM, munge and MariaDB packages from Debian's archive (as root), or raise
    :class:`ClusterError` saying which packages to install."""
    missing = sorted({pkg for cmd, pkg in COMMANDS.items() if which(cmd) is None})
    if not missing:
        return
    how = f"apt-get install -y {' '.join(missing)}"
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise ClusterError(f"the SLURM test needs the packages {', '.join(missing)}: install them with `{how}`")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for attempt in (
        ["apt-get", "install", "-y", *missing],
        ["apt-get", "update"],
        ["apt-get", "install", "-y", *missing],
    ):
        done = subprocess.run(attempt, env=env, capture_output=True, text=True, check=False)
        if done.returncode == 0 and attempt[1] == "install":
            return
    raise ClusterError(f"`{how}` failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(ready: Callable[[], bool], what: str, log: Path | None, timeout_s: float = 60.0) -> None:
    """Poll ``ready`` every 0.2 s; :class:`ClusterError` naming ``what`` and the tail of ``log`` on timeout."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        if time.monotonic() > deadline:
            tail = log.read_text(errors="replace")[-3000:] if log is not None and log.is_file() else ""
            raise ClusterError(f"{what} not ready after {timeout_s:.0f} s (log {log}):\n{tail}")
        time.sleep(0.2)


def _succeeds(*cmd: str, env: dict[str, str] | None = None) -> bool:
    return subprocess.run(cmd, env=env, capture_output=True, check=False).returncode == 0


def _accepts(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


class LocalSlurm:
    """One SLURM cluster of one node (this machine, all its CPUs) under ``root``.

    Use as a context manager, or :meth:`start` then :meth:`stop`. The database password is a test
    secret of this throw-away MariaDB, reachable only on 127.0.0.1.
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        self.user = getpass.getuser()
        self.node = socket.gethostname().split(".")[0]
        self.ports = {name: free_port() for name in ("slurmctld", "slurmd", "slurmdbd", "mariadb")}
        self.munge_socket = root / "munge" / "munge.socket"
        self.db_socket = root / "mariadb.socket"
        self.logs = root / "log"
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    # -- configuration ---------------------------------------------------------------------------------
    def env(self) -> dict[str, str]:
        """The environment of a client of this cluster (sbatch, squeue, sacct, scancel, submitit)."""
        path = os.environ.get("PATH", "") + os.pathsep + _SBIN
        return {**os.environ, "SLURM_CONF": str(self.root / "slurm.conf"), "PATH": path}

    def _write_configs(self) -> None:
        mem_mb = int(_mem_total_mb() * 0.8)
        slurm_conf = f"""\
ClusterName={CLUSTER}
SlurmctldHost={self.node}(127.0.0.1)
SlurmctldPort={self.ports["slurmctld"]}
SlurmdPort={self.ports["slurmd"]}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.munge_socket}
SlurmUser={self.user}
SlurmdUser={self.user}
StateSaveLocation={self.root / "state"}
SlurmdSpoolDir={self.root / "spool"}
SlurmctldPidFile={self.root / "slurmctld.pid"}
SlurmdPidFile={self.root / "slurmd.pid"}
SlurmctldLogFile={self.logs / "slurmctld.log"}
SlurmdLogFile={self.logs / "slurmd.log"}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
ReturnToService=2
MpiDefault=none
KillWait=1
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStoragePort={self.ports["slurmdbd"]}
AccountingStoragePass={self.munge_socket}
NodeName={self.node} NodeAddr=127.0.0.1 CPUs={os.cpu_count()} RealMemory={mem_mb} State=UNKNOWN
PartitionName={PARTITION} Nodes={self.node} Default=YES MaxTime=INFINITE State=UP
"""
        dbd_conf = f"""\
AuthType=auth/munge
AuthInfo=socket={self.munge_socket}
DbdHost=localhost
DbdAddr=127.0.0.1
DbdPort={self.ports["slurmdbd"]}
SlurmUser={self.user}
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort={self.ports["mariadb"]}
StorageUser=slurm
StoragePass=test-only
StorageLoc=slurm_acct_db
PidFile={self.root / "slurmdbd.pid"}
LogFile={self.logs / "slurmdbd.log"}
"""
        (self.root / "slurm.conf").write_text(slurm_conf)
        (self.root / "slurmdbd.conf").write_text(dbd_conf)
        (self.root / "slurmdbd.conf").chmod(0o600)  # slurmdbd refuses a readable one: it holds a password

    # -- daemons ---------------------------------------------------------------------------------------
    def _spawn(self, name: str, *cmd: str) -> None:
        """Start ``cmd`` in the foreground of its own session (pytest's signals never reach it)."""
        out = open(self.logs / f"{name}.out", "wb")  # kept open for the daemon's life
        self.procs[name] = subprocess.Popen(
            cmd, stdout=out, stderr=subprocess.STDOUT, env=self.env(), start_new_session=True
        )

    def _check_alive(self, name: str) -> Callable[[], bool]:
        def alive() -> bool:
            if self.procs[name].poll() is not None:
                out = (self.logs / f"{name}.out").read_text(errors="replace")[-2000:]
                raise ClusterError(f"{name} exited with {self.procs[name].returncode}: {out}")
            return True

        return alive

    def start(self) -> LocalSlurm:
        """Write the configuration and start munged, MariaDB, slurmdbd, slurmctld and slurmd, each
        waited for; on any failure the ones started are stopped again."""
        for sub in ("munge", "state", "spool", "log", "db"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.root.chmod(0o755)  # munged wants its socket's directories searchable by all
        (self.root / "munge").chmod(0o755)
        key = self.root / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self._write_configs()
        try:
            self._start_munge()
            self._start_database()
            self._start_slurm()
        except BaseException:
            self.stop()
            raise
        return self

    def _start_munge(self) -> None:
        munge = self.root / "munge"
        self._spawn(
            "munged",
            which("munged") or "munged",
            "--foreground",
            "--force",
            f"--socket={self.munge_socket}",
            f"--key-file={munge / 'munge.key'}",
            f"--log-file={self.logs / 'munged.log'}",
            f"--pid-file={munge / 'munged.pid'}",
            f"--seed-file={munge / 'munged.seed'}",
        )
        alive = self._check_alive("munged")
        wait_until(
            lambda: alive() and _succeeds("munge", "-S", str(self.munge_socket), "-n"),
            "munged",
            self.logs / "munged.log",
        )

    def _start_database(self) -> None:
        done = subprocess.run(
            [
                which("mariadb-install-db") or "mariadb-install-db",
                "--no-defaults",
                f"--datadir={self.root / 'db'}",
                f"--user={self.user}",
                "--skip-test-db",
                "--auth-root-authentication-method=normal",
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode:
            raise ClusterError(f"mariadb-install-db failed: {done.stderr[-2000:]}")
        self._spawn(
            "mariadbd",
            which("mariadbd") or "mariadbd",
            "--no-defaults",
            f"--datadir={self.root / 'db'}",
            f"--user={self.user}",
            f"--socket={self.db_socket}",
            f"--port={self.ports['mariadb']}",
            "--bind-address=127.0.0.1",
            f"--pid-file={self.root / 'mariadb.pid'}",
            f"--log-error={self.logs / 'mariadb.log'}",
            "--innodb-buffer-pool-size=64M",
        )
        alive = self._check_alive("mariadbd")
        sql = ["mariadb", "--no-defaults", "-S", str(self.db_socket), "-u", "root"]
        wait_until(lambda: alive() and _succeeds(*sql, "-e", "SELECT 1"), "MariaDB", self.logs / "mariadb.log")
        grant = "; ".join(
            f"CREATE USER 'slurm'@'{h}' IDENTIFIED BY 'test-only'; GRANT ALL ON slurm_acct_db.* TO 'slurm'@'{h}'"
            for h in ("localhost", "127.0.0.1")
        )
        done = subprocess.run([*sql, "-e", grant], capture_output=True, text=True, check=False)
        if done.returncode:
            raise ClusterError(f"creating the accounting database user failed: {done.stderr}")

    def _start_slurm(self) -> None:
        env = self.env()
        self._spawn("slurmdbd", which("slurmdbd") or "slurmdbd", "-D")
        alive = self._check_alive("slurmdbd")
        wait_until(lambda: alive() and _accepts(self.ports["slurmdbd"]), "slurmdbd", self.logs / "slurmdbd.log")
        self._spawn("slurmctld", which("slurmctld") or "slurmctld", "-D", "-i")
        alive = self._check_alive("slurmctld")
        # slurmctld registers the cluster with slurmdbd on start; without that sacct knows no job.
        wait_until(
            lambda: (
                alive()
                and CLUSTER
                in subprocess.run(
                    ["sacctmgr", "-n", "-P", "show", "cluster", "format=cluster"],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=False,
                ).stdout
            ),
            "slurmctld (cluster registration)",
            self.logs / "slurmctld.log",
        )
        self._spawn("slurmd", which("slurmd") or "slurmd", "-D", "-N", self.node)
        alive = self._check_alive("slurmd")
        wait_until(
            lambda: (
                alive()
                and subprocess.run(
                    ["sinfo", "-h", "-n", self.node, "-o", "%T"], env=env, capture_output=True, text=True, check=False
                ).stdout.strip()
                == "idle"
            ),
            "slurmd (node idle)",
            self.logs / "slurmd.log",
        )

    def stop(self) -> None:
        """Cancel every job, stop the daemons this object started (newest first: SIGTERM, then SIGKILL
        after 20 s) and remove the cluster's directory."""
        if "slurmctld" in self.procs and self.procs["slurmctld"].poll() is None:
            subprocess.run(["scancel", "--user", self.user], env=self.env(), capture_output=True, check=False)
            wait_until_quiet = time.monotonic() + 30
            while time.monotonic() < wait_until_quiet and self.jobs():
                time.sleep(0.5)
        for name in reversed(list(self.procs)):
            proc = self.procs.pop(name)
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        shutil.rmtree(self.root, ignore_errors=True)

    # -- clients ---------------------------------------------------------------------------------------
    def jobs(self) -> dict[str, str]:
        """Job id -> state (squeue's) of the jobs the cluster still knows as pending or running."""
        out = subprocess.run(
            ["squeue", "-h", "-o", "%i %T"], env=self.env(), capture_output=True, text=True, check=False
        ).stdout
        return dict(line.split() for line in out.splitlines() if line.strip())

    def stdout_path(self, job_id: str) -> Path | None:
        """Where job ``job_id`` writes its standard output (``scontrol show job``), while it is known."""
        out = subprocess.run(
            ["scontrol", "show", "job", job_id], env=self.env(), capture_output=True, text=True, check=False
        ).stdout
        for field in out.split():
            if field.startswith("StdOut="):
                return Path(field.removeprefix("StdOut="))
        return None

    def accounting(self) -> list[dict[str, str]]:
        """sacct's rows of every job of this cluster (allocations only): JobID, JobName, State, Start, End,
        Elapsed."""
        keys = ("JobID", "JobName", "State", "Start", "End", "Elapsed")
        out = subprocess.run(
            ["sacct", "-a", "-X", "-P", "-n", "-o", ",".join(keys)],
            env=self.env(),
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        return [dict(zip(keys, line.split("|"), strict=True)) for line in out.splitlines() if line]

    def __enter__(self) -> LocalSlurm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _mem_total_mb() -> int:
    """The machine's memory in MB, as slurmd reads it (/proc/meminfo)."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024
    raise ClusterError("/proc/meminfo has no MemTotal")
