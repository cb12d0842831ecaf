"""One CoM estimation episode: scene + estimator settings + backend -> estimate and push records.

Everything an episode needs travels in `EpisodeSpec` (plain data, picklable for Ray): the
object's polygon is included so that workers never read config files.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class EstimatorSettings:
    w: tuple[float, float] = (1.0, 0.5)
    theta_T_deg: float = 1.0
    C_bw_px: float = 10.0
    n_push: int = 5
    rotation_source: str = "vision"  # vision | oracle


@dataclass(frozen=True)
class EpisodeSpec:
    backend: str
    floor: str  # iso | aniso (the config group name, for the database)
    mu_floor_x: float
    mu_floor_y: float
    mu_pusher: float
    speed_cm_s: float
    izz_scale: float
    object: str
    outline_cm: tuple[tuple[float, float], ...]  # footprint, object frame (origin at its centroid)
    height_cm: float
    com_index: int
    com_cm: tuple[float, float]  # true CoM, object frame
    mass_kg: float = 0.2
    push_length_cm: float = 3.0
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    seed: int = 0


@dataclass(frozen=True)
class PushRecord:
    k: int
    contact_x_cm: float  # object frame, at the time of the push
    contact_y_cm: float
    dir_x: float  # unit push direction, object frame
    dir_y: float
    rotation_deg: float  # measured (vision or oracle)
    rotation_true_deg: float
    decision: str  # ccw | cw | band
    region_px: int  # region size after the update


@dataclass(frozen=True)
class EpisodeResult:
    spec: EpisodeSpec
    status: str  # ok | failed
    failure: (
        str | None
    )  # tipped, left_view, no_valid_contact, sim_unstable, not_settled, timeout, error
    est_com_cm: tuple[float, float] | None
    error_cm: float | None
    n_pushes: int
    pushes: tuple[PushRecord, ...]
    wall_s: float
    sim_time_s: float = 0.0
    detail: str = ""
