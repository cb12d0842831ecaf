"""Structured configuration of one experiment job, its validation, and object lookup.

The dataclasses below are the one place every default is written (push length, re-centring
distance, mass, camera rate, grid, workers, ...): conf/config.yaml holds only the group choices
and Hydra's own settings, and other modules derive their defaults from these classes
(tests/test_config.py checks README.md and docs/ against them).

The dataclasses below are registered in Hydra's ConfigStore as the schema of `conf/config.yaml`,
so a wrong *type* (``speed=abc``) is rejected by Hydra while composing. Wrong *values*
(negative speed, unknown object, ...) are caught by `prepare_job`, which the CLI runs before
Hydra creates any output folder (see `comexp.cli.run`): bad input must cost nothing and leave
nothing behind. Validation is pure: it imports neither the results store nor the workers, and
probes neither the database nor Ray (the command does, once: `comexp.cli.run.probe_resources`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf, open_dict

from comexp.experiment.objects import ObjectDef, load_objects
from comexp.experiment.registry import (
    ENGINES,
    FLOOR_FRICTION_CHOICES,
    RENDERER_CHOICES,
    backend_names,
    resolve_backend,
)
from comexp.method.estimator import EstimatorSettings

FLOOR_KINDS = ("iso", "aniso")
ANISO_ORIENTATIONS = ("xy", "yx")
SCHEMA_NAME = "comexp_schema"


class ConfigError(ValueError):
    """Bad user input; the message is one line that names the offending key."""


# --- schema -------------------------------------------------------------------------------


@dataclass
class BackendConfig:
    name: str = MISSING  # the `backend` group's option (default: conf/config.yaml's defaults list)
    # engines only: "model" = the shared footprint friction model applied as a force each step
    # (the engine's own object-floor friction off); "native" = the engine's own friction
    floor_friction: str = "model"

    def options(self) -> dict[str, str]:
        """The simulator's constructor options (`comexp.experiment.registry.make_simulator`)."""
        return {"floor_friction": self.floor_friction} if self.name in ENGINES else {}


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
    mass_kg: float = 0.2  # the object's mass (paper: 0.2 kg)


# A commodity depth camera (RealSense D4xx, Azure Kinect, ...) streams depth at up to 30 fps.
MAX_CAMERA_FPS = 30.0


@dataclass
class CameraConfig:
    """The depth camera. `fps`: tracking frames per second while the object moves during a
    push, so that the rotation is followed frame to frame (unwrapped); 0 = the images before
    and after each push only. The default is the lowest measured rate that unwraps every
    rotation of the study (docs/method.md, "Tracking during the push")."""

    fps: float = 30.0
    # how the engines make depth images: raycast (the exact ray cast of the prism at the
    # engine's pose, planar's camera) | engine (the engine's own renderer); docs/method.md
    renderer: str = "raycast"


@dataclass
class RayConfig:
    address: str | None = None  # None: start a local Ray; "auto" or host:port: join a cluster
    log_to_driver: bool = False  # worker stdout/stderr on the terminal (engines are chatty)


@dataclass
class ExecutionConfig:
    """How episodes are run."""

    batch_size: int = 8  # episodes per Ray task: ~0.5 ms overhead vs ~100 ms per episode
    max_retries: int = 2  # a batch whose worker dies is retried this often, then split
    restart_timeout_s: float = 60.0  # a replacement worker not up by then is dropped
    # An episode still running after this is failed with `failure="timeout"` and its worker
    # carries on (episodes take ~0.1-0.3 s; quasi-static ones a few s): catches hangs only.
    episode_timeout_s: float = 120.0


_EST = EstimatorSettings()  # the defaults are the settings' own: written once, there


