"""Structured configuration of one experiment job, its validation, and what it names by name
(objects, backends).

The job's schema (`ExperimentConfig`, registered in Hydra's ConfigStore as the schema of
`conf/config.yaml`) is composed of the settings each part of comexp owns, with their defaults
written once, there: the push protocol's (`episode`, `camera`: `comexp.episode.task`), the
estimator's (`estimator`: generated from `comexp.method.estimator.EstimatorSettings`, a knob per
field), the pool's and Ray's (`execution`, `ray`, `workers`: `comexp.workers.settings`);
conf/config.yaml holds only the group choices and Hydra's own settings. A wrong *type*
(``speed=abc``) is rejected by Hydra while composing; wrong *values* (negative speed, unknown
object, ...) by `prepare_job`, which the CLI runs before Hydra creates any output folder
(`comexp.cli.run`): bad input costs nothing and leaves nothing behind. Validation is pure: it
probes neither the database nor Ray (the job does, once: `comexp.experiment.job.probe_resources`).

A backend is its config group option (`conf/backend/NAME.yaml`): its `name` and its simulator
class (`_target_`, `module.Class`); a researcher's own backend is one such file in their config
directory plus their module (docs/physics.md, "Your own backend").
"""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from hydra.errors import MissingConfigException
from omegaconf import MISSING, DictConfig, OmegaConf, open_dict

from comexp.backends.physics_settings import (
    FLOOR_FRICTION_CHOICES,
    RENDERER_CHOICES,
    backend_physics,
)
from comexp.episode.task import CameraSettings, EpisodeSettings
from comexp.experiment.objects import ObjectDef, load_objects
from comexp.experiment.sources import PACKAGE_SOURCES, group_files, read_mapping, yaml_error_line
from comexp.method.estimator import EstimatorSettings
from comexp.method.estimators import resolve_estimator
from comexp.sim.scene import SimSettings
from comexp.sim.simulator import Simulator, SimulatorSpec
from comexp.workers.settings import PoolSettings, RaySettings, check_workers

FLOOR_KINDS = ("iso", "aniso")
ANISO_ORIENTATIONS = ("xy", "yx")
SCHEMA_NAME = "comexp_schema"
BACKEND_GROUP = "backend"
# A commodity depth camera (RealSense D4xx, Azure Kinect, ...) streams depth at up to 30 fps.
MAX_CAMERA_FPS = 30.0


class ConfigError(ValueError):
    """Bad user input; the message is one line that names the offending key."""


# --- schema -------------------------------------------------------------------------------


@dataclass
class BackendConfig:
    """The `backend` group's option (conf/backend/NAME.yaml; default: conf/config.yaml's
    defaults list)."""

    name: str = MISSING  # the backend's name in the database and the reports
    _target_: str = MISSING  # its simulator class, module.Class (a `Simulator` subclass)
    # a 3-D engine: it takes `floor_friction` and draws its images with `camera.renderer`
    engine: bool = False
    # engines: "model" = the shared footprint friction model applied as a force each step
    # (the engine's own object-floor friction off); "native" = the engine's own friction
    floor_friction: str = "model"
    # what only Linux has, when the backend needs it (refused elsewhere in one line)
    linux_only: str | None = None
    # the simulator class's own keyword arguments (a plug-in's: part of its physics identity)
    options: dict[str, Any] = field(default_factory=dict)


@dataclass
class FloorConfig:
    """`floor=iso`: each value of `mu` is one floor, mu_x = mu_y = value.

    `floor=aniso`: `mu` = [mu_a, mu_b], the coefficients along the floor's two principal axes;
    each entry of `orientations` is one floor: ``xy`` gives (mu_x, mu_y) = (mu_a, mu_b) and
    ``yx`` the swapped one. Both orientations run by default (``floor.orientations=[xy]``
    runs one).
    """

    name: str = MISSING  # iso | aniso
    mu: list[float] = MISSING
    orientations: list[str] | None = None


@dataclass
class PusherConfig:
    mu: list[float] = field(default_factory=lambda: [0.1, 1.0])


@dataclass
class GridConfig:
    objects: list[str] | None = None  # None: every config in the `object` group
    coms_per_object: int = 10
    izz_scales: list[float] = field(default_factory=lambda: [1.0, 10.0])
    com_margin_cm: float = 1.0  # sampled CoMs keep this distance from the outline


# the `estimator` node's types for the settings' (OmegaConf has lists, not tuples)
_NODE_TYPES = {
    "tuple[float, float]": list[float],
    "float": float,
    "int": int,
    "str": str,
    "bool": bool,
}


