"""Structured configuration of one experiment job, its validation, and object lookup.

The dataclasses below are registered in Hydra's ConfigStore as the schema of `conf/config.yaml`,
so a wrong *type* (``speed=abc``) is rejected by Hydra while composing. Wrong *values*
(negative speed, unknown object, unwritable database, ...) are caught by `prepare_job`, which
the CLI runs before Hydra creates any output folder (see `comexp.cli`): bad input must cost
nothing and leave nothing behind.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import socket
import tempfile
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf, open_dict

from comexp.episode import EstimatorSettings

FLOOR_KINDS = ("iso", "aniso")
ANISO_ORIENTATIONS = ("xy", "yx")
ROTATION_SOURCES = ("vision", "oracle")
OBJECT_GROUP = "object"
SCHEMA_NAME = "comexp_schema"


class ConfigError(ValueError):
    """Bad user input; the message is one line that names the offending key."""


# --- schema -------------------------------------------------------------------------------


@dataclass
class BackendConfig:
    name: str = "pybullet"  # planar | pybullet | mujoco
    # engines only: "model" = the shared footprint friction model applied as a force each step
    # (the engine's own object-floor friction off); "native" = the engine's own friction
    floor_friction: str = "model"

    def options(self) -> dict[str, str]:
        """The simulator's constructor options (`comexp.simulator.make_simulator`)."""
        return {} if self.name == "planar" else {"floor_friction": self.floor_friction}


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


@dataclass
class EpisodeConfig:
    """The push protocol of every episode (see docs/method.md, "Episode runner")."""

    push_length_cm: float = 3.0  # how far the pusher goes past the contact point (paper: 3 cm)
    recenter_beyond_cm: float = 10.0  # put the object back at the centre beyond this; 0: never


# A commodity depth camera (RealSense D4xx, Azure Kinect, ...) streams depth at up to 30 fps.
MAX_CAMERA_FPS = 30.0


@dataclass
class CameraConfig:
    """The depth camera. `fps`: tracking frames per second while the object moves during a
    push, so that the rotation is followed frame to frame (unwrapped); 0 = the images before
    and after each push only. The default is the lowest measured rate that unwraps every
    rotation of the study (docs/method.md, "Tracking during the push")."""

    fps: float = 10.0


@dataclass
class RayConfig:
    address: str | None = None  # None: start a local Ray; "auto" or host:port: join a cluster
    log_to_driver: bool = False  # worker stdout/stderr on the terminal (engines are chatty)


@dataclass
class ExecutionConfig:
    """How episodes are run; the dotted paths exist so tests can inject cheap fakes."""

    batch_size: int = 8  # episodes per Ray task: ~0.5 ms overhead vs ~100 ms per episode
    max_retries: int = 2  # a batch whose worker dies is retried this often, then split
    restart_timeout_s: float = 60.0  # a replacement worker not up by then is dropped
    # An episode still running after this is failed with `failure="timeout"` and its worker
    # carries on (episodes take ~0.1-0.3 s; quasi-static ones a few s): catches hangs only.
    episode_timeout_s: float = 120.0
    runner: str = "comexp.episode:run_episode"
    simulator_factory: str = "comexp.simulator:make_simulator"


_UNIT_SUFFIX = re.compile(r"_(deg|rad|px|cm|mm|m|s|ms|kg)$")


def _config_name(field_name: str) -> str:
    """`theta_T_deg` -> `theta_T`: the command line names estimator knobs as the paper does."""
    return _UNIT_SUFFIX.sub("", field_name)


def _config_type(tp: Any) -> Any:
    """OmegaConf has no tuples: a tuple field becomes a list of its element type."""
    if typing.get_origin(tp) is tuple:
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return list[args[0]] if args else list[Any]
    if typing.get_origin(tp) is typing.Literal:
        return str
    return tp


