"""One physics per result: what determines the physics is part of every episode's identity."""

from __future__ import annotations

from dataclasses import replace

import pytest

from comexp.experiment.episode import EpisodeResult, EpisodeSpec
from comexp.experiment.simulator import physics_identity
from comexp.method.scene import SimSettings
from comexp.results.identity import episode_key
from comexp.results.store import ResultsDB


def _spec(**kw) -> EpisodeSpec:
    base = dict(
        backend="planar",
        floor="iso",
        mu_floor_x=1.0,
        mu_floor_y=1.0,
        mu_pusher=0.5,
        speed_cm_s=40.0,
        izz_scale=1.0,
        object="box",
        outline_cm=((-4.0, -2.5), (4.0, -2.5), (4.0, 2.5), (-4.0, 2.5)),
        height_cm=1.5,
        com_index=0,
        com_cm=(0.5, 0.2),
    )
    base.update(kw)
    return EpisodeSpec(**base)


def test_identity_names_backend_revision_engine_and_settings():
    ident = physics_identity("pybullet", options={"floor_friction": "model"})
    name, revision, engine, digest = ident.split("/")
    assert name == "pybullet" and revision.startswith("pybullet-")
    assert engine.startswith("pybullet-3.") and len(digest) == 10
    assert physics_identity("pybullet", options={"floor_friction": "native"}) != ident
    slower = replace(SimSettings(), settle_hold_s=0.1)
    assert physics_identity("pybullet", slower, {"floor_friction": "model"}) != ident
    assert physics_identity("planar").startswith("planar/planar-")
    with pytest.raises(ValueError, match="unknown backend"):
        physics_identity("bullet")


def test_a_changed_backend_revision_changes_every_key(monkeypatch):
    import comexp.backends.planar_sim as planar

    a = _spec(physics=physics_identity("planar"))
    monkeypatch.setattr(planar, "PHYSICS_VERSION", "planar-999")
    b = _spec(physics=physics_identity("planar"))
    assert a.physics != b.physics
    assert episode_key(a) != episode_key(b)


def test_a_database_is_not_resumed_across_physics_versions(tmp_path):
    old = _spec(physics="planar/planar-1/numba-0.68.1/aaaaaaaaaa")
    new = replace(old, physics="planar/planar-2/numba-0.68.1/aaaaaaaaaa")
    result = EpisodeResult(old, "ok", None, (0.5, 0.2), 0.0, 0, (), 0.1)
    with ResultsDB(tmp_path / "r.db") as db:
        db.add_results(None, [result])
        stored = db.stored_keys([episode_key(old), episode_key(new)])
        assert stored == {episode_key(old)}  # the new physics' episode runs again
        row = db.episodes(columns=["physics"])[0]
        assert row["physics"] == old.physics


def test_a_worker_with_other_physics_refuses_the_episode():
    from comexp.workers.actor import EpisodeWorker

    w = EpisodeWorker("planar", runner="test_workers:fake_run")
    res = w.run_one(_spec(physics="planar/planar-0/numba-0.0/0000000000"))
    assert res.status == "failed" and res.failure == "physics_mismatch"
    assert "this worker runs planar/" in res.detail
