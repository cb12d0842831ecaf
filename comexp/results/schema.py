"""The results schema: one row per episode, one per push, one per sweep (SQLAlchemy 2), and the
mapping of an `EpisodeResult` onto those rows. Column names are the public contract (README,
"Reading results"; docs/results.md).

A *sweep* row here is one run of the driver for one Hydra job (one `comexp` job: one backend,
floor and speed), not a Hydra sweep: a multirun (`comexp -m ...`) writes one sweep row per job.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from comexp.episode.task import EpisodeResult
from comexp.results.identity import canonical_json

# 2: episodes.worker, episodes.recenter_beyond_cm; 3: episodes.physics; 4: pushes.n_frames
SCHEMA_VERSION = 5


class Base(DeclarativeBase):
    pass


def utcnow() -> datetime:
    return datetime.now(UTC)


class Sweep(Base):
    """One run of the driver (one Hydra job): what was asked and with which software."""

    __tablename__ = "sweeps"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    command_line: Mapped[str] = mapped_column(Text, default="")
    config: Mapped[str] = mapped_column(Text, default="")  # full resolved YAML
    job_name: Mapped[str] = mapped_column(String(200), default="")
    versions: Mapped[dict] = mapped_column(JSON, default=dict)
    git_rev: Mapped[str | None] = mapped_column(String(64), nullable=True)
    host: Mapped[str] = mapped_column(String(200), default="")


class Episode(Base):
    """One CoM estimation. Column names are the public contract (README, "Reading results")."""

    __tablename__ = "episodes"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    sweep_id: Mapped[int | None] = mapped_column(ForeignKey("sweeps.id"), nullable=True)
    backend: Mapped[str] = mapped_column(String(32))
    floor: Mapped[str] = mapped_column(String(32))
    mu_floor_x: Mapped[float] = mapped_column(Float)
    mu_floor_y: Mapped[float] = mapped_column(Float)
    mu_pusher: Mapped[float] = mapped_column(Float)
    speed_cm_s: Mapped[float] = mapped_column(Float)
    izz_scale: Mapped[float] = mapped_column(Float)
    object: Mapped[str] = mapped_column(String(100))
    com_index: Mapped[int] = mapped_column(Integer)
    true_com_x_cm: Mapped[float] = mapped_column(Float)
    true_com_y_cm: Mapped[float] = mapped_column(Float)
    est_com_x_cm: Mapped[float | None] = mapped_column(Float, nullable=True)
    est_com_y_cm: Mapped[float | None] = mapped_column(Float, nullable=True)
    error_cm: Mapped[float | None] = mapped_column(Float, nullable=True)
    n_pushes: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16))  # ok | failed
    failure: Mapped[str | None] = mapped_column(String(64), nullable=True)
    wall_s: Mapped[float] = mapped_column(Float)
    # Contract columns come first (in the README's order), so `SELECT *` reads like the contract.
    episode_key: Mapped[str] = mapped_column(String(64), nullable=False)
    sim_time_s: Mapped[float] = mapped_column(Float, default=0.0)
    seed: Mapped[int] = mapped_column(Integer, default=0)
    mass_kg: Mapped[float] = mapped_column(Float)
    height_cm: Mapped[float] = mapped_column(Float)
    push_length_cm: Mapped[float] = mapped_column(Float)
    recenter_beyond_cm: Mapped[float | None] = mapped_column(Float, nullable=True)
    # what determined the physics (comexp.experiment.registry.physics_identity); part of the
    # episode key
    physics: Mapped[str] = mapped_column(String(200), default="")
    camera_fps: Mapped[float] = mapped_column(Float, default=0.0)  # tracking frames per second
    w1: Mapped[float | None] = mapped_column(Float, nullable=True)
    w2: Mapped[float | None] = mapped_column(Float, nullable=True)
    theta_T_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    C_bw_px: Mapped[float | None] = mapped_column(Float, nullable=True)
    n_push: Mapped[int | None] = mapped_column(Integer, nullable=True)
    rotation_source: Mapped[str | None] = mapped_column(String(32), nullable=True)
    # The whole estimator settings and spec, canonical JSON: fields added later are kept, and
    # `estimator` doubles as the grouping key for "same estimator variant" in the reports.
    estimator: Mapped[str] = mapped_column(Text)
    spec: Mapped[str] = mapped_column(Text)
    detail: Mapped[str] = mapped_column(Text, default="")
    worker: Mapped[str] = mapped_column(String(128), default="")  # node_ip:pid that ran it
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    __table_args__ = (
        UniqueConstraint("episode_key", name="uq_episodes_episode_key"),
        Index(
            "ix_episodes_condition",
            "backend",
            "floor",
            "speed_cm_s",
            "mu_floor_x",
            "mu_floor_y",
            "mu_pusher",
        ),
        Index("ix_episodes_object", "object", "com_index"),
        Index("ix_episodes_status", "status", "failure"),
        Index("ix_episodes_sweep", "sweep_id"),
    )


class Push(Base):
    """One push of an episode; contact and direction in the object frame at push time."""

    __tablename__ = "pushes"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    episode_id: Mapped[int] = mapped_column(ForeignKey("episodes.id", ondelete="CASCADE"))
    k: Mapped[int] = mapped_column(Integer)
    contact_x_cm: Mapped[float] = mapped_column(Float)
    contact_y_cm: Mapped[float] = mapped_column(Float)
    dir_x: Mapped[float] = mapped_column(Float)
    dir_y: Mapped[float] = mapped_column(Float)
    rotation_deg: Mapped[float] = mapped_column(Float)
    rotation_true_deg: Mapped[float] = mapped_column(Float)
    # ccw | cw | band, or ccw-empty | cw-empty | band-empty (that update would have emptied the
    # region, which was kept: estimator.update_region)
    decision: Mapped[str] = mapped_column(String(16))
    region_px: Mapped[int] = mapped_column(Integer)
    # tracking frames the measured rotation went through (0: the images before and after)
    n_frames: Mapped[int] = mapped_column(Integer, default=0)
    # the convex hull of the region the estimator kept after this push: JSON [[x_cm, y_cm],
    # ...], object frame; NULL from an estimator that shows no region, or an older comexp
    region_cm: Mapped[str | None] = mapped_column(Text, nullable=True)

    __table_args__ = (UniqueConstraint("episode_id", "k", name="uq_pushes_episode_k"),)


class Meta(Base):
    """Schema version, so that a later layout can migrate or refuse old files clearly."""

    __tablename__ = "comexp_meta"
    key: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[str] = mapped_column(Text)


EPISODES = Episode.__table__
PUSHES = Push.__table__
SWEEPS = Sweep.__table__
META = Meta.__table__


# --------------------------------------------------------------------------- rows
def episode_row(sweep_id: int | None, key: str, r: EpisodeResult) -> dict[str, Any]:
    s = r.spec
    est = s.estimator
    w = tuple(getattr(est, "w", ()) or ())
    est_com = r.est_com_cm
    return {
        "sweep_id": sweep_id,
        "episode_key": key,
        "backend": s.backend,
        "floor": s.floor,
        "mu_floor_x": float(s.mu_floor_x),
        "mu_floor_y": float(s.mu_floor_y),
        "mu_pusher": float(s.mu_pusher),
        "speed_cm_s": float(s.speed_cm_s),
        "izz_scale": float(s.izz_scale),
        "object": s.object,
        "com_index": int(s.com_index),
        "true_com_x_cm": float(s.com_cm[0]),
        "true_com_y_cm": float(s.com_cm[1]),
        "est_com_x_cm": None if est_com is None else float(est_com[0]),
        "est_com_y_cm": None if est_com is None else float(est_com[1]),
        "error_cm": None if r.error_cm is None else float(r.error_cm),
        "n_pushes": int(r.n_pushes),
        "status": r.status,
        "failure": r.failure,
        "wall_s": float(r.wall_s),
        "sim_time_s": float(r.sim_time_s),
        "seed": int(s.seed),
        "mass_kg": float(s.mass_kg),
        "height_cm": float(s.height_cm),
        "push_length_cm": float(s.push_length_cm),
        "recenter_beyond_cm": _opt_float(getattr(s, "recenter_beyond_cm", None)),
        "physics": getattr(s, "physics", "") or "",
        "camera_fps": float(getattr(s, "camera_fps", 0.0)),
        "w1": float(w[0]) if len(w) > 0 else None,
        "w2": float(w[1]) if len(w) > 1 else None,
        "theta_T_deg": _opt_float(getattr(est, "theta_T_deg", None)),
        "C_bw_px": _opt_float(getattr(est, "C_bw_px", None)),
        "n_push": None if getattr(est, "n_push", None) is None else int(est.n_push),
        "rotation_source": getattr(est, "rotation_source", None),
        "estimator": canonical_json(est),
        "spec": canonical_json(s),
        "detail": r.detail or "",
        "worker": getattr(r, "worker", "") or "",
        "created_at": utcnow(),
    }


def push_row(p: Any) -> dict[str, Any]:
    return {
        "k": int(p.k),
        "contact_x_cm": float(p.contact_x_cm),
        "contact_y_cm": float(p.contact_y_cm),
        "dir_x": float(p.dir_x),
        "dir_y": float(p.dir_y),
        "rotation_deg": float(p.rotation_deg),
        "rotation_true_deg": float(p.rotation_true_deg),
        "decision": p.decision,
        "region_px": int(p.region_px),
        "n_frames": int(getattr(p, "n_frames", 0)),
        "region_cm": None if p.region_cm is None else json.dumps([list(v) for v in p.region_cm]),
    }


def _opt_float(v: Any) -> float | None:
    return None if v is None else float(v)