def _estimator_fields() -> list[tuple[str, str, Any, Any]]:
    """(config name, settings field name, config type, dataclasses.field) for every field of
    `EstimatorSettings`, so knobs added there appear on the command line without edits here."""
    hints = typing.get_type_hints(EstimatorSettings)
    names = [f.name for f in dataclasses.fields(EstimatorSettings)]
    short = [_config_name(n) for n in names]
    out = []
    for f, name, cfg_name in zip(dataclasses.fields(EstimatorSettings), names, short, strict=True):
        if short.count(cfg_name) > 1 or cfg_name in names and cfg_name != name:
            cfg_name = name  # stripping the unit would collide: keep the full name
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"EstimatorSettings.{name} needs a default to be configurable")
        if isinstance(default, tuple):
            default = list(default)
        if isinstance(default, list):
            spec = field(default_factory=lambda d=default: list(d))
        else:
            spec = field(default=default)
        out.append((cfg_name, name, _config_type(hints[name]), spec))
    return out


_ESTIMATOR_FIELDS = _estimator_fields()

EstimatorConfig = dataclasses.make_dataclass(
    "EstimatorConfig",
    [(cfg_name, tp, spec) for cfg_name, _, tp, spec in _ESTIMATOR_FIELDS],
)
EstimatorConfig.__doc__ = (
    "Estimator knobs, named as in the paper (units stripped): mapped field by field onto "
    "`comexp.episode.EstimatorSettings`."
)


@dataclass
class ExperimentConfig:
    """One Hydra job = one (backend, floor, speed); the grid fans out over the rest."""

    backend: BackendConfig = MISSING
    floor: FloorConfig = MISSING
    speed: float = 40.0  # cm/s
    pusher: PusherConfig = field(default_factory=PusherConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    workers: int = 2
    ray: RayConfig = field(default_factory=RayConfig)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    db: str = "results/comexp.db"  # SQLAlchemy URL or file path (relative to the current dir)
    seed: int = 0


def register_configs() -> None:
    """Register the schema; `conf/config.yaml` lists it first in its defaults."""
    cs = ConfigStore.instance()
    cs.store(name=SCHEMA_NAME, node=ExperimentConfig)


register_configs()


# --- conversion and validation ------------------------------------------------------------


def estimator_settings(est: Any) -> EstimatorSettings:
    """Map the `estimator` node onto `EstimatorSettings` (lists back to tuples)."""
    kwargs = {}
    for cfg_name, name, _, _ in _ESTIMATOR_FIELDS:
        value = getattr(est, cfg_name) if not isinstance(est, Mapping) else est[cfg_name]
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value)
        if isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
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
    """Value checks that a schema cannot express; returns the estimator settings."""
    from comexp.simulator import backend_names

    if cfg.backend.name not in backend_names():
        raise ConfigError(
            f"unknown backend {cfg.backend.name!r} (choose one of: {', '.join(backend_names())})"
        )
    from comexp.simulator import FLOOR_FRICTION_CHOICES

    if cfg.backend.floor_friction not in FLOOR_FRICTION_CHOICES:
        raise ConfigError(
            f"backend.floor_friction must be one of {', '.join(FLOOR_FRICTION_CHOICES)}, "
            f"got {cfg.backend.floor_friction!r}"
        )
    if cfg.backend.name == "planar" and cfg.backend.floor_friction != "model":
        raise ConfigError("backend=planar is the friction model itself: floor_friction=model only")
    fl = cfg.floor
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
    if not _finite(cfg.speed) or cfg.speed <= 0:
        raise ConfigError(f"speed must be a positive number of cm/s, got {cfg.speed!r}")
    _check_list("pusher.mu", cfg.pusher.mu, minimum=0.0, strict=False)
    g = cfg.grid
    if g.coms_per_object < 1:
        raise ConfigError(f"grid.coms_per_object must be >= 1, got {g.coms_per_object}")
    _check_list("grid.izz_scales", g.izz_scales, minimum=0.0, strict=True)
    if not _finite(g.com_margin_cm) or g.com_margin_cm < 0:
        raise ConfigError(f"grid.com_margin_cm must be >= 0, got {g.com_margin_cm!r}")
    ep = cfg.episode
    if not _finite(ep.push_length_cm) or ep.push_length_cm <= 0:
        raise ConfigError(f"episode.push_length_cm must be > 0, got {ep.push_length_cm!r}")
    if not _finite(ep.recenter_beyond_cm) or ep.recenter_beyond_cm < 0:
        msg = f"episode.recenter_beyond_cm must be >= 0 (0: never), got {ep.recenter_beyond_cm!r}"
        raise ConfigError(msg)
    fps = cfg.camera.fps
    if not _finite(fps) or not 0 <= fps <= MAX_CAMERA_FPS:
        raise ConfigError(
            f"camera.fps must be between 0 (before and after only) and {MAX_CAMERA_FPS:g} "
            f"(a commodity depth camera), got {fps!r}"
        )
    if g.objects is not None:
        if not g.objects:
            raise ConfigError("grid.objects must not be empty (omit it to use every object)")
        if len(set(g.objects)) != len(g.objects):
            raise ConfigError(f"grid.objects has duplicates: {list(g.objects)}")
    if cfg.workers < 1:
        raise ConfigError(f"workers must be >= 1, got {cfg.workers}")
    if cfg.execution.batch_size < 1:
        raise ConfigError(f"execution.batch_size must be >= 1, got {cfg.execution.batch_size}")
    if not cfg.execution.restart_timeout_s > 0:
        raise ConfigError(
            f"execution.restart_timeout_s must be > 0, got {cfg.execution.restart_timeout_s}"
        )
    if not (_finite(cfg.execution.episode_timeout_s) and cfg.execution.episode_timeout_s > 0):
        raise ConfigError(
            f"execution.episode_timeout_s must be > 0, got {cfg.execution.episode_timeout_s}"
        )
    if cfg.execution.max_retries < 0:
        raise ConfigError(f"execution.max_retries must be >= 0, got {cfg.execution.max_retries}")
    if cfg.seed < 0:
        raise ConfigError(f"seed must be >= 0, got {cfg.seed}")
    if not cfg.db.strip():
        raise ConfigError("db must be a database URL or a file path")
    return _validate_estimator(cfg.estimator)


