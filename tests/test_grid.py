"""Grid expansion: counts, paired CoMs and seeds across conditions, stable order."""

from __future__ import annotations

import collections
import subprocess
import sys

from hydra import compose, initialize_config_module

from comexp.experiment.config import prepare_job
from comexp.experiment.grid import episode_seed, expand_grid, floor_conditions
from comexp.results.identity import episode_key

SMALL = ["grid.coms_per_object=1", "grid.izz_scales=[1]", "pusher.mu=[1.0]"]


def _specs(*overrides: str):
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", overrides=list(overrides), return_hydra_config=True)
    job = prepare_job(cfg)
    return expand_grid(job.cfg, job.objects, estimator=job.estimator)


def test_default_job_is_1600_episodes_over_20_objects() -> None:
    specs = _specs()
    assert len({s.object for s in specs}) == 20
    assert len(specs) == 1600
    assert len({episode_key(s) for s in specs}) == 1600  # no episode twice
    per_object = collections.Counter(s.object for s in specs)
    assert set(per_object.values()) == {80}  # 10 CoMs x 2 Izz x 2 floor mu x 2 pusher mu


def test_aniso_example_is_80_episodes_with_both_orientations() -> None:
    by_speed = {v: _specs("floor=aniso", f"speed={v}", *SMALL) for v in (40, 4)}
    assert sum(len(s) for s in by_speed.values()) == 80
    for specs in by_speed.values():
        assert len(specs) == 40
        assert {(s.mu_floor_x, s.mu_floor_y) for s in specs} == {(0.1, 1.0), (1.0, 0.1)}
        assert {s.floor for s in specs} == {"aniso"}
    one = _specs("floor=aniso", "floor.orientations=[yx]", *SMALL)
    assert {(s.mu_floor_x, s.mu_floor_y) for s in one} == {(1.0, 0.1)}
    assert len(_specs("floor=aniso", "pusher.mu=[0.5]", "grid.coms_per_object=1")) == 20 * 2 * 2


def test_smoke_example_is_20_episodes() -> None:
    specs = _specs(*SMALL, "floor.mu=[1.0]")
    assert len(specs) == 20
    assert {(s.mu_floor_x, s.mu_floor_y, s.mu_pusher, s.izz_scale) for s in specs} == {
        (1.0, 1.0, 1.0, 1.0)
    }


def test_every_condition_sees_the_same_coms_and_seeds() -> None:
    grids = [
        _specs("grid.coms_per_object=3"),
        _specs("grid.coms_per_object=3", "floor=aniso", "speed=4"),
        _specs("grid.coms_per_object=3", "backend=mujoco", "grid.izz_scales=[10]"),
    ]
    seen: dict[tuple[str, int], set] = collections.defaultdict(set)
    for specs in grids:
        for s in specs:
            seen[(s.object, s.com_index)].add((s.com_cm, s.seed))
    assert len(seen) == 60
    assert all(len(v) == 1 for v in seen.values())
    # and the first k CoMs do not depend on how many are asked for
    fewer = {(s.object, s.com_index): s.com_cm for s in _specs("grid.coms_per_object=2")}
    assert all(seen[k] == {(c, episode_seed(0, *k))} for k, c in fewer.items())
    # distinct CoMs and seeds within an object
    coms = [next(iter(v))[0] for k, v in seen.items() if k[0] == "l_shape"]
    assert len(set(coms)) == 3
    assert len({next(iter(v))[1] for v in seen.values()}) == 60


def test_order_is_deterministic() -> None:
    a, b = _specs("grid.coms_per_object=2"), _specs("grid.coms_per_object=2")
    assert a == b
    objects = [s.object for s in a]
    assert objects == sorted(objects)
    first = a[:8]  # one CoM: Izz x floor mu x pusher mu, the config's own list order
    assert [(s.izz_scale, s.mu_floor_x, s.mu_pusher) for s in first] == [
        (i, f, p) for i in (1.0, 10.0) for f in (0.1, 1.0) for p in (0.1, 1.0)
    ]
    chosen = _specs("grid.objects=[u_shape,arrow]", "floor.mu=[1.0]", *SMALL)
    assert [s.object for s in chosen] == ["u_shape", "arrow"]


def test_seeds_are_stable_across_processes() -> None:
    """Seeds must not come from Python's salted hash(): pin one and recompute elsewhere."""
    code = "from comexp.experiment.grid import episode_seed; print(episode_seed(7, 'l_shape', 3))"
    outs = {
        subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONHASHSEED": str(h)},
        ).stdout.strip()
        for h in (1, 2)
    }
    assert outs == {str(episode_seed(7, "l_shape", 3))}
    assert episode_seed(0, "l_shape", 0) == 5045332
    assert episode_seed(1, "l_shape", 0) != episode_seed(0, "l_shape", 0)
    assert 0 <= episode_seed(0, "x", 0) < 2**31


def test_floor_conditions() -> None:
    assert floor_conditions("iso", [0.1, 1.0], None) == [(0.1, 0.1), (1.0, 1.0)]
    assert floor_conditions("aniso", [0.2, 0.7], ["xy", "yx"]) == [(0.2, 0.7), (0.7, 0.2)]
    assert floor_conditions("aniso", [0.2, 0.7], ["yx"]) == [(0.7, 0.2)]


def test_episode_protocol_reaches_every_spec() -> None:
    default = _specs(*SMALL, "floor.mu=[1.0]")
    assert {(s.push_length_cm, s.recenter_beyond_cm) for s in default} == {(3.0, 10.0)}
    changed = _specs(
        *SMALL, "floor.mu=[1.0]", "episode.push_length_cm=2", "episode.recenter_beyond_cm=0"
    )
    assert {(s.push_length_cm, s.recenter_beyond_cm) for s in changed} == {(2.0, 0.0)}
    # a different protocol is a different episode (never mixed up with stored ones)
    assert {episode_key(s) for s in changed}.isdisjoint({episode_key(s) for s in default})


def test_motion_jobs_pin_the_motion_model_version() -> None:
    """A motion job's episodes carry MOTION_VERSION (so a database of an older motion model is
    not resumed as if it were this one); paper's do not, and their keys are as before the
    field existed (it is left out of the key when unset)."""
    from comexp.method.motion_estimator import MOTION_VERSION
    from comexp.results.identity import canonical_json

    motion = _specs(*SMALL, "estimator.method=motion", "grid.objects=[l_shape]")
    assert {s.estimator.motion_version for s in motion} == {MOTION_VERSION}
    paper = _specs(*SMALL, "grid.objects=[l_shape]")
    assert {s.estimator.motion_version for s in paper} == {""}
    assert all("motion_version" not in canonical_json(s) for s in paper)
    pinned = _specs(*SMALL, "estimator.method=motion", "estimator.motion_version=motion-1")
    assert {s.estimator.motion_version for s in pinned} == {"motion-1"}