@dataclass
class EstimatorConfig:
    """The `estimator` node: the knobs of `comexp.method.estimator.EstimatorSettings`, named
    on the command line as the paper names them (units dropped: deg, px). `SETTINGS_FIELDS`
    maps each onto its settings field (and database column); tests/test_config.py checks that
    every settings field has its knob here."""

    w: list[float] = field(default_factory=lambda: list(_EST.w))
    theta_T: float = _EST.theta_T_deg  # deg
    C_bw: float = _EST.C_bw_px  # px
    n_push: int = _EST.n_push
    rotation_source: str = _EST.rotation_source  # vision | oracle
    track_step: float = _EST.track_step_deg  # deg
    track_gap: float = _EST.track_gap_s  # s
    track_drive: float = _EST.track_drive_mm  # mm
    d_metric: str = _EST.d_metric
    d_signed: bool = _EST.d_signed
    cos_signed: bool = _EST.cos_signed
    band_signed: bool = _EST.band_signed
    contact_spacing: float = _EST.contact_spacing_px  # px
    check_reachability: bool = _EST.check_reachability
    method: str = _EST.method  # paper | magnitude | my_pkg.module:MyEstimator (a plug-in)
    mag_noise: float = _EST.mag_noise_deg  # deg
    mag_rel_noise: float = _EST.mag_rel_noise
    mag_floor_model: bool = _EST.mag_floor_model
    # motion: the model's revision in the episode key; "" = the grid pins the current one
    motion_version: str = _EST.motion_version


# config knob (`estimator.<knob>`) -> EstimatorSettings field: the one place the two names meet
SETTINGS_FIELDS: dict[str, str] = {
    "w": "w",
    "theta_T": "theta_T_deg",
    "C_bw": "C_bw_px",
    "n_push": "n_push",
    "rotation_source": "rotation_source",
    "track_step": "track_step_deg",
    "track_gap": "track_gap_s",
    "track_drive": "track_drive_mm",
    "d_metric": "d_metric",
    "d_signed": "d_signed",
    "cos_signed": "cos_signed",
    "band_signed": "band_signed",
    "contact_spacing": "contact_spacing_px",
    "check_reachability": "check_reachability",
    "method": "method",
    "mag_noise": "mag_noise_deg",
    "mag_rel_noise": "mag_rel_noise",
    "mag_floor_model": "mag_floor_model",
    "motion_version": "motion_version",
}
_CONFIG_NAMES = {name: knob for knob, name in SETTINGS_FIELDS.items()}


AUTO = "auto"
DEFAULT_LOCAL_WORKERS = 2


def check_workers(workers: Any) -> int | str | None:
    """`workers` as configured, checked: a count >= 1, `AUTO` or None; ValueError (one line)
    otherwise. A count given as text ("4", from a command line) becomes an int."""
    if workers is None:
        return None
    if isinstance(workers, str):
        text = workers.strip().lower()
        if text == AUTO:
            return AUTO
        if not text.isdigit():
            raise ValueError(f"workers must be a count >= 1 or auto, got {workers!r}")
        workers = int(text)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a count >= 1 or auto, got {workers!r}")
    return workers


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
    # a count, `auto` (every CPU of the Ray cluster, or of this machine for a local Ray), or
    # null: 2 on a local Ray, `auto` when the job joins a cluster (`ray.address` set)
    workers: Any = None
    ray: RayConfig = field(default_factory=RayConfig)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    db: str = "results/comexp.db"  # SQLAlchemy URL or file path (relative to the current dir)
    seed: int = 0


def simulator_options(cfg: Any) -> dict[str, str]:
    """The simulator's constructor options for a job (`make_simulator`, the workers' pool and
    the episodes' physics identity): the backend's own, and the engines' renderer."""
    opts = dict(cfg.backend.options())
    if cfg.backend.name in ENGINES:
        opts["renderer"] = cfg.camera.renderer
    return opts


def register_configs() -> None:
    """Register the schema; `conf/config.yaml` lists it first in its defaults."""
    cs = ConfigStore.instance()
    cs.store(name=SCHEMA_NAME, node=ExperimentConfig)


register_configs()


# --- conversion and validation ------------------------------------------------------------


