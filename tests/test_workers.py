"""The Ray side with a cheap fake runner and simulator: every episode exactly once, dying
workers retried, results streamed to the store before the end, interrupted runs keep results.

The fakes live in this module, which the worker processes import (the tests directory is on
their PYTHONPATH): the simulator by its class path (`FAKE`, as a backend's `_target_`), the
runner as the function itself (Ray sends it by reference).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path

import pytest

from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.sim.simulator import SimulatorSpec
from comexp.workers.settings import PoolSettings

TESTS_DIR = str(Path(__file__).resolve().parent)
FAKE = SimulatorSpec("fake", "test_workers.FakeSimulator")
BROKEN = SimulatorSpec("broken", "test_workers.BrokenSimulator")
GATE_WAIT_S = 10.0  # only a broken run waits this long


# --- fakes (imported by the workers) --------------------------------------------------------


class FakeSimulator:
    builds = 0

    def __init__(self, settings=None, closed_marker_dir: str | None = None, **options) -> None:
        # options: the backend's own (a command-line job's, tests/test_cli.py)
        self.closed = False
        self.closed_marker_dir = closed_marker_dir  # close() leaves a file there
        FakeSimulator.builds += 1

    def close(self) -> None:
        self.closed = True
        if self.closed_marker_dir is not None:
            Path(self.closed_marker_dir, f"closed-{os.getpid()}").touch()


class BrokenSimulator(FakeSimulator):
    def __init__(self, settings=None, **options) -> None:
        raise RuntimeError("engine failed to start")


def fake_run(
    spec: EpisodeSpec,
    sim: FakeSimulator,
    *,
    sleep_s: float | None = None,
    marker_dir: str | None = None,
    gate_file: str | None = None,
    gated_from: int = 0,
) -> EpisodeResult:
    """`object` selects the behaviour: `raise` raises, `die_once` kills the worker process
    the first time (marker file), `die_always` every time; others succeed after `sleep_s`
    (default: $FAKE_RUN_SLEEP_S, so command-line tests can slow it down).

    With `gate_file`, episodes from `com_index` `gated_from` on wait for that file (the
    driver creates it) and fail if it does not appear within GATE_WAIT_S: an order of
    events to test, instead of wall-clock gaps that a loaded machine stretches."""
    assert not sim.closed
    if sleep_s is None:
        sleep_s = float(os.environ.get("FAKE_RUN_SLEEP_S", "0"))
    if spec.object == "raise":
        raise ValueError("boom")
    if spec.object.startswith("die"):
        marker = Path(marker_dir or "/nonexistent") / f"{spec.object}-{spec.com_index}"
        if spec.object == "die_always" or not marker.exists():
            marker.touch()
            os._exit(1)
    if sleep_s:
        time.sleep(sleep_s)
    if gate_file is not None and spec.com_index >= gated_from:
        deadline = time.monotonic() + GATE_WAIT_S
        while not os.path.exists(gate_file):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{gate_file} did not appear within {GATE_WAIT_S} s")
            time.sleep(0.005)
    import ray

    node = ray.get_runtime_context().get_node_id() if ray.is_initialized() else "-"
    return EpisodeResult(
        spec=spec,
        status="ok",
        failure=None,
        est_com_cm=spec.com_cm,
        error_cm=0.1 * spec.com_index,
        n_pushes=0,
        pushes=(),
        wall_s=sleep_s,
        detail=f"pid {os.getpid()} node {node}",
    )


def threads_run(spec: EpisodeSpec, sim: FakeSimulator) -> EpisodeResult:
    """An episode that reports the worker's native thread pools: OpenCV's threads and
    OMP_NUM_THREADS (which OpenBLAS follows)."""
    import cv2

    result = fake_run(spec, sim, sleep_s=0.0)
    omp = os.environ.get("OMP_NUM_THREADS")
    return dataclasses.replace(result, detail=f"opencv {cv2.getNumThreads()} omp {omp}")


def make_specs(n: int, obj: str = "box", start: int = 0) -> list[EpisodeSpec]:
    return [
        EpisodeSpec(
            backend="fake",
            floor="iso",
            mu_floor_x=1.0,
            mu_floor_y=1.0,
            mu_pusher=1.0,
            speed_cm_s=40.0,
            izz_scale=1.0,
            object=obj,
            outline_cm=((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)),
            height_cm=2.0,
            com_index=k,
            com_cm=(0.01 * k, 0.0),
        )
        for k in range(start, start + n)
    ]


def ids(results: list[EpisodeResult]) -> list[tuple[str, int]]:
    return sorted((r.spec.object, r.spec.com_index) for r in results)


def spec_ids(specs: list[EpisodeSpec]) -> list[tuple[str, int]]:
    return sorted((s.object, s.com_index) for s in specs)


# --- the worker without Ray -------------------------------------------------------------------


def test_worker_turns_exceptions_into_failed_results() -> None:
    from comexp.workers.actor import EpisodeWorker

    w = EpisodeWorker(FAKE, runner=fake_run)
    specs = make_specs(2) + make_specs(1, "raise") + make_specs(2, start=2)
    before = FakeSimulator.builds
    out = w.run_batch(specs)
    assert [r.status for r in out] == ["ok", "ok", "failed", "ok", "ok"]
    assert out[2].failure == "error" and "ValueError: boom" in out[2].detail
    assert FakeSimulator.builds == before + 1  # a fresh simulator after the exception
    w.close()


# --- the pool on a real (local) Ray -------------------------------------------------------


@pytest.fixture(scope="module")
def ray_session(local_ray):
    """The module's local Ray (conftest.py), started by `ensure_ray` as `comexp` starts it."""
    yield