def _knob(f: dataclasses.Field) -> str:
    """The config name of an `EstimatorSettings` field."""
    return f.metadata.get("knob", f.name)


def _estimator_node() -> type:
    """The `estimator` node: a knob per `EstimatorSettings` field, its default the field's."""
    fields = []
    for f in dataclasses.fields(EstimatorSettings):
        default = f.default
        if isinstance(default, tuple):
            spec = field(default_factory=lambda d=default: list(d))
        else:
            spec = field(default=default)
        fields.append((_knob(f), _NODE_TYPES[str(f.type)], spec))
    return dataclasses.make_dataclass("EstimatorConfig", fields)


EstimatorConfig = _estimator_node()


@dataclass
class ExperimentConfig:
    """One Hydra job = one (backend, floor, speed); the grid fans out over the rest."""

    backend: BackendConfig = MISSING
    floor: FloorConfig = MISSING
    speed: float = 40.0  # cm/s
    pusher: PusherConfig = field(default_factory=PusherConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    episode: EpisodeSettings = field(default_factory=EpisodeSettings)
    estimator: Any = field(default_factory=EstimatorConfig)
    camera: CameraSettings = field(default_factory=CameraSettings)
    # a count, `auto` (every CPU of the Ray cluster, or of this machine for a local Ray), or
    # null: 2 on a local Ray, `auto` when the job joins a cluster (`ray.address` set)
    workers: Any = None
    ray: RaySettings = field(default_factory=RaySettings)
    execution: PoolSettings = field(default_factory=PoolSettings)
    db: str = "results/comexp.db"  # SQLAlchemy URL or file path (relative to the current dir)
    seed: int = 0


def register_configs() -> None:
    """Register the schema; `conf/config.yaml` lists it first in its defaults."""
    cs = ConfigStore.instance()
    cs.store(name=SCHEMA_NAME, node=ExperimentConfig)


register_configs()


# --- backends by name ----------------------------------------------------------------------


def simulator_spec(backend: BackendConfig, camera: CameraSettings) -> SimulatorSpec:
    """The simulator a job's workers build: the backend's class and its options (its own, and
    an engine's floor friction and renderer)."""
    options = dict(backend.options)
    if backend.engine:
        options.update(floor_friction=backend.floor_friction, renderer=camera.renderer)
    return SimulatorSpec(backend.name, backend._target_, options)


def load_backend(
    name: str, sources: Sequence[Mapping[str, Any]] = PACKAGE_SOURCES
) -> BackendConfig:
    """The backend config group's option `name` (`backend/NAME.yaml` of the sources: the
    package's own by default), as the job's `backend` node; ValueError (one line) for an
    unknown name."""
    files = group_files(BACKEND_GROUP, sources)
    if name not in files:
        raise ValueError(f"unknown backend {name!r} (choose one of: {', '.join(sorted(files))})")
    data = read_mapping(f"backend {name!r}", files[name])
    node = OmegaConf.merge(OmegaConf.structured(BackendConfig), data)
    return OmegaConf.to_object(node)  # type: ignore[return-value]


def make_simulator(name: str, settings: SimSettings | None = None, **options: Any) -> Simulator:
    """A simulator of the built-in backend `name` (tests, bench, replay); `options` are its own
    (an engine's `floor_friction`, `renderer`)."""
    backend = load_backend(name)
    return SimulatorSpec(name, backend._target_, options).make(settings)


def hydra_error_line(e: BaseException) -> str:
    """One line out of Hydra's, OmegaConf's and PyYAML's multi-line messages."""
    if isinstance(e, yaml.YAMLError):
        return yaml_error_line(e)
    if isinstance(e, MissingConfigException) and e.missing_cfg_file and e.options is not None:
        group, _, name = e.missing_cfg_file.rpartition("/")
        if group:
            return f"unknown {group} {name!r} (choose one of: {', '.join(e.options)})"
    cause = e.__cause__ or e.__context__
    for err in (cause, e):
        key = getattr(err, "full_key", None)
        msg = getattr(err, "msg", None)
        if key and msg:
            return f"{key}: {str(msg).splitlines()[0]}"
    text = [t.strip() for t in str(e).splitlines() if t.strip()]
    if cause is not None and (not text or text[-1].endswith(":")):
        text += [t.strip() for t in str(cause).splitlines() if t.strip()][:1]
    return " ".join(text[:2]) if text else type(e).__name__


# --- conversion and validation ------------------------------------------------------------


def estimator_settings(est: Any) -> EstimatorSettings:
    """The `estimator` node as `EstimatorSettings` (lists back to tuples)."""
    kwargs = {}
    for f in dataclasses.fields(EstimatorSettings):
        knob = _knob(f)
        value = est[knob] if isinstance(est, Mapping) else getattr(est, knob)
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value)
        kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    return EstimatorSettings(**kwargs)


