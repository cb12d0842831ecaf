"""`comexp` on a real multi-node Ray cluster on loopback, and the faults a sweep must survive.

The head runs on 127.0.0.2 and a second node on 127.0.0.3 (Ray rewrites 127.0.0.1 to the
routable address; other 127.x addresses it leaves alone), each from `ray start --block` in its
own session and its own short temp dir, so the test can find every process it started and
kill exactly those (never `ray stop`: it would end other users' Ray sessions on this machine).

Faults, each checked against the database (every episode stored exactly once, all ok):
(a) the second node's raylet is SIGKILLed mid-sweep (and the whole node, for comparison);
(b) one worker (actor) process is SIGKILLed mid-sweep;
(c) the driver is SIGKILLed mid-sweep: the same command resumes, a third run stores nothing;
(d) two sweeps write one SQLite file at once (overlapping grids).
The sweeps run the tests' backend (tests/scripted_backend.py: planar episodes, each build
slowed by 0.25 s) so that there is time to strike part-way; one test runs real pybullet
episodes across both nodes.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

TESTS_DIR = str(Path(__file__).resolve().parent)
BIN = Path(sys.executable).parent
HEAD_IP, NODE_IP = "127.0.0.2", "127.0.0.3"
# the tests' backend, every build slowed down (a plug-in: every node imports it from TESTS_DIR)
SCRIPTED = (
    f"hydra.searchpath=[file://{TESTS_DIR}/conf]",
    "backend=scripted",
    "+backend.options.build_sleep_s=0.25",
)
# 20 objects x 2 CoMs = 40 episodes of 0.25 s: ~5 s per worker pair, time to strike part-way
SWEEP = [
    "grid.coms_per_object=2",
    "grid.izz_scales=[1]",
    "floor.mu=[1.0]",
    "pusher.mu=[1.0]",
    "execution.batch_size=2",
    "execution.restart_timeout_s=20",
]
N_SWEEP = 40
_READY = re.compile(r"worker (\d+) ready: pid (\d+) on node (\S+)")
_PER_NODE = re.compile(r"episodes per node: (.*)")


# --- processes we start, and only those ----------------------------------------------------------


def _free_port(ip: str = HEAD_IP) -> int:
    with socket.socket() as s:
        s.bind((ip, 0))
        return s.getsockname()[1]


def _pids_with(needle: str) -> list[int]:
    """Processes whose command line contains `needle` (our private temp dir)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if needle in cmd:
            out.append(int(d.name))
    return out


def _in_sessions(sids: set[int]) -> list[int]:
    """Processes in one of the sessions `sids` (Ray's agents rename themselves `ray::...`,
    so their command line does not name our temp dir; their session still says whose they are).
    """
    return [
        int(d.name)
        for d in Path("/proc").iterdir()
        if d.name.isdigit() and _session_of(int(d.name)) in sids and int(d.name) not in sids
    ]


def _session_of(pid: int) -> int | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[3])  # after "comm": state ppid pgrp sid


