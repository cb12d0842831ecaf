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
import hashlib
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import ray
import ray.exceptions as rex

from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.sim.simulator import SimulatorSpec

from .actor import RemoteEpisodeWorker, Runner, failed_result
from .kept import code_stamp
from .session import joined_cluster, kept_session, one_line
from .settings import AUTO, DEFAULT_LOCAL_WORKERS, PoolSettings, check_workers

log = logging.getLogger("comexp.pool")

# how long `EpisodePool.close` waits for its workers to close their simulators (s)
CLOSE_WAIT_S = 5.0


KEPT_PREFIX = "comexp-worker-"  # the named workers left warm on a kept Ray


def warm_key(actor_args: tuple) -> str:
    """What a warm worker was made of: the simulator, the runner, the time limits and the code
    (comexp's and a plug-in backend's modules), as a short digest."""
    simulator, runner, *limits = actor_args
    runner_name = f"{getattr(runner, '__module__', '')}.{getattr(runner, '__qualname__', runner)}"
    text = repr((simulator.name, simulator.target, sorted(simulator.options.items())))
    text += repr((runner_name, limits, code_stamp(simulator.target)))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _named_actors() -> list[str]:
    return list(ray.util.list_named_actors())


def resolve_workers(workers: Any, cluster_cpus: int, *, on_cluster: bool) -> int:
    """How many workers (one CPU each) a pool starts: `auto` (and the default on a cluster)
    is every CPU the Ray cluster has; a count is kept (`EpisodePool.start` caps it at the
    cluster's CPUs)."""
    w = check_workers(workers)
    if w is None:
        w = AUTO if on_cluster else DEFAULT_LOCAL_WORKERS
    if w == AUTO:
        return max(1, int(cluster_cpus))
    return int(w)


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
    index: int = 0  # the worker's place in the pool (its name on a kept Ray)
    warm: bool = False  # a named worker of a kept Ray: it outlives the job
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
        simulator: SimulatorSpec,
        workers: int | str | None = None,
        settings: PoolSettings | None = None,
        *,
        runner: Runner = run_episode,
        inflight_per_worker: int = 2,
        start_timeout_s: float = 600.0,
        kill_grace_s: float | None = None,
    ) -> None:
        settings = settings or PoolSettings()
        if settings.batch_size < 1 or settings.max_retries < 0 or inflight_per_worker < 1:
            raise ValueError("batch_size, inflight_per_worker >= 1; max_retries >= 0")
        self.simulator = simulator
        self.backend = simulator.name
        # as asked (a count, `auto` or None: see `resolve_workers`); `workers` is the count,
        # known once Ray is up (`start`)
        self.requested_workers = check_workers(workers)
        self.workers = self.requested_workers if isinstance(self.requested_workers, int) else 0
        self.settings = settings
        self.batch_size = settings.batch_size
        self.max_retries = settings.max_retries
        self.inflight_per_worker = inflight_per_worker
        self.start_timeout_s = start_timeout_s
        self.replace_timeout_s = settings.restart_timeout_s
        # the per-episode limit is enforced in the worker (workers/actor.py)
        self._actor_args = (simulator, runner, settings.episode_timeout_s, kill_grace_s)
        # on a kept Ray the workers are named by everything they were made of, code included,
        # so that a later job finds them warm only when they are the ones it would start
        kept = kept_session()
        self._warm_key = None if kept is None else warm_key(self._actor_args)
        self._slots: list[_Slot] = []
        self.stats = PoolStats()

    # lifecycle ----------------------------------------------------------------------------
    def _new_slot(self, index: int) -> _Slot:
        """Worker `index`: a new actor, or, on a kept Ray, the named one a former job of the
        same backend, physics and code left running there (`get_if_exists`), warm."""
        options: dict[str, Any] = {"num_cpus": 1, "max_restarts": 0}
        if self._warm_key is not None:
            name = f"{KEPT_PREFIX}{self._warm_key}-{index}"
            options.update(name=name, lifetime="detached", get_if_exists=True)
        actor = RemoteEpisodeWorker.options(**options).remote(*self._actor_args)
        return _Slot(actor, index, warm=self._warm_key is not None)

    def _new_actor(self) -> Any:
        """A replacement worker: never named (the name of the one it replaces is released only
        once Ray has ended it), so it ends with the job; the next job starts a named one."""
        return RemoteEpisodeWorker.options(num_cpus=1, max_restarts=0).remote(*self._actor_args)

    def warm_workers(self) -> int:
        """How many of this pool's workers already run, warm, on the kept Ray (0 elsewhere)."""
        if self._warm_key is None:
            return 0
        prefix = f"{KEPT_PREFIX}{self._warm_key}-"
        return sum(n.startswith(prefix) for n in _named_actors())

    def _make_room(self) -> None:
        """On a kept Ray, end the warm workers other jobs left when this pool's would not fit
        beside them (each holds a CPU)."""
        mine = f"{KEPT_PREFIX}{self._warm_key}-"
        others = [
            n for n in _named_actors() if n.startswith(KEPT_PREFIX) and not n.startswith(mine)
        ]
        needed = self.workers - self.warm_workers()
        if others and ray.available_resources().get("CPU", 0) < needed:
            for name in others:
                with contextlib.suppress(Exception):
                    _kill(ray.get_actor(name))
            log.info("ended %d warm workers of another job to make room", len(others))

    def start(self) -> None:
        """Create the actors and wait until each owns its simulator (init errors surface here,
        before any episode runs)."""
        if self._slots:
            return
        cpus = int(ray.cluster_resources().get("CPU", 0))
        self.workers = resolve_workers(self.requested_workers, cpus, on_cluster=joined_cluster())
        if self.requested_workers == AUTO:
            log.info("workers=%s: %d workers (the Ray cluster's CPUs)", self.requested_workers,
                     self.workers)  # fmt: skip
        if 0 < cpus < self.workers:  # each actor holds one CPU: more would wait forever
            log.warning("the Ray cluster has %d CPUs: using %d workers", cpus, cpus)
            self.workers = cpus
        if self._warm_key is not None:
            self._make_room()
        self._slots = [self._new_slot(i) for i in range(self.workers)]
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
            raise PoolError(f"workers failed to start: {one_line(e)}") from None
        for i, (slot, info) in enumerate(zip(self._slots, infos, strict=True)):
            self._note_ready(i, slot, info)

    def _note_ready(self, index: int, slot: _Slot, info: dict[str, Any]) -> None:
        """Log where a worker runs: the pid and node are what an operator needs to find (or,
        in a fault drill, kill) it."""
        slot.where = str(info.get("node_ip", "?"))
        log.info("worker %d ready: pid %s on node %s", index, info.get("pid"), slot.where)

    def close(self, keep_warm: bool = False) -> None:
        """Let every worker close its simulator, then end it: a killed process runs no
        cleanup, and an engine leaves what it holds behind (pybullet's scene files in the
        temp dir). A worker still busy after `CLOSE_WAIT_S` (an interrupted run) is ended
        all the same. `keep_warm` on a kept Ray: the workers stay up, warm, for the next job
        of the same backend and physics."""
        if not ray.is_initialized():  # its workers ended with their Ray session (and a remote
            self._slots = []  # call now would start a new Ray: Ray's auto-init)
            return
        ending = [s for s in self._slots if not (keep_warm and s.warm)]
        actors = [s.actor for s in ending if s.actor is not None]
        closing = []
        for a in actors:
            with contextlib.suppress(Exception):
                closing.append(a.close.remote())
        if closing:
            with contextlib.suppress(Exception):
                ray.wait(closing, num_returns=len(closing), timeout=CLOSE_WAIT_S)
        for a in actors:
            _kill(a)
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
        # a worker a former run was replacing when it ended (a kept pool: `job_pool`)
        starting: dict[Any, _Slot] = {
            s.ready_ref: s for s in self._slots if s.ready_ref is not None
        }
        before = collections.Counter(self.stats.episodes_by_node)
        consecutive_deaths = 0

        def death(e: BaseException, doing: str) -> None:
            """A worker died (starting, or running batches): fail the pool when it cannot
            start at all, or when deaths keep coming with no batch completing in between
            (systemic); otherwise the caller replaces the worker and carries on."""
            nonlocal consecutive_deaths
            if isinstance(e, rex.RayActorError) and e.actor_init_failed:
                raise PoolError(f"a worker failed to {doing}: {one_line(e)}") from None
            consecutive_deaths += 1
            if consecutive_deaths > 2 * len(self._slots) * (self.max_retries + 1) + 4:
                raise PoolError(f"workers keep dying: {one_line(e)}") from None

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
                    death(e, "restart")
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
                death(e, "start")
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
                log.warning("a batch failed: %s", one_line(e))
                yield from self._requeue(queue, [batch], charged=0)
                continue
            inflight.pop(ref)
            slot.pending.remove(ref)
            consecutive_deaths = 0
            self.stats.episodes_by_node[slot.where] += len(results)
            yield results
        ran = self.stats.episodes_by_node - before
        by_node = ", ".join(f"{n} {c}" for n, c in sorted(ran.items()))
        log.info("episodes per node: %s", by_node or "none")

    def _replace(self, slot: _Slot, starting: dict[Any, _Slot]) -> None:
        _kill(slot.actor)
        slot.where = "?"
        slot.actor = self._new_actor()
        slot.warm = False
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


