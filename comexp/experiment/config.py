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
import re
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


def knob(default: Any = MISSING, help: str = "", **kw: Any) -> Any:  # noqa: A002 - the key's help
    """A config key: its default and what it means (`help`: the one description of the key,
    which `comexp-db knobs` and docs/operations.md's table show)."""
    if callable(default):
        return field(default_factory=default, metadata={"help": help}, **kw)
    return field(default=default, metadata={"help": help}, **kw)


@dataclass
class BackendConfig:
    """The `backend` group's option (conf/backend/NAME.yaml; default: conf/config.yaml's
    defaults list)."""

    name: str = knob(help="the backend's name in the database and the reports")
    _target_: str = knob(help="its simulator class, module.Class (a Simulator subclass)")
    engine: bool = knob(
        False, "a 3-D engine: takes backend.floor_friction and draws with camera.renderer"
    )
    floor_friction: str = knob(
        "model",
        "engines: model (the shared footprint friction applied each step, the engine's own "
        "floor friction off) | native (the engine's own contact friction)",
    )
    linux_only: str | None = knob(
        None, "what only Linux has, when the backend needs it (refused elsewhere in one line)"
    )
    options: dict[str, Any] = knob(
        dict, "the simulator class's own keyword arguments (part of its physics identity)"
    )


@dataclass
class FloorConfig:
    """`floor=iso`: each value of `mu` is one floor, mu_x = mu_y = value.

    `floor=aniso`: `mu` = [mu_a, mu_b], the coefficients along the floor's two principal axes;
    each entry of `orientations` is one floor: ``xy`` gives (mu_x, mu_y) = (mu_a, mu_b) and
    ``yx`` the swapped one. Both orientations run by default (``floor.orientations=[xy]``
    runs one).
    """

    name: str = knob(help="iso | aniso (the floor group's option)")
    mu: list[float] = knob(
        help="iso: one floor per value; aniso: [mu_a, mu_b] along the floor's two axes"
    )
    orientations: list[str] | None = knob(
        None, "aniso: xy -> (mu_x, mu_y) = (mu_a, mu_b), yx -> swapped; one floor each"
    )


@dataclass
class PusherConfig:
    mu: list[float] = knob(lambda: [0.1, 1.0], "pusher-object friction, one condition per value")


@dataclass
class GridConfig:
    objects: list[str] | None = knob(
        None, "object names (object/NAME.yaml); null: every object of the object group"
    )
    coms_per_object: int = knob(10, "CoMs per object, the same ones for every condition")
    izz_scales: list[float] = knob(
        lambda: [1.0, 10.0], "Izz multipliers of the uniform-density value, one per condition"
    )
    com_margin_cm: float = knob(1.0, "sampled CoMs keep this distance (cm) from the outline")


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
            spec = field(default_factory=lambda d=default: list(d), metadata=f.metadata)
        else:
            spec = field(default=default, metadata=f.metadata)
        fields.append((_knob(f), _NODE_TYPES[str(f.type)], spec))
    return dataclasses.make_dataclass("EstimatorConfig", fields)


EstimatorConfig = _estimator_node()


RETRY_CHOICES = ("failed",)


