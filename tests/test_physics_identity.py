"""One physics per result: what determines the physics is part of every episode's identity."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import pytest

from comexp.backends.physics_settings import physics_identity
from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.results.identity import episode_key
from comexp.results.store import ResultsDB
from comexp.sim.scene import SimSettings
from comexp.sim.simulator import SimulatorSpec


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


PLANAR = "comexp.backends.planar_sim.PlanarSimulator"
PYBULLET = "comexp.backends.pybullet_sim.PybulletSimulator"


def test_identity_names_backend_revision_engine_and_settings():
    ident = physics_identity("pybullet", PYBULLET, options={"floor_friction": "model"})
    name, revision, engine, digest = ident.split("/")
    assert name == "pybullet" and revision.startswith("pybullet-")
    assert engine.startswith("pybullet-3.") and len(digest) == 10
    assert physics_identity("pybullet", PYBULLET, options={"floor_friction": "native"}) != ident
    slower = replace(SimSettings(), settle_hold_s=0.1)
    assert physics_identity("pybullet", PYBULLET, slower, {"floor_friction": "model"}) != ident
    assert physics_identity("planar", PLANAR).startswith("planar/planar-")
    with pytest.raises(ValueError, match="cannot import"):
        physics_identity("bullet", "no_such_module.Bullet")


def test_the_built_in_identities_are_the_ones_stored_before():
    """Episode keys hold the physics identity: a built-in's must not change unless its
    physics does (then its version is bumped). These are the identities main's studies were
    stored with (their rows resume)."""
    assert physics_identity("planar", PLANAR) == "planar/planar-9/numba-0.68.1/518833411a"


def test_a_changed_backend_revision_changes_every_key(monkeypatch):
    import comexp.backends.physics_settings as physics

    a = _spec(physics=physics_identity("planar", PLANAR))
    bumped = physics.PLANAR._replace(version="planar-999")
    monkeypatch.setitem(physics.BUILTIN_PHYSICS, "comexp.backends.planar_sim", bumped)
    b = _spec(physics=physics_identity("planar", PLANAR))
    assert a.physics != b.physics
    assert episode_key(a) != episode_key(b)


@pytest.mark.parametrize("name", ["planar", "pybullet", "mujoco"])
def test_a_builtin_module_exports_the_physics_its_identity_reads(name):
    """The driver reads a built-in's physics from `physics_settings` without its engine; the
    backend's module (the plug-in contract's names) must say the same."""
    import importlib

    from comexp.backends.physics_settings import BUILTIN_PHYSICS
    from comexp.experiment.config import load_backend

    module_name = load_backend(name)._target_.rpartition(".")[0]
    module = importlib.import_module(module_name)
    version, engine, settings = BUILTIN_PHYSICS[module_name]
    assert version == module.PHYSICS_VERSION and version.startswith(f"{name}-")
    assert engine == module.ENGINE_DISTRIBUTION
    assert repr(module.PHYSICS_SETTINGS) == repr(settings)


def test_naming_the_physics_imports_no_engine():
    """Expanding a grid names every episode's physics in the driver: no engine, Numba or the
    episode loop may load for it (+79 MB of the driver's RSS with MuJoCo's)."""
    code = (
        "import sys\n"
        "from comexp.backends.physics_settings import physics_identity\n"
        "for b, c in (('planar', 'Planar'), ('pybullet', 'Pybullet'), ('mujoco', 'Mujoco')):\n"
        "    t = f'comexp.backends.{b}_sim.{c}Simulator'\n"
        "    physics_identity(b, t, options={} if b == 'planar' else {'floor_friction': 'model'})\n"
        "heavy = ('mujoco', 'pybullet', 'numba', 'scipy', 'comexp.backends.floor_friction')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


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
    from test_workers import fake_run

    from comexp.workers.actor import EpisodeWorker

    w = EpisodeWorker(SimulatorSpec("planar", PLANAR), runner=fake_run)
    res = w.run_one(_spec(physics="planar/planar-0/numba-0.0/0000000000"))
    assert res.status == "failed" and res.failure == "physics_mismatch"
    assert "this worker runs planar/" in res.detail