def _pool(simulator=FAKE, runner=fake_run, **settings):
    """A pool of 2 fake workers; `settings`: `PoolSettings`' (no episode time limit)."""
    from comexp.workers.pool import EpisodePool

    settings.setdefault("episode_timeout_s", 0.0)
    return EpisodePool(simulator, 2, PoolSettings(**settings), runner=runner)


def test_pool_runs_every_episode_once_and_streams(ray_session) -> None:
    specs = make_specs(40)
    got: list[EpisodeResult] = []
    yields = 0
    with _pool(batch_size=4, runner=functools.partial(fake_run, sleep_s=0.005)) as pool:
        for chunk in pool.run(specs):
            yields += 1
            got.extend(chunk)
            assert len(chunk) <= 4
    assert ids(got) == spec_ids(specs)
    assert yields == 10  # one yield per batch: results stream back as batches finish
    assert len({r.detail for r in got}) == 2  # both workers took part
    assert len({r.worker for r in got}) == 2  # and each result says which one ran it
    assert all(r.worker.count(":") == 1 for r in got)


def test_pool_workers_use_one_cpu_each(ray_session) -> None:
    """A worker is one CPU: its libraries' thread pools run on one thread. OpenCV's pool
    ignores OMP_NUM_THREADS; with two threads its idle one spins on the other worker's CPU
    (`use_one_cpu`)."""
    with _pool(runner=threads_run, batch_size=2) as pool:
        got = [r for chunk in pool.run(make_specs(8)) for r in chunk]
    assert len({r.worker for r in got}) == 2
    assert {r.detail for r in got} == {"opencv 1 omp 1"}


def test_closing_the_pool_closes_every_worker_s_simulator(ray_session, tmp_path) -> None:
    """Workers are ended by a kill, which runs no cleanup: the pool has each close its
    simulator first (pybullet's scene files in the temp dir were left behind)."""
    marked = SimulatorSpec("fake", FAKE.target, {"closed_marker_dir": str(tmp_path)})
    pool = _pool(marked, batch_size=2)
    with pool:
        got = [r for chunk in pool.run(make_specs(8)) for r in chunk]
    pids = {r.detail.split()[1] for r in got}
    assert len(pids) == 2
    assert {p.name for p in tmp_path.iterdir()} == {f"closed-{pid}" for pid in pids}


def test_a_job_pool_carries_its_workers_to_the_next_job_with_the_same_arguments(
    ray_session,
) -> None:
    from comexp.workers.pool import close_job_pool, job_pool

    # the job's own runner is the episode loop: a fake simulator whose `build` answers as
    # `fake_run` does would be the job's path; here the pool's reuse is what is tested
    settings = PoolSettings(batch_size=2)
    first = job_pool(FAKE, 2, settings, runner=fake_run)
    pids = [{r.detail for c in first.run(make_specs(6)) for r in c} for _ in range(2)]
    assert job_pool(FAKE, 2, PoolSettings(batch_size=2), runner=fake_run) is first
    again = {r.detail for c in first.run(make_specs(6)) for r in c}
    assert pids[0] == pids[1] == again and len(again) == 2  # the same two processes
    other = job_pool(FAKE, 2, PoolSettings(batch_size=3), runner=fake_run)  # a new pool
    assert other is not first and first._slots == []  # the last one closed
    assert {r.detail for c in other.run(make_specs(6)) for r in c}.isdisjoint(again)
    close_job_pool()
    assert other._slots == [] and job_pool(FAKE, 2, settings, runner=fake_run) is not first
    close_job_pool()


def test_pool_retries_the_batch_of_a_dying_worker(ray_session, tmp_path) -> None:
    specs = make_specs(10) + make_specs(1, "die_once") + make_specs(10, start=10)
    got: list[EpisodeResult] = []
    runner = functools.partial(fake_run, marker_dir=str(tmp_path))
    with _pool(batch_size=4, runner=runner) as pool:
        for chunk in pool.run(specs):
            got.extend(chunk)
        assert pool.stats.actor_restarts == 1
        assert pool.stats.batch_retries == 1
    assert ids(got) == spec_ids(specs)
    assert all(r.status == "ok" for r in got)
    assert (tmp_path / "die_once-0").exists()