def to_experiment(cfg: DictConfig) -> ExperimentConfig:
    """The job's config as plain dataclasses (the `hydra` node is dropped)."""
    job = cfg
    if "hydra" in cfg:  # a callback's view of the config: drop Hydra's own node
        job = copy.deepcopy(cfg)
        with open_dict(job):
            job.pop("hydra")
    try:
        obj = OmegaConf.to_object(job)
    except Exception as e:  # MissingMandatoryValue, ValidationError: say which key
        key = getattr(e, "full_key", None)
        msg = getattr(e, "msg", str(e)).splitlines()[0]
        raise ConfigError(f"{key}: {msg}" if key else msg) from None
    if not isinstance(obj, ExperimentConfig):
        raise ConfigError("the primary config must be based on the comexp schema")
    return obj


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


def _check_list(key: str, values: Sequence[float], *, minimum: float, strict: bool) -> None:
    if not values:
        raise ConfigError(f"{key} must not be empty")
    for v in values:
        bad = not _finite(v) or (v <= minimum if strict else v < minimum)
        if bad:
            op = ">" if strict else ">="
            raise ConfigError(f"{key} values must be finite and {op} {minimum:g}, got {v!r}")
    if len(set(values)) != len(values):
        raise ConfigError(f"{key} has duplicate values: {list(values)}")


def validate(cfg: ExperimentConfig) -> EstimatorSettings:
    """Value checks that a schema cannot express; returns the estimator settings.

    The checks run in the order of the config's sections, and the first that fails raises."""
    _validate_backend(cfg.backend)
    _validate_floor(cfg.floor)
    if not _finite(cfg.speed) or cfg.speed <= 0:
        raise ConfigError(f"speed must be a positive number of cm/s, got {cfg.speed!r}")
    _check_list("pusher.mu", cfg.pusher.mu, minimum=0.0, strict=False)
    g = cfg.grid
    if g.coms_per_object < 1:
        raise ConfigError(f"grid.coms_per_object must be >= 1, got {g.coms_per_object}")
    _check_list("grid.izz_scales", g.izz_scales, minimum=0.0, strict=True)
    if not _finite(g.com_margin_cm) or g.com_margin_cm < 0:
        raise ConfigError(f"grid.com_margin_cm must be >= 0, got {g.com_margin_cm!r}")
    _validate_episode(cfg.episode)
    _validate_camera(cfg.camera)
    if g.objects is not None:
        if not g.objects:
            raise ConfigError("grid.objects must not be empty (omit it to use every object)")
        if len(set(g.objects)) != len(g.objects):
            raise ConfigError(f"grid.objects has duplicates: {list(g.objects)}")
    try:
        check_workers(cfg.workers)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    _validate_execution(cfg.execution)
    if cfg.seed < 0:
        raise ConfigError(f"seed must be >= 0, got {cfg.seed}")
    if not cfg.db.strip():
        raise ConfigError("db must be a database URL or a file path")
    return _validate_estimator(cfg.estimator)


def _validate_backend(backend: BackendConfig) -> None:
    try:
        cls = simulator_spec(backend, CameraSettings()).simulator_class()
        backend_physics(backend._target_)
    except ValueError as e:
        raise ConfigError(
            f"backend={backend.name}: {str(e).removeprefix(f'backend {backend.name!r}: ')}"
        ) from None
    if not issubclass(cls, Simulator):  # (simulator_class checks it; stated for the reader)
        raise ConfigError(f"backend={backend.name}: not a Simulator")
    if backend.floor_friction not in FLOOR_FRICTION_CHOICES:
        raise ConfigError(
            f"backend.floor_friction must be one of {', '.join(FLOOR_FRICTION_CHOICES)}, "
            f"got {backend.floor_friction!r}"
        )
    if not backend.engine and backend.floor_friction != "model":
        raise ConfigError(
            f"backend={backend.name} is the friction model itself: floor_friction=model only"
        )
    if backend.linux_only and not sys.platform.startswith("linux"):
        raise ConfigError(
            f"backend={backend.name} runs on Linux only ({backend.linux_only}); this is "
            f"{sys.platform}: use backend=planar or backend=pybullet, or the docker image (docker/)"
        )