def _validate_estimator(est: Any) -> EstimatorSettings:
    known = {f.name for f in dataclasses.fields(est)}
    if "w" in known and (len(est.w) != 2 or not all(_finite(v) for v in est.w)):
        raise ConfigError(f"estimator.w must be two finite numbers, got {list(est.w)}")
    for key in ("theta_T", "C_bw"):
        if key in known and (not _finite(getattr(est, key)) or getattr(est, key) < 0):
            raise ConfigError(f"estimator.{key} must be >= 0, got {getattr(est, key)!r}")
    if "n_push" in known and est.n_push < 1:
        raise ConfigError(f"estimator.n_push must be >= 1, got {est.n_push}")
    if "rotation_source" in known and est.rotation_source not in ROTATION_SOURCES:
        raise ConfigError(
            f"estimator.rotation_source must be one of {', '.join(ROTATION_SOURCES)}, "
            f"got {est.rotation_source!r}"
        )
    try:
        return estimator_settings(est)
    except (TypeError, ValueError) as e:  # the settings' own checks, if any
        msg = str(e).splitlines()[0]
        for cfg_name, name, _, _ in _ESTIMATOR_FIELDS:  # name the knob as the command line does
            if msg.startswith(name + " "):
                raise ConfigError(f"estimator.{cfg_name}{msg[len(name) :]}") from None
        raise ConfigError(f"estimator: {msg}") from None


# --- database location ---------------------------------------------------------------------