def estimator_settings(est: Any) -> EstimatorSettings:
    """Map the `estimator` node onto `EstimatorSettings` (lists back to tuples)."""
    kwargs = {}
    for cfg_name, name in SETTINGS_FIELDS.items():
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
    if backend.name not in backend_names():
        if ":" not in backend.name:
            raise ConfigError(
                f"unknown backend {backend.name!r} (choose one of: {', '.join(backend_names())}"
                ", or a plug-in module:Class)"
            )
        try:  # a plug-in: importable, a Simulator, with its physics identity
            resolve_backend(backend.name)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    if backend.floor_friction not in FLOOR_FRICTION_CHOICES:
        raise ConfigError(
            f"backend.floor_friction must be one of {', '.join(FLOOR_FRICTION_CHOICES)}, "
            f"got {backend.floor_friction!r}"
        )
    if backend.name == "planar" and backend.floor_friction != "model":
        raise ConfigError("backend=planar is the friction model itself: floor_friction=model only")


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


def _validate_episode(ep: EpisodeConfig) -> None:
    if not _finite(ep.push_length_cm) or ep.push_length_cm <= 0:
        raise ConfigError(f"episode.push_length_cm must be > 0, got {ep.push_length_cm!r}")
    if not _finite(ep.mass_kg) or ep.mass_kg <= 0:
        raise ConfigError(f"episode.mass_kg must be > 0, got {ep.mass_kg!r}")
    if not _finite(ep.recenter_beyond_cm) or ep.recenter_beyond_cm < 0:
        msg = f"episode.recenter_beyond_cm must be >= 0 (0: never), got {ep.recenter_beyond_cm!r}"
        raise ConfigError(msg)


def _validate_camera(camera: CameraConfig) -> None:
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


def _validate_execution(ex: ExecutionConfig) -> None:
    if ex.batch_size < 1:
        raise ConfigError(f"execution.batch_size must be >= 1, got {ex.batch_size}")
    if not ex.restart_timeout_s > 0:
        raise ConfigError(f"execution.restart_timeout_s must be > 0, got {ex.restart_timeout_s}")
    if not (_finite(ex.episode_timeout_s) and ex.episode_timeout_s > 0):
        raise ConfigError(f"execution.episode_timeout_s must be > 0, got {ex.episode_timeout_s}")
    if ex.max_retries < 0:
        raise ConfigError(f"execution.max_retries must be >= 0, got {ex.max_retries}")


def _validate_estimator(est: Any) -> EstimatorSettings:
    """The estimator node through `EstimatorSettings`' own checks (the one set of rules), its
    message naming the config key (`theta_T_deg` -> `estimator.theta_T`)."""
    try:
        return estimator_settings(est)
    except (TypeError, ValueError) as e:
        msg = str(e).splitlines()[0]
        field_name, _, rest = msg.partition(" ")
        key = _CONFIG_NAMES.get(field_name)
        raise ConfigError(f"estimator.{key} {rest}" if key else f"estimator: {msg}") from None


# --- everything a job needs, checked ---------------------------------------------------------


@dataclass
class PreparedJob:
    cfg: ExperimentConfig
    estimator: EstimatorSettings
    objects: dict[str, ObjectDef]


def prepare_job(cfg: DictConfig) -> PreparedJob:
    """Typed config + validation + objects; raises `ConfigError`. Pure: it reads the job's
    config and its object files, and probes nothing outside (the database location and the Ray
    address are the command's to probe, once: `comexp.cli.run.probe_resources`).

    Objects are looked up in the job's config sources: `cfg.hydra` in a callback's view of the
    config, `HydraConfig` inside the task function.
    """
    exp = to_experiment(cfg)
    est = validate(exp)
    from comexp.experiment.platform import check_backend

    try:
        check_backend(exp.backend.name)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    sources = OmegaConf.select(cfg, "hydra.runtime.config_sources")
    if sources is None:
        from hydra.core.hydra_config import HydraConfig

        sources = HydraConfig.get().runtime.config_sources
    try:
        objects = load_objects(exp.grid.objects, OmegaConf.to_container(sources, resolve=False))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return PreparedJob(cfg=exp, estimator=est, objects=objects)