def _validate_floor(fl: FloorConfig) -> None:
    if fl.name not in FLOOR_KINDS:
        raise ConfigError(f"floor.name must be one of {', '.join(FLOOR_KINDS)}, got {fl.name!r}")
    _check_list("floor.mu", fl.mu, minimum=0.0, strict=False)
    if fl.name == "iso" and fl.orientations is not None:
        raise ConfigError("floor.orientations applies to floor=aniso only")
    if fl.name == "aniso":
        if len(fl.mu) != 2:
            raise ConfigError(
                f"floor=aniso needs floor.mu=[mu_a, mu_b] (two values), got {list(fl.mu)}"
            )
        if not fl.orientations:
            raise ConfigError("floor.orientations must list at least one of: xy, yx")
        for o in fl.orientations:
            if o not in ANISO_ORIENTATIONS:
                raise ConfigError(f"floor.orientations: unknown orientation {o!r} (use xy, yx)")
        if len(set(fl.orientations)) != len(fl.orientations):
            raise ConfigError(f"floor.orientations has duplicates: {list(fl.orientations)}")


def _validate_episode(ep: EpisodeSettings) -> None:
    if not _finite(ep.push_length_cm) or ep.push_length_cm <= 0:
        raise ConfigError(f"episode.push_length_cm must be > 0, got {ep.push_length_cm!r}")
    if not _finite(ep.mass_kg) or ep.mass_kg <= 0:
        raise ConfigError(f"episode.mass_kg must be > 0, got {ep.mass_kg!r}")
    if not _finite(ep.recenter_beyond_cm) or ep.recenter_beyond_cm < 0:
        msg = f"episode.recenter_beyond_cm must be >= 0 (0: never), got {ep.recenter_beyond_cm!r}"
        raise ConfigError(msg)


def _validate_camera(camera: CameraSettings) -> None:
    fps = camera.fps
    if not _finite(fps) or not 0 <= fps <= MAX_CAMERA_FPS:
        raise ConfigError(
            f"camera.fps must be between 0 (before and after only) and {MAX_CAMERA_FPS:g} "
            f"(a commodity depth camera), got {fps!r}"
        )
    if camera.renderer not in RENDERER_CHOICES:
        raise ConfigError(
            f"camera.renderer must be one of {', '.join(RENDERER_CHOICES)}, got {camera.renderer!r}"
        )


def _validate_execution(ex: PoolSettings) -> None:
    if ex.batch_size < 1:
        raise ConfigError(f"execution.batch_size must be >= 1, got {ex.batch_size}")
    if not ex.restart_timeout_s > 0:
        raise ConfigError(f"execution.restart_timeout_s must be > 0, got {ex.restart_timeout_s}")
    if not (_finite(ex.episode_timeout_s) and ex.episode_timeout_s > 0):
        raise ConfigError(f"execution.episode_timeout_s must be > 0, got {ex.episode_timeout_s}")
    if ex.max_retries < 0:
        raise ConfigError(f"execution.max_retries must be >= 0, got {ex.max_retries}")


def _validate_estimator(est: Any) -> EstimatorSettings:
    """The estimator node through `EstimatorSettings`' own checks (the one set of rules) and
    the estimator's class (`resolve_estimator`: a plug-in that cannot be used fails here), its
    message naming the config key (`theta_T_deg` -> `estimator.theta_T`)."""
    knobs = {f.name: _knob(f) for f in dataclasses.fields(EstimatorSettings)}
    try:
        settings = estimator_settings(est)
        resolve_estimator(settings.method)
        return settings
    except (TypeError, ValueError) as e:
        msg = str(e).splitlines()[0]
        field_name, _, rest = msg.partition(" ")
        key = knobs.get(field_name)
        raise ConfigError(f"estimator.{key} {rest}" if key else f"estimator: {msg}") from None


# --- everything a job needs, checked ---------------------------------------------------------


@dataclass
class PreparedJob:
    cfg: ExperimentConfig
    estimator: EstimatorSettings
    objects: dict[str, ObjectDef]
    simulator: SimulatorSpec


def prepare_job(cfg: DictConfig) -> PreparedJob:
    """Typed config + validation + objects; raises `ConfigError`. Pure: it reads the job's
    config and its object files, and probes nothing outside (the database location and the Ray
    address are the job's to probe, once: `comexp.experiment.job.probe_resources`).

    Objects are looked up in the job's config sources: `cfg.hydra` in a callback's view of the
    config, `HydraConfig` inside the task function.
    """
    exp = to_experiment(cfg)
    est = validate(exp)
    sources = OmegaConf.select(cfg, "hydra.runtime.config_sources")
    if sources is None:
        sources = HydraConfig.get().runtime.config_sources
    try:
        objects = load_objects(exp.grid.objects, OmegaConf.to_container(sources, resolve=False))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    simulator = simulator_spec(exp.backend, exp.camera)
    return PreparedJob(cfg=exp, estimator=est, objects=objects, simulator=simulator)