@dataclass
class ExperimentConfig:
    """One Hydra job = one (backend, floor, speed); the grid fans out over the rest."""

    backend: BackendConfig = MISSING
    floor: FloorConfig = MISSING
    speed: float = knob(40.0, "push speed, cm/s (the paper: 40 dynamic, 4 quasi-static)")
    pusher: PusherConfig = field(default_factory=PusherConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    episode: EpisodeSettings = field(default_factory=EpisodeSettings)
    estimator: Any = field(default_factory=EstimatorConfig)
    camera: CameraSettings = field(default_factory=CameraSettings)
    workers: Any = knob(
        None,
        "workers (one CPU each): a count, auto (every CPU of the Ray cluster, or of this "
        "machine) or null (2 on a local Ray, auto on a cluster)",
    )
    ray: RaySettings = field(default_factory=RaySettings)
    execution: PoolSettings = field(default_factory=PoolSettings)
    db: str = knob(
        "results/comexp.db", "the results database: SQLAlchemy URL or file path (from cwd)"
    )
    seed: int = knob(0, "fixes every random choice: CoMs, initial yaws")
    retry: str | None = knob(
        None, "failed: rerun the job's stored failed episodes, each replaced by its new result"
    )


@dataclass(frozen=True)
class ConfigKey:
    """One key of the job's config, as `comexp --cfg job` prints it."""

    key: str  # dotted, e.g. grid.coms_per_object
    default: Any  # MISSING for a group's own keys (backend.*, floor.*: set by the option)
    help: str


def config_keys(node: type = ExperimentConfig, prefix: str = "") -> list[ConfigKey]:
    """Every key of the schema, in `--cfg job` order, with its default and meaning: the one
    source of the knob table (docs/operations.md, `bench/docs_tables.py knobs`)."""
    out = []
    for f in dataclasses.fields(node):
        key = f"{prefix}{f.name}"
        factory = f.default_factory
        sub = f.type if dataclasses.is_dataclass(f.type) else None
        if sub is None and factory is not dataclasses.MISSING and dataclasses.is_dataclass(factory):
            sub = factory
        if sub is None and isinstance(f.type, str) and f.type in _SCHEMA_NODES:
            sub = _SCHEMA_NODES[f.type]
        if sub is not None:
            out += config_keys(sub, f"{key}.")
            continue
        default = f.default if factory is dataclasses.MISSING else factory()
        out.append(ConfigKey(key, default, f.metadata.get("help", "")))
    return out


def register_configs() -> None:
    """Register the schema; `conf/config.yaml` lists it first in its defaults."""
    cs = ConfigStore.instance()
    cs.store(name=SCHEMA_NAME, node=ExperimentConfig)


register_configs()

# the schema's nested nodes by their annotation (the module's annotations are strings)
_SCHEMA_NODES: dict[str, type] = {
    c.__name__: c
    for c in (BackendConfig, FloorConfig, PusherConfig, GridConfig, EpisodeSettings)
    + (CameraSettings, RaySettings, PoolSettings)
}


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
    """A simulator of the built-in backend `name` as a job's workers build it with the default
    camera (`simulator_spec`), `options` over its own (an engine's `floor_friction`,
    `renderer`): tests, bench, `comexp-real replay`."""
    spec = simulator_spec(load_backend(name), CameraSettings())
    return SimulatorSpec(name, spec.target, {**spec.options, **options}).make(settings)


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
            return f"{key}: {_in_user_words(str(key), str(msg).splitlines()[0])}"
    text = [t.strip() for t in str(e).splitlines() if t.strip()]
    if cause is not None and (not text or text[-1].endswith(":")):
        text += [t.strip() for t in str(cause).splitlines() if t.strip()][:1]
    return " ".join(text[:2]) if text else type(e).__name__


_KINDS = {"Float": "a number", "Integer": "a whole number", "Boolean": "true or false"}


def _in_user_words(key: str, msg: str) -> str:
    """OmegaConf's message about the key the user typed, in the user's words."""
    unknown = re.match(r"Key '([^']+)' not in '(\w+)'", msg)
    if unknown:
        return f"no such key; {_siblings(key)}"
    if "is not a ListConfig" in msg:
        return f"expects a list, e.g. {key}=[a,b]"
    if "is not a DictConfig" in msg or "is not a dict" in msg:
        return "expects a mapping of keys, not a value"
    convert = re.match(r"Value '(.*)' of type '\w+' could not be converted to (\w+)", msg)
    if convert:
        kind = _KINDS.get(convert[2], convert[2].lower())
        return f"expects {kind}, got {convert[1]!r}"
    return msg


def _siblings(key: str) -> str:
    """The keys beside `key` (e.g. grid.objectz: grid's keys), to say what is there."""
    parent = key.rpartition(".")[0]
    names = sorted(
        {
            k.key[len(parent) + 1 :].split(".")[0] if parent else k.key.split(".")[0]
            for k in config_keys()
            if not parent or k.key.startswith(parent + ".")
        }
    )
    return f"{parent or 'the config'} has: {', '.join(names)}"


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
    extra = sorted(set(job) - {f.name for f in dataclasses.fields(ExperimentConfig)})
    if extra:  # `+key=value` adds a key the schema does not have: nothing would read it
        raise ConfigError(f"{extra[0]}: no such key; {_siblings(extra[0])}")
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
    if cfg.retry is not None and cfg.retry not in RETRY_CHOICES:
        raise ConfigError(
            f"retry must be {' or '.join(RETRY_CHOICES)} (or unset), got {cfg.retry!r}"
        )
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
