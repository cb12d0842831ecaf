"""A researcher's own estimator plugs in from config, without editing the package: a user config
directory (`--config-dir` / `hydra.searchpath`) adds `estimator/NAME.yaml` naming a class
(`estimator.method=module:Class`) that implements the `Estimator` protocol.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from comexp.experiment.config import ConfigError, prepare_job
from comexp.experiment.grid import expand_grid
from comexp.method.estimator import ComEstimator, EstimatorSettings
from comexp.method.estimators import Estimator, make_estimator, resolve_estimator

PLUGIN = '''\
"""A user's estimator: Algorithm 1's push choice and Algorithm 2's update from the library,
without the reachability check; counts its calls."""

import numpy as np

from comexp.method.estimator import choose_contact, update_region

CALLS = []


class CentroidEstimator:
    def __init__(self, region_m, contacts_m, normals, pixel_m, settings, outline_m=None,
                 pusher_radius_m=None):
        self.region = np.asarray(region_m, dtype=float)
        self.contacts = np.asarray(contacts_m, dtype=float).reshape(-1, 2)
        n = np.asarray(normals, dtype=float).reshape(-1, 2)
        self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.pixel_m, self.settings = float(pixel_m), settings
        CALLS.append("init")

    def next_push(self):
        j = choose_contact(self.region, self.contacts, self.normals, self.settings, self.pixel_m)
        return None if j is None else (self.contacts[j].copy(), self.normals[j].copy())

    def observe(self, contact_m, direction, rotation_deg, line_direction=None):
        self.region, decision = update_region(
            self.region, contact_m, direction, rotation_deg, self.settings, self.pixel_m
        )
        CALLS.append(decision)
        return decision

    @property
    def estimate_m(self):
        return self.region.mean(axis=0)

    @property
    def region_px(self):
        return len(self.region)
'''
METHOD = "my_estimators:CentroidEstimator"


@pytest.fixture
def user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """DIR/conf/estimator/centroid.yaml (the config) and DIR/plug/my_estimators.py (the code,
    on sys.path as an installed package or PYTHONPATH would put it)."""
    (tmp_path / "conf" / "estimator").mkdir(parents=True)
    (tmp_path / "conf" / "estimator" / "centroid.yaml").write_text(f"method: {METHOD}\n")
    (tmp_path / "plug").mkdir()
    (tmp_path / "plug" / "my_estimators.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path / "plug"))
    monkeypatch.delitem(sys.modules, "my_estimators", raising=False)
    return tmp_path


def _compose(conf: Path, *overrides: str):
    with initialize_config_module("comexp.conf", version_base="1.3"):
        return compose(
            "config",
            overrides=[f"hydra.searchpath=[file://{conf}]", *overrides],
            return_hydra_config=True,
        )


def _square(half_m: float = 0.03, pixel_m: float = 0.0027):
    """A square object's CoM region (grid points), contour points with inward normals."""
    g = np.arange(-half_m + pixel_m / 2, half_m, pixel_m)
    region = np.array([(x, y) for x in g for y in g])
    s = np.linspace(-half_m * 0.9, half_m * 0.9, 9)
    P, N = [], []
    for x in s:
        P += [(x, -half_m), (x, half_m)]
        N += [(0.0, 1.0), (0.0, -1.0)]
        P += [(-half_m, x), (half_m, x)]
        N += [(1.0, 0.0), (-1.0, 0.0)]
    return region, np.array(P), np.array(N), pixel_m


def test_a_plugin_from_a_user_config_dir_is_resolved_and_called(user_dir: Path) -> None:
    job = prepare_job(_compose(user_dir / "conf", "estimator=centroid", "grid.objects=[l_shape]"))
    assert job.estimator.method == METHOD
    specs = expand_grid(job.cfg, job.objects, estimator=job.estimator)
    assert specs and {s.estimator.method for s in specs} == {METHOD}
    cls = resolve_estimator(METHOD)
    assert cls.__module__ == "my_estimators"
    region, P, N, pixel_m = _square()
    est = make_estimator(region, P, N, pixel_m, job.estimator)
    assert isinstance(est, cls) and isinstance(est, Estimator)
    com = np.array([0.012, -0.007])
    for _ in range(job.estimator.n_push):  # the voting theorem's sign, 5 deg
        push = est.next_push()
        if push is None:
            break
        contact, direction = push
        lever = direction[0] * (com[1] - contact[1]) - direction[1] * (com[0] - contact[0])
        est.observe(contact, direction, 5.0 if lever > 0 else -5.0)
    calls = sys.modules["my_estimators"].CALLS
    assert calls[0] == "init" and len(calls) > 2
    assert np.linalg.norm(est.estimate_m - com) < 0.01
    assert est.region_px < len(region)


def test_the_built_in_methods_stay_the_built_in_estimator() -> None:
    region, P, N, pixel_m = _square()
    for method in ("paper", "magnitude"):
        est = make_estimator(region, P, N, pixel_m, EstimatorSettings(method=method))
        assert type(est) is ComEstimator and isinstance(est, Estimator)


@pytest.mark.parametrize(
    ("method", "needle"),
    [
        ("no_such_module:Estimator", "cannot import"),
        ("math:no_such_name", "cannot import"),
        ("math:pi", "not an estimator class"),
        ("bayes", "must be one of"),
    ],
)
def test_a_plugin_that_cannot_be_used_is_one_config_error(method: str, needle: str) -> None:
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"estimator.method={method}"], return_hydra_config=True)
    with pytest.raises(ConfigError) as info:
        prepare_job(cfg)
    msg = str(info.value)
    assert msg.startswith("estimator.method ") and needle in msg and "\n" not in msg


def test_the_command_line_takes_the_users_config_dir(user_dir: Path) -> None:
    script = Path(sys.executable).with_name("comexp")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "comexp.cli.run"]
    r = subprocess.run(
        [*cmd, "--config-dir", str(user_dir / "conf"), "estimator=centroid"]
        + ["--cfg", "job", "-p", "estimator.method"],
        capture_output=True,
        text=True,
        cwd=user_dir,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == METHOD


def test_an_episode_runs_the_plugin(user_dir: Path) -> None:
    from test_episode import KinematicSim, run_kinematic, spec_for

    res = run_kinematic(spec_for(method=METHOD), KinematicSim())
    assert res.status == "ok", (res.failure, res.detail)
    assert res.n_pushes > 0 and len(sys.modules["my_estimators"].CALLS) > 1
