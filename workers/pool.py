"""The pool: a few long-lived actors, batches of episodes, results streamed back as they finish.

Design choices (see docs): a batch (default 8 episodes, ~1 s of work) makes Ray's per-task
overhead (~0.5 ms) negligible while a worker that dies costs at most the retry of its batch.
Each actor holds two batches in flight so it never idles waiting for the driver. The driver
alone writes the database, in chunks, as results arrive (`run_and_store`), so an interrupted
job keeps what it finished.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import logging
import math
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import ray
import ray.exceptions as rex

from comexp.experiment.episode import EpisodeResult, EpisodeSpec

from .actor import DEFAULT_RUNNER, DEFAULT_SIMULATOR_FACTORY, RemoteEpisodeWorker, failed_result

log = logging.getLogger("comexp.pool")

# Errors that mean "the process running this batch is gone", not "the batch raised".
_DEATH_ERRORS: tuple[type[BaseException], ...] = (
    rex.RayActorError,
    rex.WorkerCrashedError,
    rex.NodeDiedError,
    rex.ObjectLostError,
    rex.LocalRayletDiedError,
)


class PoolError(RuntimeError):
    """The pool cannot make progress (workers fail to start, or keep dying)."""


# --- the Ray session: once per process ----------------------------------------------------

_ray_started_here = False
_join_node: JoinNode | None = None
JOIN_TIMEOUT_S = 60.0  # `ray start` joins a reachable cluster in ~5 s on 2 busy cores
# `ray start` against a port that answers but is no Ray GCS: its first warning, after ~5 s
_JOIN_FAILED = re.compile(r"^.*(Failed to connect to|Timed out while waiting for GCS).*$", re.M)


def worker_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for worker processes: headless MuJoCo rendering, no usage stats."""
    env = {
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
        "RAY_USAGE_STATS_ENABLED": "0",
    }
    env.update(extra or {})
    return env


