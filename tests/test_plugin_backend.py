"""A researcher's own backend plugs in from config, without editing the package: a user config
directory adds `backend/NAME.yaml` naming a `Simulator` subclass (`_target_: module.Class`)
whose module defines the physics identity's names, as the built-in backends' modules do.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from comexp.backends.physics_settings import physics_identity
from comexp.experiment.config import ConfigError, prepare_job
from comexp.experiment.grid import expand_grid

PLUGIN = '''\
"""A user's backend: the planar model under another name, counting its builds."""

from comexp.backends.planar_sim import PlanarSimulator

PHYSICS_VERSION = "toy-1"
PHYSICS_SETTINGS = {"what": "planar, renamed"}
BUILDS = []


class ToyPlanar(PlanarSimulator):
    name = "toy"

    def build(self, scene):
        BUILDS.append(scene.obj.name)
        super().build(scene)
'''
BROKEN = """\
from comexp.backends.planar_sim import PlanarSimulator


class NoIdentity(PlanarSimulator):
    pass
"""
NAME = "toy"
TARGET = "my_backends.ToyPlanar"


@pytest.fixture
def user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """DIR/conf/backend/toy.yaml (the config) and DIR/plug/my_backends.py (the code, on
    sys.path as an installed package or PYTHONPATH would put it)."""
    (tmp_path / "conf" / "backend").mkdir(parents=True)
    (tmp_path / "conf" / "backend" / "toy.yaml").write_text(f"name: {NAME}\n_target_: {TARGET}\n")
    (tmp_path / "plug").mkdir()
    (tmp_path / "plug" / "my_backends.py").write_text(PLUGIN)
    (tmp_path / "plug" / "my_broken_backends.py").write_text(BROKEN)
    monkeypatch.syspath_prepend(str(tmp_path / "plug"))
    for mod in ("my_backends", "my_broken_backends"):
        monkeypatch.delitem(sys.modules, mod, raising=False)
    return tmp_path


def _compose(*overrides: str, conf: Path | None = None):
    search = [f"hydra.searchpath=[file://{conf}]"] if conf else []
    with initialize_config_module("comexp.conf", version_base="1.3"):
        return compose("config", overrides=[*search, *overrides], return_hydra_config=True)


def test_a_plugin_backend_from_a_user_config_dir_runs_an_episode(user_dir: Path) -> None:
    from comexp.episode.loop import run_episode

    job = prepare_job(
        _compose(
            "backend=toy",
            "grid.objects=[l_shape]",
            "grid.coms_per_object=1",
            conf=user_dir / "conf",
        )
    )
    assert job.cfg.backend.name == NAME
    assert job.simulator.options == {}  # neither floor_friction nor a renderer: engines'
    specs = expand_grid(job.cfg, job.objects, estimator=job.estimator)
    physics = physics_identity(NAME, TARGET)
    assert physics.startswith(f"{NAME}/toy-1/numpy-none/")
    assert (
        specs and {s.physics for s in specs} == {physics} and {s.backend for s in specs} == {NAME}
    )
    sim = job.simulator.make()
    assert type(sim).__name__ == "ToyPlanar"
    res = run_episode(specs[0], sim)
    assert res.status == "ok", (res.failure, res.detail)
    assert res.n_pushes > 0 and sys.modules["my_backends"].BUILDS[0] == "l_shape"


@pytest.mark.parametrize(
    ("name", "needle"),
    [
        ("no_such_module.Sim", "cannot import"),
        ("math.no_such_name", "cannot import"),
        ("math.pi", "not a Simulator subclass"),
        ("my_broken_backends.NoIdentity", "must define PHYSICS_VERSION, PHYSICS_SETTINGS"),
        ("Sim", "must be module.Class"),
    ],
)
def test_a_backend_that_cannot_be_used_is_one_config_error(
    user_dir: Path, name: str, needle: str
) -> None:
    with pytest.raises(ConfigError) as info:
        prepare_job(_compose("backend=toy", f"backend._target_={name}", conf=user_dir / "conf"))
    msg = str(info.value)
    assert needle in msg and "\n" not in msg, msg


def test_an_unknown_backend_is_one_line_naming_the_choices() -> None:
    from hydra.errors import HydraException

    from comexp.experiment.config import hydra_error_line

    with pytest.raises(HydraException) as info:
        _compose("backend=bullet3")
    assert hydra_error_line(info.value) == (
        "unknown backend 'bullet3' (choose one of: mujoco, planar, pybullet)"
    )
