"""`workers=auto`: every CPU of the Ray cluster (and the default once a job joins a cluster);
a local Ray keeps 2 unless asked. Tested without starting Ray: the session's `ray.init` and
the pool's view of the cluster are stand-ins."""

from __future__ import annotations

import pytest

from comexp.sim.simulator import SimulatorSpec
from comexp.workers import pool as pool_mod
from comexp.workers import session
from comexp.workers.pool import EpisodePool, resolve_workers
from comexp.workers.session import local_ray_cpus
from comexp.workers.settings import AUTO, check_workers

PLANAR = SimulatorSpec("planar", "comexp.backends.planar_sim.PlanarSimulator")


@pytest.mark.parametrize(
    ("given", "checked"),
    [(None, None), ("auto", AUTO), (" AUTO ", AUTO), (3, 3), ("4", 4), (1, 1)],
)
def test_check_workers_accepts_counts_and_auto(given, checked) -> None:
    assert check_workers(given) == checked


@pytest.mark.parametrize("bad", [0, -1, "0", "two", 1.5, True, "", [2]])
def test_check_workers_refuses_anything_else_in_one_line(bad) -> None:
    with pytest.raises(ValueError, match=r"^workers must be a count >= 1 or auto, got "):
        check_workers(bad)


def test_a_local_ray_gets_the_count_or_every_cpu() -> None:
    assert local_ray_cpus(None) == 2 and local_ray_cpus(3) == 3
    assert local_ray_cpus("auto") is None  # ray.init(num_cpus=None): every CPU here


@pytest.mark.parametrize(
    ("workers", "cpus", "on_cluster", "count"),
    [
        ("auto", 48, True, 48),  # every CPU of the cluster
        (None, 48, True, 48),  # the default when ray.address is set
        (None, 48, False, 2),  # the default on a local Ray
        ("auto", 8, False, 8),  # a local Ray started with every CPU
        (3, 48, True, 3),  # a count is a count
        ("auto", 0, True, 1),  # a cluster reporting no CPU yet: one worker, which waits
    ],
)
def test_resolve_workers(workers, cpus, on_cluster, count) -> None:
    assert resolve_workers(workers, cpus, on_cluster=on_cluster) == count


class _StartedError(Exception):
    pass


@pytest.mark.parametrize(
    ("workers", "joined", "count"), [("auto", False, 6), (None, True, 6), (None, False, 2),
                                     (2, True, 2), (10, True, 6)],
)  # fmt: skip
def test_the_pool_starts_one_worker_per_cluster_cpu(monkeypatch, workers, joined, count):
    monkeypatch.setattr(pool_mod.ray, "cluster_resources", lambda: {"CPU": 6.0})
    monkeypatch.setattr(session, "_joined_cluster", joined)
    p = EpisodePool(PLANAR, workers)
    assert p.requested_workers == check_workers(workers)

    def new_slot(index):
        raise _StartedError

    monkeypatch.setattr(p, "_new_slot", new_slot)
    with pytest.raises(_StartedError):
        p.start()
    assert p.workers == count


def test_a_bad_count_fails_before_ray(monkeypatch) -> None:
    with pytest.raises(ValueError, match="workers must be a count >= 1 or auto, got 0"):
        EpisodePool(PLANAR, 0)


@pytest.mark.parametrize(
    ("address", "workers", "num_cpus", "joined"),
    [(None, 2, 2, False), (None, "auto", None, False), (None, None, 2, False),
     ("auto", "auto", None, True), ("auto", None, None, True)],
)  # fmt: skip
def test_ensure_ray_starts_a_local_ray_with_the_workers_cpus(
    monkeypatch, address, workers, num_cpus, joined
) -> None:
    calls = []
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    monkeypatch.setattr(session.ray, "is_initialized", lambda: False)
    monkeypatch.setattr(session.ray, "init", lambda **kw: calls.append(kw))
    monkeypatch.setattr(session, "worker_env", lambda env=None: {})
    monkeypatch.setattr(session, "_in_memory_auth_token", lambda: None)
    monkeypatch.setattr(session, "_ray_started_here", True)  # no atexit hook from a test
    monkeypatch.setattr(session, "_joined_cluster", False)
    session.ensure_ray(address, workers)
    (kw,) = calls
    if address is None:
        assert kw["address"] == "local" and kw["num_cpus"] == num_cpus
    else:
        assert kw["address"] == address and "num_cpus" not in kw  # the cluster's own CPUs
    assert session.joined_cluster() is joined


def test_a_pool_whose_ray_session_ended_closes_without_ray(monkeypatch) -> None:
    """The pool a job kept (`job_pool`) after its Ray was shut down: closing it makes no
    remote call, which Ray would answer by starting a new local Ray (its auto-init: a test
    waited 80 s on one)."""

    touched: list[str] = []

    class Gone:  # an actor of the ended session: any use of it is recorded
        def __getattr__(self, name):
            touched.append(name)
            raise AttributeError(name)

    monkeypatch.setattr(pool_mod.ray, "is_initialized", lambda: False)
    monkeypatch.setattr(pool_mod.ray, "wait", lambda *a, **k: touched.append("wait"))
    monkeypatch.setattr(pool_mod.ray, "kill", lambda *a, **k: touched.append("kill"))
    p = EpisodePool(PLANAR, 2)
    p._slots = [pool_mod._Slot(Gone(), 0), pool_mod._Slot(Gone(), 1)]
    p.close()
    assert p._slots == [] and touched == []
