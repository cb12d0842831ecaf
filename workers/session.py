"""The Ray session of this process: start a quiet local Ray or join a cluster (as a zero-CPU node
of our own, `JoinNode`), once per process, with token auth that lives in memory only; the
environment worker processes get; how many workers a job asks for (`workers`, `RaySettings`);
and the check, before anything is written, that a cluster address answers.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import ray

from . import kept as kept_ray
from .settings import AUTO, DEFAULT_LOCAL_WORKERS, LOCAL, check_workers

log = logging.getLogger("comexp.pool")


class SessionError(RuntimeError):
    """Ray cannot be started here, or the cluster cannot be joined (one line)."""


def local_ray_cpus(workers: Any) -> int | None:
    """`num_cpus` for a local Ray started for `workers`: the count (2 by default), or None
    for `auto` (Ray then takes every CPU of this machine)."""
    w = check_workers(workers)
    if w is None:
        return DEFAULT_LOCAL_WORKERS
    return None if w == AUTO else int(w)


def one_line(e: BaseException) -> str:
    """A Ray error in one line: its type and the last non-empty line of its message (Ray's
    messages start with boilerplate; the last line names the cause)."""
    text = str(e).strip().splitlines()
    lines = [t.strip() for t in text if t.strip()]
    return f"{type(e).__name__}: {lines[-1] if lines else ''}"[:300]


RAY_CONNECT_TIMEOUT_S = 5.0


def parse_ray_address(address: str) -> tuple[str, int]:
    """HOST:PORT (a cluster's GCS address, `[v6addr]:PORT` too) as (host, port), or
    ValueError. Ray Client addresses (`ray://`) would need `ray[client]` (grpcio), which is
    not a dependency: comexp joins clusters as a node instead (`JoinNode` below)."""
    if "://" in address:
        raise ValueError(
            f"{address!r}: Ray Client (ray://) is not supported; "
            "give the cluster's HOST:PORT (the head's --port, 6379 by default)"
        )
    host, sep, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected null, auto or HOST:PORT, got {address!r}")
    return host, int(port)


def check_ray_address(address: str | None, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Fail within `timeout_s`, before anything is written, when no server listens at a
    HOST:PORT `ray.address`. Left to itself Ray retries an unreachable address for minutes,
    printing GCS warnings. (`auto` names the local node, which Ray finds or fails on at once.)
    """
    if address is None or address in ("auto", LOCAL):
        return
    host, port = parse_ray_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except socket.gaierror as e:
        raise ValueError(f"cannot resolve host {host!r} ({e.strerror})") from None
    except TimeoutError:
        raise ValueError(
            f"no answer from {address} within {timeout_s:g} s (is the Ray head up?)"
        ) from None
    except OSError as e:
        reason = e.strerror or type(e).__name__
        raise ValueError(f"cannot reach {address}: {reason} (is the Ray head up?)") from None


_ray_started_here = False
_kept: kept_ray.KeptRay | None = None  # the kept Ray this process is connected to
KEPT_NAMESPACE = "comexp"
_join_node: JoinNode | None = None
_joined_cluster = False  # ensure_ray was given an address: the job runs on a cluster
JOIN_TIMEOUT_S = 60.0  # `ray start` joins a reachable cluster in ~5 s on 2 busy cores
# `ray start` against a port that answers but is no Ray GCS: its first warning, after ~5 s
_JOIN_FAILED = re.compile(r"^.*(Failed to connect to|Timed out while waiting for GCS).*$", re.M)


def worker_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for worker processes: no usage stats, and the driver's rendering choice when
    it made one (MUJOCO_GL, PYOPENGL_PLATFORM); the default, headless EGL, is set in one place,
    where MuJoCo is imported (backends/mujoco_sim.py)."""
    env = {k: os.environ[k] for k in ("MUJOCO_GL", "PYOPENGL_PLATFORM") if k in os.environ}
    env["RAY_USAGE_STATS_ENABLED"] = "0"
    env.update(extra or {})
    return env


def ray_temp_dir() -> str:
    """Short path under the system temp dir: Ray's unix sockets live below it (~107 chars)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return os.path.join(tempfile.gettempdir(), f"comexp-ray-{uid}")


def joined_cluster() -> bool:
    """Whether this process's Ray session joined a cluster (`ray.address` set) rather than
    starting a local Ray of its own."""
    return _joined_cluster


def ensure_ray(
    address: str | None = None,
    num_cpus: int | str | None = 2,
    *,
    log_to_driver: bool = False,
    env: dict[str, str] | None = None,
) -> None:
    """Start (address None) or join (`auto`, host:port) Ray, once per process.

    A host:port address is joined through a zero-CPU node of this process's own (`JoinNode`):
    Ray 2.60 attaches a driver to a Ray node on the driver's machine, and a laptop or the
    compose `sweep` container runs none. `auto` means "this machine is a cluster node".
    Later calls reuse the session, so the jobs of a multirun share it; the session (and the
    join node) is shut down at exit when this process started it. Raises `SessionError` (one
    line naming the address) when the cluster cannot be joined.

    `num_cpus` is the job's `workers` for a local Ray: a count, `auto` (every CPU of this
    machine) or None (2); a cluster brings its own CPUs.
    """
    global _ray_started_here, _join_node, _joined_cluster, _kept
    if ray.is_initialized():
        return
    local_cpus = local_ray_cpus(num_cpus)
    if address is None:  # a local Ray: the kept one when there is one (`comexp-ray start`)
        kept, why = kept_ray.load()
        if why:
            log.warning("%s", why)
        if kept is not None:
            _connect_kept(kept, log_to_driver)
            return
    address = None if address == LOCAL else address
    _joined_cluster = address is not None
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    kwargs: dict[str, Any] = dict(logging_level=logging.WARNING, log_to_driver=log_to_driver)
    if address is None:
        # A local Ray's processes inherit this environment; a job-level runtime_env would
        # cost ~2 s per actor start (runtime-env agent, no prestarted workers).
        for k, v in worker_env(env).items():
            if k in (env or {}) or k not in os.environ:
                os.environ[k] = v
        _in_memory_auth_token()
        # "local" forces a new local instance even when RAY_ADDRESS is set.
        kwargs.update(
            address="local",
            num_cpus=local_cpus,
            include_dashboard=False,
            _temp_dir=ray_temp_dir(),
        )
    else:
        # Other nodes have their own environment: ship ours with the job.
        kwargs.update(address=address, runtime_env={"env_vars": worker_env(env)})
        if address != "auto":
            _join_node = JoinNode.start(address)
            kwargs["_temp_dir"] = _join_node.temp_dir  # attach to that node, no other
    if not _ray_started_here:
        atexit.register(shutdown_ray)
    _ray_started_here = True
    try:
        # A local head also starts Ray's autoscaler monitor and log monitor, which a one-machine
        # job never uses (~85 MB); `ray.init` has no public switch for either (Ray issue
        # ray-project/ray#46732, "Ray cluster with necessary process only").
        ray.init(**kwargs)
    except (ConnectionError, RuntimeError) as e:
        shutdown_ray()
        where = {None: "a new local Ray", "auto": "a local Ray node (ray.address=auto)"}.get(
            address, address
        )
        raise SessionError(f"cannot connect to {where}: {one_line(e)}") from None
    if _join_node is not None:
        log.info(
            "joined the Ray cluster at %s as a zero-CPU node (temp dir %s)",
            address,
            _join_node.temp_dir,
        )


def _connect_kept(kept: kept_ray.KeptRay, log_to_driver: bool) -> None:
    """Connect to the kept Ray (its token is in the environment: `kept_ray.export_auth`, when
    the package was imported); SessionError when it does not answer."""
    global _kept, _ray_started_here
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    if not _ray_started_here:
        atexit.register(shutdown_ray)  # disconnects; the kept Ray runs on
    _ray_started_here = True
    try:
        ray.init(
            address=kept.address,
            namespace=KEPT_NAMESPACE,  # where the warm workers of earlier jobs are named
            logging_level=logging.WARNING,
            log_to_driver=log_to_driver,
        )
    except (ConnectionError, RuntimeError) as e:
        shutdown_ray()
        raise SessionError(
            f"cannot connect to the kept Ray at {kept.address} ({one_line(e)}); "
            "comexp-ray stop ends it"
        ) from None
    _kept = kept
    log.info("using the kept Ray at %s (comexp-ray stop stops it)", kept.address)


def kept_session() -> kept_ray.KeptRay | None:
    """The kept Ray this process's session is connected to (None: a Ray of its own, or a
    cluster): its workers may outlive the job (`comexp.workers.pool`)."""
    return _kept


def _in_memory_auth_token() -> None:
    """Token auth for a local Ray with a token that lives only in the environment (inherited
    by Ray's processes): Ray turns token auth on for a new local Ray by itself and, without a
    token in `RAY_AUTH_TOKEN` (its documented first source), writes one to ~/.ray/auth_token.
    A user's own RAY_AUTH_* settings win. Ray's warning that it turned token auth on is
    dropped (`_TokenAuthNotice`): this is the auth comexp asked for."""
    if any(os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")):
        return
    os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    notice = logging.getLogger(_TOKEN_AUTH_LOGGER)
    if not any(isinstance(f, _TokenAuthNotice) for f in notice.filters):
        notice.addFilter(_TokenAuthNotice())


# the logger of Ray's "Token authentication is enabled for this Ray cluster" warning
_TOKEN_AUTH_LOGGER = "ray._private.authentication.authentication_token_setup"


class _TokenAuthNotice(logging.Filter):
    """Drops Ray's warning that it enabled token auth (comexp enabled it on purpose)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Token authentication is enabled for this Ray cluster" not in record.getMessage()


def shutdown_ray() -> None:
    global _join_node, _kept
    _kept = None
    if ray.is_initialized():
        ray.shutdown()
    if _join_node is not None:
        _join_node.stop()
        _join_node = None


@dataclass
class JoinNode:
    """A zero-CPU Ray node on the driver's machine, so that `ray.init(address=HOST:PORT)`
    finds a local node there (what Ray 2.60 requires of a driver; the workaround the Ray
    maintainers give in ray-project/ray#4090 and #32933). It schedules nothing: episodes run
    on the cluster's CPUs.

    `ray start --block` in a session of its own and a temp dir of its own: `stop` ends
    exactly its processes (never `ray stop`, which ends every Ray on the machine). If the
    driver dies without `stop` (SIGKILL), the kernel sends `ray start` SIGTERM
    (PR_SET_PDEATHSIG) and it shuts its node down. No log monitor: no worker runs here.
    """

    proc: subprocess.Popen
    temp_dir: str

    @property
    def log_path(self) -> str:
        return os.path.join(self.temp_dir, "ray-start.log")

    @classmethod
    def start(cls, address: str, timeout_s: float = JOIN_TIMEOUT_S) -> JoinNode:
        temp_dir = tempfile.mkdtemp(prefix="comexp-join-", dir=tempfile.gettempdir())
        cmd = [
            sys.executable,
            "-m",
            "ray.scripts.scripts",
            "start",
            f"--address={address}",
            "--num-cpus=0",
            "--num-gpus=0",
            # The driver's own objects only (results come back inlined or fetched one batch
            # at a time): 200 MB, not 30% of RAM, fits a container's /dev/shm.
            "--object-store-memory=200000000",
            f"--temp-dir={temp_dir}",
            "--include-log-monitor=false",
            "--disable-usage-stats",
            "--block",
        ]
        with open(os.path.join(temp_dir, "ray-start.log"), "wb") as out:
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # no Ctrl-C from the terminal: the driver stops it
                # unbuffered: Ray's GCS warnings reach the log as they happen, not at exit
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
                preexec_fn=_die_with_parent(),
            )
        node = cls(proc, temp_dir)
        try:
            node._wait_started(address, timeout_s)
        except BaseException:
            node.stop(grace_s=0)  # not joined: nothing to drain (it may sit in a GCS call)
            raise
        return node

    def _wait_started(self, address: str, timeout_s: float) -> None:
        """Until `ray start` says the node runs; fail fast when it cannot reach a GCS there
        (an open port that is not a Ray head: `ray start` would retry forever)."""
        deadline = time.monotonic() + timeout_s
        while True:
            text = _read_text(self.log_path)
            if "Ray runtime started" in text:
                return
            failed = _JOIN_FAILED.search(text)
            rc = self.proc.poll()
            if rc is not None or failed or time.monotonic() > deadline:
                lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
                why = (
                    failed.group(0).strip()
                    if failed
                    else f"`ray start` exited with {rc}"
                    if rc is not None
                    else f"`ray start` did not join within {timeout_s:g} s"
                )
                if not failed and lines:
                    why += f": {lines[-1]}"
                why = re.sub(r"^\[[^]]*\]\s*(\S+:\d+:\s*)?", "", why)  # Ray's log prefix
                raise SessionError(f"cannot join the Ray cluster at {address}: {why[:300]}")
            time.sleep(0.2)

    def stop(self, grace_s: float = 20.0) -> None:
        """SIGTERM to `ray start` (it stops its node's processes), then SIGKILL to whatever is
        left in its process group, looked up before the leader is reaped (no pid reuse)."""
        pid = self.proc.pid
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline:
            if os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None:
                break
            time.sleep(0.1)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)
        self.proc.wait()
        shutil.rmtree(self.temp_dir, ignore_errors=True)


def _die_with_parent() -> Callable[[], None] | None:
    """A preexec_fn: SIGTERM to the child when the thread that started it ends (Linux
    prctl PR_SET_PDEATHSIG; Hydra runs jobs in the main thread, so: when the driver ends)."""
    if sys.platform != "linux" or threading.current_thread() is not threading.main_thread():
        return None
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)

    def preexec() -> None:
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG

    return preexec


def _read_text(path: str) -> str:
    try:
        with open(path, errors="replace") as f:
            return f.read()
    except OSError:
        return ""