def test_pool_gives_up_on_an_episode_that_always_kills_its_worker(ray_session, tmp_path) -> None:
    specs = make_specs(3) + make_specs(1, "die_always") + make_specs(3, start=3)
    got: list[EpisodeResult] = []
    runner = functools.partial(fake_run, marker_dir=str(tmp_path))
    with _pool(batch_size=4, max_retries=0, runner=runner) as pool:
        for chunk in pool.run(specs):
            got.extend(chunk)
        # batch dies once (no retry) -> split into 4 singles -> the poison one dies once more
        assert pool.stats.actor_restarts == 2
    assert len(got) == 7 and len(set(ids(got))) == 7
    bad = [r for r in got if r.spec.object == "die_always"]
    assert len(bad) == 1 and bad[0].status == "failed" and bad[0].failure == "worker_died"
    assert sum(r.status == "ok" for r in got) == 6


def test_pool_reports_workers_that_cannot_start(ray_session) -> None:
    from comexp.workers.pool import EpisodePool, PoolError

    pool = EpisodePool(BROKEN, 1, runner=fake_run)
    with pytest.raises(PoolError, match="engine failed to start"):
        pool.start()


def test_run_and_store_writes_while_running(ray_session, tmp_path) -> None:
    """The last batch cannot finish before something was stored: it waits for a file the
    store creates. (This replaced `first write > 0.1 s before the end`, a wall-clock gap that
    measured 0.21-0.22 s in 3 runs here: a margin a stalled worker start-up eats.)"""
    from comexp.workers.driver import run_and_store

    specs = make_specs(24)
    gate = tmp_path / "stored"
    calls: list[int] = []

    def store(results: list[EpisodeResult]) -> int:
        calls.append(len(results))
        gate.touch()
        return len(results)

    kwargs = {"sleep_s": 0.01, "gate_file": str(gate), "gated_from": 22}
    with _pool(batch_size=2, runner=functools.partial(fake_run, **kwargs)) as pool:
        stats = run_and_store(pool, specs, store, flush_every=4, flush_interval_s=60)
    assert stats.failed == 0, stats.failures  # the gated batch did not time out
    assert stats.done == stats.stored == 24
    assert sum(calls) == 24
    assert len(calls) >= 5  # chunks of ~4, not one write at the end


# --- the driver loop without Ray --------------------------------------------------------------


class _FakePool:
    """Yields results of fake_run in batches; raises `exc` after `fail_after` batches."""

    def __init__(self, fail_after: int | None = None, exc: BaseException | None = None):
        self.fail_after = fail_after
        self.exc = exc

    def run(self, specs):
        sim = FakeSimulator()
        for i in range(0, len(specs), 3):
            if self.fail_after is not None and i // 3 == self.fail_after:
                raise self.exc
            yield [fake_run(s, sim) for s in specs[i : i + 3]]


def test_interrupted_run_keeps_what_finished() -> None:
    from comexp.workers.driver import run_and_store

    stored: list[EpisodeResult] = []

    def store(results):
        stored.extend(results)
        return len(results)

    specs = make_specs(30)
    pool = _FakePool(fail_after=4, exc=KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        run_and_store(pool, specs, store, flush_every=100, flush_interval_s=1e9)
    assert ids(stored) == spec_ids(specs[:12])  # four finished batches, flushed on the way out


def test_run_and_store_counts_failures() -> None:
    from comexp.workers.driver import Progress, run_and_store

    specs = make_specs(4) + make_specs(2, "raise")

    class Pool:
        def run(self, specs):
            from comexp.workers.actor import EpisodeWorker

            w = EpisodeWorker(FAKE, runner=fake_run)
            yield w.run_batch(specs)

    progress = Progress(len(specs), "t", tty=False, every_s=0)
    stats = run_and_store(Pool(), specs, lambda rs: len(rs), progress=progress)
    assert (stats.done, stats.failed, stats.failures["error"]) == (6, 2, 2)
    assert "6/6 done, 2 failed" in progress.line(stats)


@pytest.mark.parametrize(("env", "bar"), [("bar", True), ("log", False), ("", False)])
def test_comexp_progress_chooses_the_bar_off_a_terminal(monkeypatch, env: str, bar: bool) -> None:
    """`COMEXP_PROGRESS=bar` draws tqdm's bar where stderr is no terminal (a pipe, a log
    file); `log` or unset off a terminal: the periodic log lines."""
    import io

    from comexp.workers.driver import Progress

    monkeypatch.setenv("COMEXP_PROGRESS", env)
    err = io.StringIO()  # not a terminal
    monkeypatch.setattr("sys.stderr", err)
    progress = Progress(3, "t")
    try:
        assert (progress._bar is not None) is bar
    finally:
        progress.close()
    if bar:
        assert "\r" in err.getvalue() and "0/3" in err.getvalue()


# The real multi-node cluster and its faults: tests/test_cluster.py.