def ray_temp_dir() -> str:
    """Short path under the system temp dir: Ray's unix sockets live below it (~107 chars)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return os.path.join(tempfile.gettempdir(), f"comexp-ray-{uid}")


def ensure_ray(
    address: str | None = None,
    num_cpus: int = 2,
    *,
    log_to_driver: bool = False,
    env: dict[str, str] | None = None,
) -> None:
    """Start (address None) or join (`auto`, host:port) Ray, once per process.

    A host:port address is joined through a zero-CPU node of this process's own (`JoinNode`):
    Ray 2.60 attaches a driver to a Ray node on the driver's machine, and a laptop or the
    compose `sweep` container runs none. `auto` means "this machine is a cluster node".
    Later calls reuse the session, so the jobs of a multirun share it; the session (and the
    join node) is shut down at exit when this process started it. Raises `PoolError` (one
    line naming the address) when the cluster cannot be joined.
    """
    global _ray_started_here, _join_node
    if ray.is_initialized():
        return
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
            num_cpus=num_cpus,
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
        ray.init(**kwargs)
    except (ConnectionError, RuntimeError) as e:
        shutdown_ray()
        where = {None: "a new local Ray", "auto": "a local Ray node (ray.address=auto)"}.get(
            address, address
        )
        raise PoolError(f"cannot connect to {where}: {_one_line(e)}") from None
    if _join_node is not None:
        log.info(
            "joined the Ray cluster at %s as a zero-CPU node (temp dir %s)",
            address,
            _join_node.temp_dir,
        )


def _in_memory_auth_token() -> None:
    """Token auth for a local Ray with a token that lives only in the environment (inherited
    by Ray's processes). Left to itself, Ray 2.5x writes one to ~/.ray/auth_token and warns.
    A user's own RAY_AUTH_* settings win."""
    if any(os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")):
        return
    try:
        from ray._raylet import Config
    except ImportError:  # another Ray version: keep its default behaviour
        return
    os.environ["RAY_AUTH_MODE"] = "token"
    os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    Config.initialize("")  # Ray caches its config at import; re-read the environment


def shutdown_ray() -> None:
    global _join_node
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
                raise PoolError(f"cannot join the Ray cluster at {address}: {why[:300]}")
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


# --- the pool --------------------------------------------------------------------------------


@dataclass
class _Batch:
    specs: list[EpisodeSpec]
    attempts: int = 0  # deaths charged to this batch
    # Run alone on its actor: a death is then surely this batch's doing. (With two batches
    # queued, a death right after the first one finished can lose its reply too.)
    isolated: bool = False


@dataclass
class _Slot:
    """One worker position. A replacement actor is `starting` until its simulator exists;
    batches go to active slots only, so a replacement that cannot be placed (its node is
    gone, no free CPU) holds no work hostage."""

    actor: Any
    ready_ref: Any = None  # pending `ready()` call while starting
    since: float = 0.0
    pending: list[Any] = field(default_factory=list)  # run_batch refs, submission order
    where: str = "?"  # node address of the current actor, once it is ready (provenance)

    @property
    def active(self) -> bool:
        return self.actor is not None and self.ready_ref is None


@dataclass
class PoolStats:
    actor_restarts: int = 0
    batch_retries: int = 0
    worker_died_episodes: int = 0
    workers_dropped: int = 0
    # Episodes whose results came back from each node (by node address), for the end-of-run
    # log line; each stored episode also records its worker (`episodes.worker`).
    episodes_by_node: collections.Counter[str] = field(default_factory=collections.Counter)


class EpisodePool:
    """`workers` actors, each owning one simulator of `backend`."""

    def __init__(
        self,
        backend: str,
        workers: int = 2,
        *,
        runner: str = DEFAULT_RUNNER,
        simulator_factory: str = DEFAULT_SIMULATOR_FACTORY,
        runner_kwargs: dict[str, Any] | None = None,
        batch_size: int = 8,
        max_retries: int = 2,
        inflight_per_worker: int = 2,
        start_timeout_s: float = 600.0,
        replace_timeout_s: float = 60.0,
        episode_timeout_s: float | None = None,
        kill_grace_s: float | None = None,
        backend_options: dict[str, Any] | None = None,
    ) -> None:
        if workers < 1 or batch_size < 1 or max_retries < 0 or inflight_per_worker < 1:
            raise ValueError("workers, batch_size, inflight_per_worker >= 1; max_retries >= 0")
        self.backend = backend
        self.workers = workers
        self.batch_size = batch_size
        self.max_retries = max_retries
        self.inflight_per_worker = inflight_per_worker
        self.start_timeout_s = start_timeout_s
        self.replace_timeout_s = replace_timeout_s
        # episode_timeout_s: per-episode limit enforced in the worker (see workers.actor)
        self._actor_args = (
            backend,
            runner,
            simulator_factory,
            runner_kwargs,
            episode_timeout_s,
            kill_grace_s,
            backend_options,
        )
        self._slots: list[_Slot] = []
        self.stats = PoolStats()

    # lifecycle ----------------------------------------------------------------------------
    def _new_actor(self) -> Any:
        return RemoteEpisodeWorker.options(num_cpus=1, max_restarts=0).remote(*self._actor_args)

    def start(self) -> None:
        """Create the actors and wait until each owns its simulator (init errors surface here,
        before any episode runs)."""
        if self._slots:
            return
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if 0 < cpus < self.workers:  # each actor holds one CPU: more would wait forever
            log.warning("the Ray cluster has %d CPUs: using %d workers", cpus, cpus)
            self.workers = cpus
        self._slots = [_Slot(self._new_actor()) for _ in range(self.workers)]
        try:
            infos = ray.get(
                [s.actor.ready.remote() for s in self._slots], timeout=self.start_timeout_s
            )
        except rex.GetTimeoutError:
            self.close()
            raise PoolError(
                f"workers did not start within {self.start_timeout_s:g} s "
                "(too few free CPUs in the Ray cluster?)"
            ) from None
        except rex.RayError as e:
            self.close()
            raise PoolError(f"workers failed to start: {_one_line(e)}") from None
        for i, (slot, info) in enumerate(zip(self._slots, infos, strict=True)):
            self._note_ready(i, slot, info)

    def _note_ready(self, index: int, slot: _Slot, info: dict[str, Any]) -> None:
        """Log where a worker runs: the pid and node are what an operator needs to find (or,
        in a fault drill, kill) it."""
        slot.where = str(info.get("node_ip", "?"))
        log.info("worker %d ready: pid %s on node %s", index, info.get("pid"), slot.where)

    def close(self) -> None:
        for s in self._slots:
            _kill(s.actor)
        self._slots = []

    def __enter__(self) -> EpisodePool:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # running ------------------------------------------------------------------------------
    def run(self, specs: Sequence[EpisodeSpec]) -> Iterator[list[EpisodeResult]]:
        """Yield results batch by batch, in completion order; every spec exactly once."""
        self.start()
        bs = self.batch_size
        queue = collections.deque(_Batch(list(specs[i : i + bs])) for i in range(0, len(specs), bs))
        inflight: dict[Any, tuple[_Slot, _Batch]] = {}
        starting: dict[Any, _Slot] = {}
        consecutive_deaths = 0

        def fill() -> None:
            for _ in range(self.inflight_per_worker):  # round robin: spread work evenly
                for slot in self._slots:
                    if (
                        not queue
                        or not slot.active
                        or len(slot.pending) >= self.inflight_per_worker
                    ):
                        continue
                    if slot.pending and (
                        queue[0].isolated or inflight[slot.pending[0]][1].isolated
                    ):
                        continue
                    b = queue.popleft()
                    ref = slot.actor.run_batch.remote(b.specs)
                    inflight[ref] = (slot, b)
                    slot.pending.append(ref)

        while queue or inflight:
            fill()
            self._check_starting(starting)
            ready, _ = ray.wait([*inflight, *starting], num_returns=1, timeout=2.0)
            if not ready:
                continue
            ref = ready[0]
            if ref in starting:
                slot = starting.pop(ref)
                try:
                    info = ray.get(ref)
                except _DEATH_ERRORS as e:
                    if isinstance(e, rex.RayActorError) and e.actor_init_failed:
                        raise PoolError(f"a worker failed to restart: {_one_line(e)}") from None
                    consecutive_deaths += 1
                    if consecutive_deaths > 2 * len(self._slots) * (self.max_retries + 1) + 4:
                        raise PoolError(f"workers keep dying: {_one_line(e)}") from None
                    self._replace(slot, starting)  # e.g. placed on a node that then died
                    continue
                slot.ready_ref = None
                if slot in self._slots:
                    self._note_ready(self._slots.index(slot), slot, info)
                continue
            slot, batch = inflight[ref]
            try:
                results = ray.get(ref)
            except _DEATH_ERRORS as e:
                if isinstance(e, rex.RayActorError) and e.actor_init_failed:
                    raise PoolError(f"a worker failed to start: {_one_line(e)}") from None
                consecutive_deaths += 1
                # a run of deaths with no batch completing in between is systemic
                if consecutive_deaths > 2 * len(self._slots) * (self.max_retries + 1) + 4:
                    raise PoolError(f"workers keep dying: {_one_line(e)}") from None
                # Batches that finished before the death still have their results; of the
                # rest, the oldest was running (actor tasks run in submission order).
                done, _ = ray.wait(slot.pending, num_returns=len(slot.pending), timeout=0)
                lost = []
                for r in slot.pending:
                    b = inflight.pop(r)[1]
                    try:
                        finished = ray.get(r) if r in done else None
                    except rex.RayError:
                        finished = None
                    if finished is None:
                        lost.append(b)
                    else:
                        self.stats.episodes_by_node[slot.where] += len(finished)
                        yield finished
                slot.pending = []
                log.warning(
                    "a worker died (%s); restarting it and retrying %d batch(es)",
                    type(e).__name__,
                    len(lost),
                )
                self._replace(slot, starting)
                yield from self._requeue(queue, lost, charged=0)
                continue
            except rex.RayError as e:  # run_batch itself raised: the actor is alive
                inflight.pop(ref)
                slot.pending.remove(ref)
                log.warning("a batch failed: %s", _one_line(e))
                yield from self._requeue(queue, [batch], charged=0)
                continue
            inflight.pop(ref)
            slot.pending.remove(ref)
            consecutive_deaths = 0
            self.stats.episodes_by_node[slot.where] += len(results)
            yield results
        by_node = ", ".join(f"{n} {c}" for n, c in sorted(self.stats.episodes_by_node.items()))
        log.info("episodes per node: %s", by_node or "none")

    def _replace(self, slot: _Slot, starting: dict[Any, _Slot]) -> None:
        _kill(slot.actor)
        slot.where = "?"
        slot.actor = self._new_actor()
        slot.ready_ref = slot.actor.ready.remote()
        slot.since = time.monotonic()
        starting[slot.ready_ref] = slot
        self.stats.actor_restarts += 1

    def _check_starting(self, starting: dict[Any, _Slot]) -> None:
        """Give up on replacements that cannot be placed: carry on with the other workers,
        or fail when there are none left."""
        now = time.monotonic()
        n_active = sum(s.active for s in self._slots)
        for ref, slot in list(starting.items()):
            waited = now - slot.since
            if (n_active and waited > self.replace_timeout_s) or waited > self.start_timeout_s:
                if not n_active:
                    raise PoolError(
                        f"no worker could be restarted within {self.start_timeout_s:g} s "
                        "(too few free CPUs in the Ray cluster?)"
                    )
                del starting[ref]
                _kill(slot.actor)
                self._slots.remove(slot)
                self.stats.workers_dropped += 1
                log.warning(
                    "a replacement worker did not start within %.0f s; continuing with %d",
                    waited,
                    len(self._slots),
                )

    def _requeue(
        self, queue: collections.deque[_Batch], lost: list[_Batch], charged: int
    ) -> Iterator[list[EpisodeResult]]:
        """Put lost batches back at the front; the charged one (the oldest: it was running)
        gets `max_retries` more attempts, then is split into single episodes that each run
        alone on a worker, and a single episode that keeps killing its worker becomes a failed
        result (`failure="worker_died"`)."""
        back: list[_Batch] = []
        for i, b in enumerate(lost):
            if i != charged:
                back.append(b)
                continue
            b.attempts += 1
            self.stats.batch_retries += 1
            if b.attempts <= self.max_retries:
                back.append(b)
            elif not b.isolated:
                back.extend(_Batch([s], isolated=True) for s in b.specs)
            else:
                self.stats.worker_died_episodes += 1
                yield [
                    failed_result(
                        b.specs[0],
                        "worker_died",
                        f"the worker process died {b.attempts} times running this episode",
                        0.0,
                    )
                ]
        queue.extendleft(reversed(back))


def _kill(actor: Any) -> None:
    with contextlib.suppress(Exception):  # already gone
        ray.kill(actor, no_restart=True)


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    # Ray's messages start with boilerplate; the last non-empty line names the cause.
    lines = [t.strip() for t in text if t.strip()]
    return f"{type(e).__name__}: {lines[-1] if lines else ''}"[:300]


# --- the driver: progress and the database ---------------------------------------------------


@dataclass
class RunStats:
    total: int
    done: int = 0
    failed: int = 0
    stored: int = 0
    wall_s: float = 0.0
    failures: collections.Counter[str] = field(default_factory=collections.Counter)


class Progress:
    """tqdm on a terminal; plain periodic log lines otherwise (log files, CI)."""

    def __init__(self, total: int, desc: str = "", *, tty: bool | None = None, every_s=10.0):
        self.total = total
        self.desc = desc
        self.every_s = every_s
        self.t0 = time.monotonic()
        self._last = self.t0
        self._bar = None
        if tty if tty is not None else sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit="ep", dynamic_ncols=True, smoothing=0.1)

    def update(self, n: int, stats: RunStats) -> None:
        if self._bar is not None:
            self._bar.update(n)
            self._bar.set_postfix(failed=stats.failed, refresh=False)
            return
        now = time.monotonic()
        if now - self._last >= self.every_s or stats.done == self.total:
            self._last = now
            log.info("%s", self.line(stats))

    def line(self, stats: RunStats) -> str:
        el = time.monotonic() - self.t0
        rate = stats.done / el if el > 0 else 0.0
        eta = (self.total - stats.done) / rate if rate > 0 else math.inf
        eta_s = "?" if math.isinf(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        return (
            f"{self.desc} {stats.done}/{self.total} done, {stats.failed} failed, "
            f"{rate:.1f} ep/s, ETA {eta_s}"
        ).strip()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def run_and_store(
    pool: EpisodePool,
    specs: Sequence[EpisodeSpec],
    store: Callable[[list[EpisodeResult]], int],
    *,
    flush_every: int = 32,
    flush_interval_s: float = 2.0,
    progress: Progress | None = None,
) -> RunStats:
    """Run `specs` on the pool and hand results to `store` in chunks as they arrive.

    Whatever arrived is stored even when the run is interrupted (Ctrl-C, a pool error), so
    rerunning the same command resumes where this one stopped.
    """
    stats = RunStats(total=len(specs))
    pending: list[EpisodeResult] = []
    t0 = time.monotonic()
    last_flush = t0

    def flush() -> None:
        nonlocal pending, last_flush
        if pending:
            stats.stored += store(pending)
        pending = []
        last_flush = time.monotonic()

    try:
        for results in pool.run(specs):
            pending.extend(results)
            stats.done += len(results)
            for r in results:
                if r.status != "ok":
                    stats.failed += 1
                    stats.failures[r.failure or "unknown"] += 1
            if progress is not None:
                progress.update(len(results), stats)
            if len(pending) >= flush_every or time.monotonic() - last_flush >= flush_interval_s:
                flush()
    finally:
        try:
            flush()
        finally:
            stats.wall_s = time.monotonic() - t0
            if progress is not None:
                progress.close()
    return stats