def sqlite_path(db: str) -> Path | None:
    """The file behind `db` when it is SQLite (plain path or sqlite:/// URL); None otherwise
    (another SQLAlchemy URL, or SQLite in memory)."""
    if "://" not in db:
        return Path(db).expanduser()
    scheme, _, rest = db.partition("://")
    if not scheme.startswith("sqlite"):
        return None
    rest = rest.split("?", 1)[0]
    if rest in ("", "/", "/:memory:") or rest.startswith("/file:"):
        return None
    return Path(rest[1:]).expanduser() if rest.startswith("/") else Path(rest)


def check_db_location(db: str) -> None:
    """Fail early, leaving nothing behind, when an SQLite file could not be created or written.

    Probes for real (permission bits lie for root and on read-only mounts): an existing file
    is opened for update, otherwise a temporary file is created in the nearest existing parent.
    """
    path = sqlite_path(db)
    if path is None:
        return
    if path.is_dir():
        raise ConfigError(f"db: {str(path)!r} is a directory, not a database file")
    if path.exists():
        try:
            with open(path, "r+b") as f:
                head = f.read(16)
        except OSError as e:
            raise ConfigError(f"db: cannot write to {str(path)!r}: {e.strerror}") from None
        if head and head != b"SQLite format 3\x00":
            raise ConfigError(f"db: {str(path)!r} exists and is not an SQLite database")
        return
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"db: cannot create {str(path)!r}: {str(parent)!r} is not a directory")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise ConfigError(
            f"db: cannot create {str(path)!r}: {str(parent)!r} is not writable ({e.strerror})"
        ) from None


RAY_CONNECT_TIMEOUT_S = 5.0


def parse_ray_address(address: str) -> tuple[str, int]:
    """HOST:PORT (a cluster's GCS address, `[v6addr]:PORT` too) as (host, port), or
    `ConfigError`. Ray Client addresses (`ray://`) would need `ray[client]` (grpcio), which is
    not a dependency: comexp joins clusters as a node instead (workers/pool.py `JoinNode`)."""
    if "://" in address:
        raise ConfigError(
            f"ray.address: {address!r}: Ray Client (ray://) is not supported; "
            "give the cluster's HOST:PORT (the head's --port, 6379 by default)"
        )
    host, sep, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"ray.address: expected null, auto or HOST:PORT, got {address!r}")
    return host, int(port)


