"""Grid expansion: one job's config -> the ordered list of episodes it runs.

Order: object, CoM index, Izz scale, floor friction, pusher friction (the config's own list
orders). Seeds and CoMs depend only on the global seed, the object and the CoM index, never on
the condition, so every condition (speed, friction, Izz, backend) sees the very same CoMs and
starting randomness: comparisons between conditions are paired.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any, Protocol

from comexp.backends.physics_settings import physics_identity
from comexp.episode.task import EpisodeSpec
from comexp.experiment.config import ExperimentConfig, estimator_settings, simulator_spec
from comexp.experiment.objects import com_points
from comexp.method.estimator import EstimatorSettings
from comexp.method.fit_estimator import FIT_VERSION
from comexp.method.motion_estimator import MOTION_VERSION

# the model revisions pinned in the episode key (`EstimatorSettings.motion_version`)
PINNED_VERSIONS = {"motion": MOTION_VERSION, "fit": FIT_VERSION}


class ObjectLike(Protocol):
    name: str
    outline_cm: Sequence[Sequence[float]]
    height_cm: float


ComFn = Callable[..., Sequence[Sequence[float]]]


def floor_conditions(name: str, mu: Sequence[float], orientations: Sequence[str] | None):
    """(mu_x, mu_y) per floor condition of a `floor` config node."""
    if name == "iso":
        return [(float(m), float(m)) for m in mu]
    a, b = (float(m) for m in mu)
    return [(a, b) if o == "xy" else (b, a) for o in (orientations or ())]


def episode_seed(seed: int, object_name: str, com_index: int) -> int:
    """Stable seed in [0, 2**31) for one (object, CoM): blake2b, not Python's salted hash();
    31 bits so that it fits a 32-bit integer column in any database."""
    key = f"{seed}\x1f{object_name}\x1f{com_index}".encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=4).digest(), "big") >> 1


def expand_grid(
    cfg: ExperimentConfig,
    objects: Mapping[str, ObjectLike],
    *,
    estimator: EstimatorSettings | None = None,
    com_fn: ComFn = com_points,
) -> list[EpisodeSpec]:
    """All episodes of one job. `objects` maps names to object definitions (in grid order when
    `cfg.grid.objects` is None); `com_fn(obj, n, base_seed=, margin_cm=)` gives the CoMs."""
    est = estimator if estimator is not None else estimator_settings(cfg.estimator)
    if est.method in PINNED_VERSIONS and not est.motion_version:
        est = replace(est, motion_version=PINNED_VERSIONS[est.method])
    sim = simulator_spec(cfg.backend, cfg.camera)
    physics = physics_identity(sim.name, sim.target, options=dict(sim.options))
    names = list(cfg.grid.objects) if cfg.grid.objects is not None else sorted(objects)
    floors = floor_conditions(cfg.floor.name, cfg.floor.mu, cfg.floor.orientations)
    n_com = cfg.grid.coms_per_object
    specs: list[EpisodeSpec] = []
    for name in names:
        obj = objects[name]
        coms = com_fn(obj, n_com, base_seed=cfg.seed, margin_cm=cfg.grid.com_margin_cm)
        if len(coms) != n_com:
            raise ValueError(f"{name}: expected {n_com} CoMs, got {len(coms)}")
        for k, com in enumerate(coms):
            common: dict[str, Any] = dict(
                backend=cfg.backend.name,
                floor=cfg.floor.name,
                speed_cm_s=float(cfg.speed),
                estimator=est,
                seed=episode_seed(cfg.seed, name, k),
                push_length_cm=float(cfg.episode.push_length_cm),
                recenter_beyond_cm=float(cfg.episode.recenter_beyond_cm),
                mass_kg=float(cfg.episode.mass_kg),
                physics=physics,
                camera_fps=float(cfg.camera.fps),
            )
            for izz in cfg.grid.izz_scales:
                for mu_x, mu_y in floors:
                    for mu_p in cfg.pusher.mu:
                        specs.append(
                            EpisodeSpec.for_object(
                                obj,
                                k,
                                com,
                                mu_floor_x=mu_x,
                                mu_floor_y=mu_y,
                                mu_pusher=float(mu_p),
                                izz_scale=float(izz),
                                **common,
                            )
                        )
    return specs