def _state(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return None


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


class LoopbackCluster:
    """A Ray head and extra nodes on 127.0.0.x, every process tracked for an exact stop.

    Each `ray start --block` runs in a new session; Ray's daemons (gcs, raylet, workers) stay
    in it, so `os.killpg(session)` plus a sweep of processes that mention our temp dirs stops
    exactly what we started.
    """

    def __init__(self, cpus_per_node: int = 1) -> None:
        self.cpus = cpus_per_node
        self.port = _free_port()
        self.address = f"{HEAD_IP}:{self.port}"
        self.root = tempfile.mkdtemp(prefix="cxc-", dir="/tmp")  # short: unix socket paths
        self.env = {
            k: v
            for k, v in os.environ.items()
            if k not in ("RAY_ADDRESS", "HYDRA_FULL_ERROR") and not k.startswith("RAY_AUTH")
        }
        self.env.update(
            PYTHONPATH=TESTS_DIR,
            RAY_USAGE_STATS_ENABLED="0",
            RAY_AUTH_MODE="token",
            RAY_AUTH_TOKEN=secrets.token_hex(32),  # in the environment only, never in ~/.ray
            # drivers put their zero-CPU join node's temp dir here: `leftovers` sees it
            TMPDIR=self.root,
        )
        self.nodes: dict[str, subprocess.Popen] = {}
        self.drivers: list[subprocess.Popen] = []

    # nodes ----------------------------------------------------------------------------------
    def temp_dir(self, ip: str) -> str:
        return os.path.join(self.root, ip.rsplit(".", 1)[1])

    def _start(self, ip: str, *args: str) -> None:
        os.makedirs(self.temp_dir(ip), exist_ok=True)
        self.nodes[ip] = subprocess.Popen(
            [
                str(BIN / "ray"),
                "start",
                *args,
                f"--node-ip-address={ip}",
                f"--temp-dir={self.temp_dir(ip)}",
                f"--num-cpus={self.cpus}",
                "--disable-usage-stats",
                "--block",
            ],
            env=self.env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )

    def start(self, n_nodes: int = 2, timeout_s: float = 150) -> None:
        self._start(HEAD_IP, "--head", f"--port={self.port}", "--include-dashboard=false")
        for i in range(1, n_nodes):
            self._start(f"127.0.0.{2 + i}", f"--address={self.address}")
        deadline = time.monotonic() + timeout_s
        while self.alive_nodes() < n_nodes:
            for ip, p in self.nodes.items():
                assert p.poll() is None, f"ray start for {ip} exited with {p.returncode}"
            assert time.monotonic() < deadline, "the loopback cluster did not come up"
            time.sleep(2)

    def alive_nodes(self) -> int:
        code = (
            f"import ray; ray.init(address={self.address!r}, logging_level='ERROR');"
            "print(sum(n['Alive'] for n in ray.nodes()))"
        )
        r = subprocess.run(
            [sys.executable, "-c", code], env=self.env, capture_output=True, text=True, timeout=90
        )
        return int(r.stdout.strip() or 0)

    def raylet_pid(self, ip: str) -> int:
        """The raylet of node `ip`: in that node's session, named raylet."""
        sid = self.nodes[ip].pid
        pids = [
            p
            for p in _pids_with(self.temp_dir(ip))
            if _session_of(p) == sid and "/raylet" in _cmdline(p).split(" ", 1)[0]
        ]
        assert len(pids) == 1, pids
        return pids[0]

    # drivers ----------------------------------------------------------------------------------
    def comexp(
        self, cwd: Path, *args: str, prefix: tuple[str, ...] = (), fake: bool = True
    ) -> Driver:
        """A driver on the cluster; `fake`: on the tests' slowed-down backend."""
        p = subprocess.Popen(
            [
                *prefix,
                str(BIN / "comexp"),
                f"ray.address={self.address}",
                *args,
                *(SCRIPTED if fake else ()),
            ],
            cwd=cwd,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.drivers.append(p)
        return Driver(p)

    # stopping ---------------------------------------------------------------------------------
    def sessions(self) -> set[int]:
        return {p.pid for p in self.nodes.values()}

    def leftovers(self) -> list[int]:
        """Live (not zombie) processes of ours after `stop`: should be none."""
        pids = {*_in_sessions(self.sessions()), *_pids_with(self.root)}
        return [p for p in pids if _state(p) not in ("Z", None)]

    def stop(self) -> None:
        for p in self.drivers:
            if p.poll() is None:
                p.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=30)
        for p in self.nodes.values():
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
        # Anything else of ours: still in a node's session (reparented after its parent
        # died), or a daemon that left the session but names our temp dir. Looked up before
        # the session leaders are reaped, so that their ids cannot have been reused.
        for _ in range(2):
            for pid in {*_in_sessions(self.sessions()), *_pids_with(self.root)}:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.2)
        for p in self.nodes.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=30)
        shutil.rmtree(self.root, ignore_errors=True)