# the pool `job_pool` keeps for the next job of this process: (its arguments, the pool)
_kept: tuple[str, EpisodePool] | None = None


def job_pool(
    simulator: SimulatorSpec,
    workers: int | str | None,
    settings: PoolSettings,
    *,
    runner: Runner = run_episode,
) -> EpisodePool:
    """The pool of a `comexp` job: the last job's, its workers still running, when it was
    made with the same arguments (the jobs of a multirun on one backend and physics: starting
    two workers costs each job ~0.8 s), else a new one (the last one closed). The caller
    closes it (`close_job_pool`) when a job fails or the process is done; at exit at the
    latest (before Ray's own shutdown, which was registered first)."""
    global _kept
    options = sorted(simulator.options.items())
    key = repr((simulator.name, simulator.target, options, workers, settings, runner))
    if _kept is not None and _kept[0] == key:
        return _kept[1]
    close_job_pool()
    if not _exit_hook:
        atexit.register(close_job_pool, keep_warm=True)
        _exit_hook.append(True)
    pool = EpisodePool(simulator, workers, settings, runner=runner)
    _kept = (key, pool)
    return pool


_exit_hook: list[bool] = []


def close_job_pool(keep_warm: bool = False) -> None:
    """Close the pool `job_pool` keeps, if any; `keep_warm`: on a kept Ray its workers stay
    up for the next command's job (a run cut short ends them: not a pool to reuse)."""
    global _kept
    kept, _kept = _kept, None
    if kept is not None:
        kept[1].close(keep_warm=keep_warm)


def _kill(actor: Any) -> None:
    with contextlib.suppress(Exception):  # already gone
        ray.kill(actor, no_restart=True)
