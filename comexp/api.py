"""The notebook API: `run` (a job, as the command line runs it), `load_results` (pandas) and
`replay`.

    import comexp
    df = comexp.run(["backend=planar", "grid.objects=[l_shape]"])  # this job's episodes
    df = comexp.load_results("results/comexp.db")            # one row per episode
    result = comexp.replay("results/comexp.db", episode_id=12)  # run it again, in-process

`run` is the job service (`comexp.experiment.job.run_job`) in this process, on the config
Hydra's compose API makes of the overrides: the same grid, database, workers and reports as
`comexp OVERRIDES`. Its Ray session and workers stay up for the next call of this process
(a second job on the same backend starts no worker), and end with the process.
`load_results` adds a `condition` column (the label of `comexp.results.reports.group_episodes`'s
grouping rule), so a notebook groups exactly as the tables and plots do.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shlex
import sys
from collections.abc import Iterator, Sequence
from typing import Any

import pandas as pd
import yaml
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException
from sqlalchemy import select

from comexp.backends.physics_settings import (
    FLOOR_FRICTION_CHOICES,
    RENDERER_CHOICES,
    physics_identity,
)
from comexp.episode.loop import run_episode
from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.experiment.config import (
    BackendConfig,
    ConfigError,
    hydra_error_line,
    load_backend,
    prepare_job,
)
from comexp.experiment.job import job_config_yaml, probe_resources, run_job
from comexp.results.identity import spec_from_json
from comexp.results.reports import condition_of
from comexp.results.schema import EPISODES, PUSHES, SWEEPS
from comexp.results.store import ResultsDB
from comexp.sim.simulator import SimulatorSpec
from comexp.workers.pool import PoolError
from comexp.workers.session import SessionError

TABLES = {"episodes": EPISODES, "pushes": PUSHES, "sweeps": SWEEPS}
DbLike = ResultsDB | str | os.PathLike[str]


def _open(db: DbLike) -> tuple[ResultsDB, bool]:
    if isinstance(db, ResultsDB):
        return db, False
    return ResultsDB(db, readonly=True), True


def load_results(db: DbLike, table: str = "episodes") -> pd.DataFrame:
    """One stored table as a pandas DataFrame (read-only). `episodes` gets two more columns:
    `condition` (the grouping rule's label) and `condition_slug` (its short unique name)."""
    if table not in TABLES:
        raise ValueError(f"unknown table {table!r}; choose one of {', '.join(TABLES)}")
    handle, owned = _open(db)
    try:
        t = TABLES[table]
        with handle.engine.connect() as conn:
            rows = [dict(m) for m in conn.execute(select(t).order_by(t.c.id)).mappings()]
    finally:
        if owned:
            handle.close()
    return _frame(rows, table)


def _frame(rows: list[dict[str, Any]], table: str = "episodes") -> pd.DataFrame:
    t = TABLES[table]
    df = pd.DataFrame(rows, columns=[c.name for c in t.c])
    if table == "episodes":
        conds = [condition_of(r) for r in rows]
        df["condition"] = pd.Series([c.label() for c in conds], index=df.index, dtype=object)
        df["condition_slug"] = pd.Series([c.slug() for c in conds], index=df.index, dtype=object)
    return df


# --------------------------------------------------------------------------- run
def run(
    overrides: Sequence[str] = (), *, config_dir: str | os.PathLike[str] | None = None
) -> pd.DataFrame:
    """Run one job, as `comexp OVERRIDES...` does, and return its episodes as the DataFrame
    `load_results` gives (this job's grid only, whoever stored them: a rerun returns the
    stored rows without running anything again).

    The job runs in this process (its Ray session and workers stay up for the next call);
    its log lines and progress bar go to `sys.stderr` (a notebook's cell output), its
    summary lines to `sys.stdout`, its reports to `results/runs/` as the command's do.
    `config_dir` is `--config-dir` (your own objects: DIR/object/NAME.yaml, backends,
    estimators). Bad input raises ValueError with the command line's one-line message and
    writes nothing; workers that cannot start raise RuntimeError. One job per call: call it
    once per job of a sweep.
    """
    args = _checked_overrides(overrides)
    cfg = _compose(args, config_dir)
    try:
        job = prepare_job(cfg)
        probe_resources(job.cfg)
    except ConfigError as e:
        raise ValueError(str(e)) from None
    extra = ["--config-dir", os.fspath(config_dir)] if config_dir is not None else []
    try:
        with _job_logging():
            result = run_job(
                job,
                output_dir=str(OmegaConf.select(cfg, "hydra.run.dir")),
                command_line=shlex.join(["comexp", *extra, *args]),
                config_yaml=job_config_yaml(cfg),
                progress_bar=True,
            )
    except ConfigError as e:
        raise ValueError(str(e)) from None
    except (PoolError, SessionError) as e:
        raise RuntimeError(str(e)) from None
    with ResultsDB(job.cfg.db, readonly=True) as handle:
        return _frame(handle.episodes_by_keys(result.keys))


def _checked_overrides(overrides: Sequence[str]) -> list[str]:
    """The overrides of one job, as strings; ValueError for flags and sweeps."""
    if isinstance(overrides, str):
        raise TypeError("overrides: a list of strings, e.g. ['backend=planar', 'speed=4']")
    args = [str(a) for a in overrides]
    if any(a.startswith("-") for a in args):
        raise ValueError(f"comexp.run takes overrides only (one job per call), got {args}")
    try:
        parsed = OverridesParser.create().parse_overrides(args)
    except HydraException as e:
        raise ValueError(hydra_error_line(e)) from None
    sweeps = [o.input_line for o in parsed if o.is_sweep_override()]
    if sweeps:
        raise ValueError(f"comexp.run runs one job; call it once per value of: {sweeps}")
    return args


def _compose(args: list[str], config_dir: str | os.PathLike[str] | None) -> Any:
    """The job's config as the command composes it: the packaged config, the user's config
    directory first (`hydra.searchpath`), the overrides; Hydra's node included (the config
    sources, the output folder)."""
    search: list[str] = []
    if config_dir is not None:
        path = os.path.abspath(config_dir)
        if not os.path.isdir(path):
            raise ValueError(f"config_dir {path!r} not found")
        search = [f"hydra.searchpath=[file://{path}]"]
    try:
        with initialize_config_module("comexp.conf", version_base="1.3"):
            cfg = compose("config", overrides=[*args, *search], return_hydra_config=True)
        OmegaConf.resolve(cfg.hydra.run)  # the output folder's ${now:...} once, now
    except (HydraException, OmegaConfBaseException, yaml.YAMLError) as e:
        raise ValueError(hydra_error_line(e)) from None
    return cfg


@contextlib.contextmanager
def _job_logging() -> Iterator[None]:
    """The job's INFO lines on `sys.stderr` while it runs, as the command shows them, unless
    the caller's logging already shows them on a console stream."""
    logger = logging.getLogger("comexp")
    consoles = (sys.stderr, sys.stdout, sys.__stderr__, sys.__stdout__)
    shown = [
        h
        for h in (*logging.getLogger().handlers, *logger.handlers)
        if isinstance(h, logging.StreamHandler) and h.stream in consoles
    ]
    if shown:
        yield
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


# --------------------------------------------------------------------------- replay
def stored_spec(db: DbLike, episode_id: int) -> tuple[EpisodeSpec, dict[str, Any]]:
    """A stored episode's spec (as it ran) and its row."""
    handle, owned = _open(db)
    try:
        row = handle.episode(int(episode_id))
    finally:
        if owned:
            handle.close()
    return spec_from_json(row["spec"]), row


def stored_backend(db: DbLike, row: dict[str, Any]) -> BackendConfig:
    """The `backend` node an episode ran with: its sweep's resolved config, else (older
    sweeps, without the backend's `_target_`) the package's own backend of that name."""
    handle, owned = _open(db)
    try:
        sweep = handle.sweep(row["sweep_id"]) if row.get("sweep_id") is not None else None
    finally:
        if owned:
            handle.close()
    node = (yaml.safe_load(sweep["config"] or "") or {}).get("backend") if sweep else None
    if isinstance(node, dict) and node.get("_target_"):
        merged = OmegaConf.merge(OmegaConf.structured(BackendConfig), node)
        return OmegaConf.to_object(merged)  # type: ignore[return-value]
    return load_backend(row["backend"])


def backend_options_for(spec: EpisodeSpec, backend: BackendConfig) -> dict[str, Any]:
    """The backend options (`backend.floor_friction`, `camera.renderer`) that gave a stored
    episode its physics: the ones whose `physics_identity` is the spec's. The identity keeps
    only a hash of the options, so each choice is tried. An episode stored without a pinned
    physics runs with the defaults."""
    choices: list[dict[str, str]] = [{}]
    if backend.engine:
        choices = [
            {"floor_friction": f, "renderer": r}
            for r in RENDERER_CHOICES
            for f in FLOOR_FRICTION_CHOICES
        ]
    if not spec.physics:
        return choices[0]
    target = backend._target_
    for options in choices:
        if physics_identity(spec.backend, target, options=options) == spec.physics:
            return options
    mine = ", ".join(physics_identity(spec.backend, target, options=o) for o in choices)
    raise ValueError(
        f"the episode ran with physics {spec.physics}; this comexp's {spec.backend} offers "
        f"{mine}: it cannot replay it (check out the comexp and engine versions that stored it)"
    )


def replay(db: DbLike, episode_id: int) -> EpisodeResult:
    """Run a stored episode again, in this process, on the backend and with the backend
    options (e.g. `floor_friction=native`) it ran with. On the machine (and package
    versions) that stored it the result equals the stored one; an episode whose physics this
    comexp no longer has is refused (ValueError) rather than run with other physics."""
    spec, row = stored_spec(db, episode_id)
    if spec.backend != row["backend"]:
        raise ValueError(f"episode {episode_id}: spec backend {spec.backend} != {row['backend']}")
    backend = stored_backend(db, row)
    options = backend_options_for(spec, backend)
    with SimulatorSpec(spec.backend, backend._target_, options).make() as sim:
        return run_episode(spec, sim)


__all__ = ["load_results", "replay", "run"]