class Driver:
    """A running `comexp`; its output is collected by a thread (it logs worker pids and the
    per-node episode counts, which the fault drills need while it runs)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def out(self) -> str:
        return "".join(self.lines)

    def workers(self) -> list[tuple[int, str]]:
        """(pid, node) of every worker the pool reported ready so far."""
        return [(int(m[2]), m[3]) for m in _READY.finditer(self.out)]

    def wait(self, timeout: float = 300) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._t.join(timeout=10)
        return rc


@pytest.fixture
def cluster() -> Iterator[LoopbackCluster]:
    c = LoopbackCluster()
    try:
        c.start()
        yield c
    finally:
        c.stop()
    time.sleep(0.5)
    assert not c.leftovers(), "a process of the test cluster outlived it"


# --- database checks -----------------------------------------------------------------------------


def _rows(db: Path, sql: str) -> list[tuple]:
    with sqlite3.connect(db) as c:
        return c.execute(sql).fetchall()


def _stored(db: Path) -> list[tuple[str, str]]:
    """(status, node) of the stored episodes; [] while the file or schema is not there."""
    if not db.exists():
        return []
    try:
        rows = _rows(db, "select status, worker from episodes")
        return [(status, worker.rsplit(":", 1)[0]) for status, worker in rows]
    except sqlite3.OperationalError:
        return []


def _assert_complete(db: Path, n: int) -> None:
    """Every episode exactly once, all ok, and a sound file."""
    assert _rows(db, "select count(*), count(distinct episode_key) from episodes") == [(n, n)]
    assert _rows(db, "select count(*) from episodes where status != 'ok'") == [(0,)]
    assert _rows(db, "pragma integrity_check") == [("ok",)]


def _report(fault: str, db: Path, expected: int, before: int, *outs: str) -> None:
    """One line per drill (shown with `pytest -rP`): what docs/operations.md quotes."""
    n, distinct = _rows(db, "select count(*), count(distinct episode_key) from episodes")[0]
    ok = _rows(db, "select count(*) from episodes where status = 'ok'")[0][0]
    out = "".join(outs)
    print(
        f"FAULT {fault}: expected {expected}, stored before the fault {before}, "
        f"stored {n}, ok {ok}, duplicated {n - distinct}, lost {expected - distinct}, "
        f"worker deaths noticed {out.count('a worker died')}, "
        f"replacements dropped {out.count('a replacement worker did not start')}, "
        f"integrity {_rows(db, 'pragma integrity_check')[0][0]}"
    )


def _strike_when(
    driver: Driver, ready: Callable[[], bool], strike: Callable[[], None], timeout_s: float = 240
) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert driver.proc.poll() is None, f"the sweep ended before the fault:\n{driver.out}"
        assert time.monotonic() < deadline, f"no fault opportunity:\n{driver.out}"
        time.sleep(0.2)
    strike()


def _per_node(out: str) -> dict[str, int]:
    m = _PER_NODE.findall(out)
    assert m, out
    return {k: int(v) for k, v in (item.rsplit(" ", 1) for item in m[-1].split(", "))}


def _both_nodes_stored(db: Path, at_least: int) -> bool:
    rows = _stored(db)
    return len(rows) >= at_least and len({node for _, node in rows}) == 2


# --- a driver on a machine that runs no Ray node ------------------------------------------------

_JOINED = re.compile(r"joined the Ray cluster at \S+ as a zero-CPU node \(temp dir (\S+)\)")
# Processes of a head only, and the log monitor (no worker runs on the join node)
_NOT_ON_THE_JOIN_NODE = ("gcs_server", "dashboard.py", "monitor.py", "log_monitor.py")


def _unshare_permitted() -> bool:
    try:
        r = subprocess.run(
            ["unshare", "-pf", "--mount-proc", "true"], capture_output=True, timeout=30
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return r.returncode == 0


def test_a_driver_on_a_machine_without_ray_joins_as_a_zero_cpu_node(tmp_path: Path) -> None:
    """The compose `sweep` container, or a laptop: comexp in a PID namespace that sees no
    Ray process (`unshare -pf --mount-proc`), head on 127.0.0.2. Ray 2.60 alone fails after
    ~60 s with "No node info found"; comexp joins as a zero-CPU node of its own (raylet and
    Ray's two agents; no log monitor, no head process), runs every episode on the head's
    CPU, stores them, and stops that node."""
    if not _unshare_permitted():
        pytest.skip("unshare -pf --mount-proc is not permitted here (needs CAP_SYS_ADMIN)")
    c = LoopbackCluster()
    seen: dict[int, str] = {}
    try:
        c.start(n_nodes=1)
        db = tmp_path / "j.db"
        d = c.comexp(
            tmp_path,
            "workers=1",
            f"db={db}",
            "grid.objects=[rect_8x5,l_shape,square_7]",
            *SWEEP,  # 6 episodes of 0.25 s on the head's one CPU
            prefix=("unshare", "-pf", "--mount-proc"),
        )
        deadline = time.monotonic() + 120
        while not (m := _JOINED.search(d.out)):
            assert d.proc.poll() is None, d.out
            assert time.monotonic() < deadline, d.out
            time.sleep(0.2)
        join_dir = m[1]
        sessions = {_session_of(p) for p in _pids_with(join_dir)} - {None}
        seen = {p: _cmdline(p) for p in _in_sessions(sessions) + list(sessions)}
        assert d.wait(timeout=180) == 0, d.out
    finally:
        c.stop()
    assert not c.leftovers()
    assert "Traceback" not in d.out, d.out
    assert not os.path.exists(join_dir)  # removed at exit
    assert len(sessions) == 1, seen  # `ray start --block` and what it started
    names = " ".join(seen.values())
    assert "/raylet " in names and "ray::DashboardAgent" in names, seen
    for name in _NOT_ON_THE_JOIN_NODE:
        assert f"/{name} " not in names, (name, seen)
    assert {node for _, node in d.workers()} == {HEAD_IP}, d.out
    _assert_complete(db, 6)
    assert _rows(db, "select count(*) from sweeps") == [(1,)]


# --- a sweep across two nodes --------------------------------------------------------------------


@pytest.mark.slow
def test_real_episodes_run_on_both_nodes(cluster: LoopbackCluster, tmp_path: Path) -> None:
    """pybullet episodes, the grid of the brief, one worker per node: both nodes run
    episodes (the pool's per-node count), every episode is stored once."""
    d = cluster.comexp(
        tmp_path,
        "workers=2",
        "grid.objects=[rect_8x5,l_shape]",
        "grid.coms_per_object=2",
        "grid.izz_scales=[1]",
        "floor.mu=[1.0]",
        "pusher.mu=[1.0]",
        "execution.batch_size=1",
        "db=c.db",
        fake=False,
    )
    assert d.wait(timeout=600) == 0, d.out
    assert sorted(node for _, node in d.workers()) == [HEAD_IP, NODE_IP], d.out
    per_node = _per_node(d.out)
    assert set(per_node) == {HEAD_IP, NODE_IP} and sum(per_node.values()) == 4, d.out
    db = tmp_path / "c.db"
    assert _rows(db, "select count(*), count(distinct episode_key) from episodes") == [(4, 4)]
    assert _rows(db, "select count(*) from episodes where status = 'ok'")[0][0] >= 3
    assert _rows(db, "pragma integrity_check") == [("ok",)]


# --- faults --------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("what", ["raylet", "node"])
def test_losing_the_second_node_costs_retries_not_episodes(
    cluster: LoopbackCluster, tmp_path: Path, what: str
) -> None:
    """(a) SIGKILL the second node's raylet (or its whole process group) once both nodes have
    stored episodes: the pool notices, retries the lost batches on the head, drops the
    replacement worker it cannot place, and finishes with all 40 episodes, each once."""
    db = tmp_path / "c.db"
    d = cluster.comexp(tmp_path, "workers=2", f"db={db}", *SWEEP)

    def strike() -> None:
        if what == "raylet":
            os.kill(cluster.raylet_pid(NODE_IP), signal.SIGKILL)
        else:
            os.killpg(cluster.nodes[NODE_IP].pid, signal.SIGKILL)

    _strike_when(d, lambda: _both_nodes_stored(db, 8), strike)
    stored_at_strike = len(_stored(db))
    assert d.wait() == 0, d.out
    assert stored_at_strike < N_SWEEP, "struck too late to matter"
    assert "a worker died" in d.out, d.out
    _report(f"(a) {what} of the second node killed", db, N_SWEEP, stored_at_strike, d.out)
    _assert_complete(db, N_SWEEP)
    nodes = {node for _, node in _stored(db)}
    assert len(nodes) == 2  # both nodes did work before the loss


@pytest.mark.slow
def test_a_killed_worker_process_costs_a_retry(cluster: LoopbackCluster, tmp_path: Path) -> None:
    """(b) SIGKILL one actor (its pid from the pool's log) mid-sweep: restarted, its batches
    retried, all 40 episodes stored once."""
    db = tmp_path / "c.db"
    d = cluster.comexp(tmp_path, "workers=2", f"db={db}", *SWEEP)
    victim: list[int] = []

    def strike() -> None:
        pid = next(p for p, node in d.workers() if node == NODE_IP)
        victim.append(pid)
        os.kill(pid, signal.SIGKILL)

    _strike_when(d, lambda: len(_stored(db)) >= 8 and d.workers(), strike)
    stored_at_strike = len(_stored(db))
    assert d.wait() == 0, d.out
    assert stored_at_strike < N_SWEEP, "struck too late to matter"
    assert "a worker died" in d.out, d.out
    assert len(d.workers()) == 3, d.out  # two at the start, one replacement
    _report("(b) worker process killed", db, N_SWEEP, stored_at_strike, d.out)
    assert (
        f"worker 1 ready: pid {victim[0]}" in d.out or f"worker 0 ready: pid {victim[0]}" in d.out
    )
    _assert_complete(db, N_SWEEP)


@pytest.mark.slow
def test_a_killed_driver_is_resumed_by_the_same_command(
    cluster: LoopbackCluster, tmp_path: Path
) -> None:
    """(c) SIGKILL the driver part-way (no chance to flush or clean up): rerunning the same
    command runs only what is missing, nothing is duplicated, the file is sound, and a third
    run stores nothing (no new sweep row either)."""
    db = tmp_path / "c.db"
    args = ["workers=2", f"db={db}", *SWEEP]
    d = cluster.comexp(tmp_path, *args)
    _strike_when(d, lambda: len(_stored(db)) >= 8, lambda: d.proc.send_signal(signal.SIGKILL))
    assert d.wait() == -signal.SIGKILL
    kept = _rows(db, "select count(*) from episodes")[0][0]
    assert 8 <= kept < N_SWEEP
    assert _rows(db, "pragma integrity_check") == [("ok",)]
    d2 = cluster.comexp(tmp_path, *args)
    assert d2.wait() == 0, d2.out
    assert f"{kept} already stored, {N_SWEEP - kept} to run" in d2.out, d2.out
    _report("(c) driver killed, same command rerun", db, N_SWEEP, kept, d.out, d2.out)
    _assert_complete(db, N_SWEEP)
    sweeps = _rows(db, "select count(*) from sweeps")
    d3 = cluster.comexp(tmp_path, *args)
    assert d3.wait() == 0, d3.out
    assert f"all {N_SWEEP} episodes already stored" in d3.out, d3.out
    assert _rows(db, "select count(*) from sweeps") == sweeps
    _assert_complete(db, N_SWEEP)


@pytest.mark.slow
def test_two_sweeps_on_one_sqlite_file_at_once(tmp_path: Path) -> None:
    """(d) Two drivers, overlapping grids (10 objects each, 5 shared), one SQLite file, at
    the same time on one cluster: both succeed, the shared episodes are stored once, nothing
    is lost, no "database is locked", and the file is sound."""
    objects = sorted(p.stem for p in (Path(TESTS_DIR).parent / "conf" / "object").glob("*.yaml"))
    a, b = objects[:10], objects[5:15]
    c = LoopbackCluster(cpus_per_node=2)  # room for both sweeps' two workers
    try:
        c.start()
        db = tmp_path / "shared.db"
        drivers = [
            c.comexp(tmp_path, "workers=2", f"db={db}", *SWEEP, f"grid.objects=[{','.join(g)}]")
            for g in (a, b)
        ]
        rcs = [d.wait() for d in drivers]
    finally:
        c.stop()
    assert not c.leftovers()
    for rc, d in zip(rcs, drivers, strict=True):
        assert rc == 0, d.out
        assert "locked" not in d.out.lower() and "Traceback" not in d.out, d.out
    union = len(set(a) | set(b)) * 2
    _report("(d) two sweeps on one file", db, union, 0, *(d.out for d in drivers))
    for d in drivers:
        print("  " + next(line for line in d.lines if " ran " in line).strip())
    _assert_complete(db, union)
    stored = [int(re.search(r"stored (\d+)", d.out)[1]) for d in drivers]
    assert sum(stored) == union  # the 10 shared episodes ran twice, were stored once
    assert _rows(db, "select count(*) from sweeps") == [(2,)]