def check_ray_address(address: str | None, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Fail within `timeout_s`, before anything is written, when no server listens at a
    HOST:PORT `ray.address`. Left to itself Ray retries an unreachable address for minutes,
    printing GCS warnings. (`auto` names the local node, which Ray finds or fails on at once.)
    """
    if address is None or address == "auto":
        return
    host, port = parse_ray_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except socket.gaierror as e:
        raise ConfigError(f"ray.address: cannot resolve host {host!r} ({e.strerror})") from None
    except TimeoutError:
        raise ConfigError(
            f"ray.address: no answer from {address} within {timeout_s:g} s (is the Ray head up?)"
        ) from None
    except OSError as e:
        reason = e.strerror or type(e).__name__
        raise ConfigError(
            f"ray.address: cannot reach {address}: {reason} (is the Ray head up?)"
        ) from None


# --- objects from every config source -------------------------------------------------------


def config_repository(sources: Sequence[Mapping[str, Any]]) -> Any:
    """A Hydra config repository over the job's search path (`hydra.runtime.config_sources`):
    the package's `conf/`, `--config-dir`, `hydra.searchpath` entries and the ConfigStore."""
    from hydra._internal.config_repository import ConfigRepository
    from hydra._internal.config_search_path_impl import ConfigSearchPathImpl

    csp = ConfigSearchPathImpl()
    for s in sources:
        csp.append(provider=str(s["provider"]), path=f"{s['schema']}://{s['path']}")
    return ConfigRepository(csp)


def available_objects(repo: Any) -> list[str]:
    return list(repo.get_group_options(OBJECT_GROUP))


def yaml_error_line(e: yaml.YAMLError) -> str:
    """`malformed YAML in FILE, line L, column C: problem (context at line, column)`: PyYAML's
    multi-line message in one line, positions 1-based as editors count them."""
    if not isinstance(e, yaml.MarkedYAMLError) or e.problem_mark is None:
        text = [t.strip() for t in str(e).splitlines() if t.strip()]
        return f"malformed YAML: {' '.join(text[:2]) or type(e).__name__}"
    mark = e.problem_mark
    out = f"malformed YAML in {mark.name}, line {mark.line + 1}, column {mark.column + 1}: "
    out += e.problem or "syntax error"
    ctx = e.context_mark
    if e.context and ctx is not None:
        where = f"line {ctx.line + 1}, column {ctx.column + 1}"
        out += f" ({e.context} at {where})" if ctx.name == mark.name else f" ({e.context})"
    return out


def load_object_mapping(repo: Any, name: str) -> dict[str, Any]:
    """Raw mapping of `object/<name>` from the first source that has it."""
    try:
        res = repo.load_config(f"{OBJECT_GROUP}/{name}")
    except yaml.YAMLError as e:  # Hydra's config sources pass PyYAML's errors through
        raise ConfigError(f"object {name!r}: {yaml_error_line(e)}") from None
    if res is None:
        raise ConfigError(f"unknown object {name!r}")
    node = res.config
    if OmegaConf.is_config(node) and "defaults" in node:
        node = OmegaConf.masked_copy(node, [k for k in node if k != "defaults"])
    data = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    if not isinstance(data, dict):
        raise ConfigError(f"object {name!r}: config must be a mapping")
    return data


def load_objects(repo: Any, names: Sequence[str] | None) -> dict[str, Any]:
    """`comexp.objects.ObjectDef` per name (all objects in the group when `names` is None)."""
    from comexp.objects import ObjectDef

    available = available_objects(repo)
    if names is None:
        if not available:
            raise ConfigError("no objects found in the config group 'object'")
        names = available
    missing = [n for n in names if n not in available]
    if missing:
        shown = ", ".join(available[:30]) + (" ..." if len(available) > 30 else "")
        raise ConfigError(f"unknown object {missing[0]!r} (available: {shown or 'none'})")
    out = {}
    for n in names:
        try:
            obj = ObjectDef.from_mapping(load_object_mapping(repo, n), default_name=n)
        except ConfigError:
            raise
        except (TypeError, ValueError, KeyError) as e:
            msg = str(e).splitlines()[0]
            raise ConfigError(
                msg if msg.startswith("object ") else f"object {n!r}: {msg}"
            ) from None
        if obj.name != n:
            # users select objects by file name: a different `name` inside would be ambiguous
            raise ConfigError(f"object {n!r}: its config says name {obj.name!r}")
        out[n] = obj
    return out


# --- everything a job needs, checked ---------------------------------------------------------


@dataclass
class PreparedJob:
    cfg: ExperimentConfig
    estimator: EstimatorSettings
    objects: dict[str, Any]


def prepare_job(cfg: DictConfig) -> PreparedJob:
    """Typed config + validation + objects + database location + a reachable Ray address;
    raises `ConfigError`.

    Objects are looked up in the job's config sources: `cfg.hydra` in a callback's view of the
    config, `HydraConfig` inside the task function.
    """
    exp = to_experiment(cfg)
    est = validate(exp)
    sources = OmegaConf.select(cfg, "hydra.runtime.config_sources")
    if sources is None:
        from hydra.core.hydra_config import HydraConfig

        sources = HydraConfig.get().runtime.config_sources
    repo = config_repository(OmegaConf.to_container(sources, resolve=False))
    objects = load_objects(repo, exp.grid.objects)
    check_db_location(exp.db)
    check_ray_address(exp.ray.address)
    return PreparedJob(cfg=exp, estimator=est, objects=objects)
