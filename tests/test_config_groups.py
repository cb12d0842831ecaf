"""Every option of every config group under conf/ composes and builds a job (the
lightning-hydra-template habit): backend x floor x experiment, each through Hydra's compose API,
the validation path the command runs (`prepare_job`) and the grid expansion.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from comexp.experiment.config import prepare_job
from comexp.experiment.grid import expand_grid

CONF = Path(__file__).resolve().parents[1] / "conf"
# `object/` holds object definitions that `grid.objects` names (every job below loads all of
# them), not configs to compose.
NOT_COMPOSED = {"object"}


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def _groups() -> dict[str, list[str]]:
    return {
        d.name: _options(d.name)
        for d in sorted(CONF.iterdir())
        if d.is_dir() and not d.name.startswith(("_", ".")) and d.name not in NOT_COMPOSED
    }


def _in_defaults_list() -> set[str]:
    """Groups the primary config chooses (`group=option`); the others are added (`+group=`)."""
    import yaml

    defaults = yaml.safe_load((CONF / "config.yaml").read_text())["defaults"]
    return {next(iter(d)) for d in defaults if isinstance(d, dict)}


def _combinations() -> list[tuple[str, ...]]:
    chosen = _in_defaults_list()
    axes = []
    for group, options in _groups().items():
        if group in chosen:
            axes.append([f"{group}={o}" for o in options])
        else:  # an optional group: without it, and with each option
            axes.append([None, *(f"+{group}={o}" for o in options)])
    return [tuple(o for o in combo if o) for combo in itertools.product(*axes)]


def test_the_groups_are_found() -> None:
    groups = _groups()
    assert {"backend", "floor", "experiment"} <= set(groups)
    assert set(groups["backend"]) == {"planar", "pybullet", "mujoco"}
    assert set(groups["floor"]) == {"iso", "aniso"}
    assert len(_combinations()) >= 3 * 2 * 2


@pytest.mark.parametrize("overrides", _combinations(), ids=" ".join)
def test_every_combination_composes_and_builds_its_job(overrides: tuple[str, ...]) -> None:
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
    job = prepare_job(cfg)
    choices = cfg.hydra.runtime.choices
    assert job.cfg.backend.name == choices["backend"]
    assert job.cfg.floor.name == choices["floor"]
    specs = expand_grid(job.cfg, job.objects, estimator=job.estimator)
    g = job.cfg.grid
    n_floors = (
        len(job.cfg.floor.mu) if job.cfg.floor.name == "iso" else len(job.cfg.floor.orientations)
    )
    n = len(job.objects) * g.coms_per_object * len(g.izz_scales) * n_floors * len(job.cfg.pusher.mu)
    assert len(specs) == n > 0
    assert {s.backend for s in specs} == {job.cfg.backend.name}
    assert {s.floor for s in specs} == {job.cfg.floor.name}
