"""Results for notebooks and for re-running: `load_results` (pandas) and `replay`.

    import comexp
    df = comexp.load_results("results/comexp.db")            # one row per episode
    result = comexp.replay("results/comexp.db", episode_id=12)  # run it again, in-process

`load_results` adds a `condition` column (the label of `comexp.results.reports.group_episodes`'s
grouping rule), so a notebook groups exactly as the tables and plots do.
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from typing import TYPE_CHECKING, Any

from comexp.results.schema import EPISODES, PUSHES, SWEEPS
from comexp.results.store import ResultsDB

if TYPE_CHECKING:
    import pandas as pd

    from comexp.experiment.episode import EpisodeResult, EpisodeSpec

TABLES = {"episodes": EPISODES, "pushes": PUSHES, "sweeps": SWEEPS}
DbLike = ResultsDB | str | os.PathLike[str]


def _open(db: DbLike) -> tuple[ResultsDB, bool]:
    if isinstance(db, ResultsDB):
        return db, False
    return ResultsDB(db, readonly=True), True


def load_results(db: DbLike, table: str = "episodes") -> pd.DataFrame:
    """One stored table as a pandas DataFrame (read-only). `episodes` gets two more columns:
    `condition` (the grouping rule's label) and `condition_slug` (its short unique name)."""
    import pandas as pd
    from sqlalchemy import select

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
    df = pd.DataFrame(rows, columns=[c.name for c in t.c])
    if table == "episodes":
        from comexp.results.reports import condition_of

        conds = [condition_of(r) for r in rows]
        df["condition"] = pd.Series([c.label() for c in conds], index=df.index, dtype=object)
        df["condition_slug"] = pd.Series([c.slug() for c in conds], index=df.index, dtype=object)
    return df


def _from_json(tp: Any, value: Any) -> Any:
    """Rebuild a (nested, frozen) dataclass from its canonical JSON: lists become tuples."""
    if dataclasses.is_dataclass(tp) and isinstance(value, dict):
        hints = typing.get_type_hints(tp)
        names = {f.name for f in dataclasses.fields(tp)}
        unknown = sorted(set(value) - names)
        if unknown:
            raise ValueError(
                f"stored {tp.__name__} has fields this comexp does not know: {', '.join(unknown)}"
            )
        return tp(**{k: _from_json(hints[k], v) for k, v in value.items()})
    if isinstance(value, list):
        return tuple(_from_json(None, v) for v in value)
    if isinstance(value, dict):
        return {k: _from_json(None, v) for k, v in value.items()}
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def spec_from_json(text: str) -> EpisodeSpec:
    """The stored `spec` column back as the `EpisodeSpec` that ran (estimator included)."""
    from comexp.experiment.episode import EpisodeSpec

    return _from_json(EpisodeSpec, json.loads(text))


def stored_spec(db: DbLike, episode_id: int) -> tuple[EpisodeSpec, dict[str, Any]]:
    handle, owned = _open(db)
    try:
        row = handle.episode(int(episode_id))
    finally:
        if owned:
            handle.close()
    return spec_from_json(row["spec"]), row


def backend_options_for(spec: EpisodeSpec) -> dict[str, Any]:
    """The backend options (`backend.floor_friction`, `camera.renderer`) that gave a stored
    episode its physics: the ones whose `physics_identity` is the spec's. The identity keeps
    only a hash of the options, so each choice is tried. An episode stored without a pinned
    physics runs with the defaults."""
    from comexp.experiment.simulator import (
        FLOOR_FRICTION_CHOICES,
        RENDERER_CHOICES,
        physics_identity,
    )

    choices: list[dict[str, str]] = [{}]
    if spec.backend != "planar":  # the renderer is named only when not the engine's own
        choices = [
            {"floor_friction": f, **({} if r == "engine" else {"renderer": r})}
            for r in RENDERER_CHOICES
            for f in FLOOR_FRICTION_CHOICES
        ]
    if not spec.physics:
        return choices[0]
    for options in choices:
        if physics_identity(spec.backend, options=options) == spec.physics:
            return options
    mine = ", ".join(physics_identity(spec.backend, options=o) for o in choices)
    raise ValueError(
        f"the episode ran with physics {spec.physics}; this comexp's {spec.backend} offers "
        f"{mine}: it cannot replay it (check out the comexp and engine versions that stored it)"
    )


def replay(db: DbLike, episode_id: int) -> EpisodeResult:
    """Run a stored episode again, in this process, on the backend and with the backend
    options (e.g. `floor_friction=native`) it ran with. On the machine (and package
    versions) that stored it the result equals the stored one; an episode whose physics this
    comexp no longer has is refused (ValueError) rather than run with other physics."""
    from comexp.experiment.episode import run_episode
    from comexp.experiment.simulator import make_simulator

    spec, row = stored_spec(db, episode_id)
    if spec.backend != row["backend"]:
        raise ValueError(f"episode {episode_id}: spec backend {spec.backend} != {row['backend']}")
    with make_simulator(row["backend"], **backend_options_for(spec)) as sim:
        return run_episode(spec, sim)
