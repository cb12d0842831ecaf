"""Aggregated error tables (the paper's Tables II and III form), from one grouping rule.

A *condition* is everything that can change a result: one value of each `CONDITION_COLUMNS`
(backend, floor, frictions, speed, Izz, mass, push protocol, the whole estimator settings,
stored as canonical JSON, and the backend's physics identity). `group_episodes` is the only
place that groups episodes: job reports, `comexp-db table / summary / paper / plot`,
`comexp.load_results` and the bench all call it, so no two of them can pool differently. A
view that pools on purpose (the paper's tables pool frictions and Izz, as the paper does)
names the pooled columns and says so in its header; every other column still separates.

Per condition: per object n / mean / std / max / min of ``error_cm`` over the episodes that
finished (``status = ok``), an all-objects row, and the failed episodes that were left out,
counted by reason, so that a low mean can never hide a high failure rate.

std is the sample standard deviation (ddof = 1, the unbiased variance estimate): it is blank
(NaN) for a single episode.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from comexp.episode.task import CameraSettings, EpisodeSettings
from comexp.method.estimator import EstimatorSettings
from comexp.results import paper
from comexp.results.filters import EpisodeFilter
from comexp.results.identity import canonical_json
from comexp.results.store import ResultsDB

# Core columns: always in a label (unless pooled), in this order.
CORE_COLUMNS = (
    "backend",
    "floor",
    "mu_floor_x",
    "mu_floor_y",
    "mu_pusher",
    "speed_cm_s",
    "izz_scale",
)
# Every column that can change a result. Adding one (e.g. a physics version) here makes every
# table, report, plot and the bench tell its values apart.
CONDITION_COLUMNS: tuple[str, ...] = (
    *CORE_COLUMNS,
    "mass_kg",
    "push_length_cm",
    "recenter_beyond_cm",
    "estimator",
    "physics",
    "camera_fps",
)
FRICTION_COLUMNS = ("mu_floor_x", "mu_floor_y", "mu_pusher")
# The paper's Tables II/III and Figs. 3/4 pool the friction grid and both Izz scales.
PAPER_POOL = (*FRICTION_COLUMNS, "izz_scale")
# Protocol columns shown in a label only when they differ from these defaults: the config's
PROTOCOL_DEFAULTS: dict[str, Any] = {
    "mass_kg": EpisodeSettings.mass_kg,
    "push_length_cm": EpisodeSettings.push_length_cm,
    "recenter_beyond_cm": EpisodeSettings.recenter_beyond_cm,
    "camera_fps": CameraSettings.fps,
}
_DEFAULT_ESTIMATOR: dict[str, Any] = json.loads(canonical_json(EstimatorSettings()))
STAT_COLUMNS = ("n", "mean", "std", "max", "min")
ALL_OBJECTS = "all"
EPISODE_COLUMNS = (*CONDITION_COLUMNS, "object", "status", "failure", "error_cm")


class _Pooled:
    """Marks a condition column whose values a view pooled on purpose."""

    _instance: _Pooled | None = None

    def __new__(cls) -> _Pooled:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "POOLED"

    def __reduce__(self) -> str:
        return "POOLED"


POOLED = _Pooled()


def natural_key(name: str) -> list[Any]:
    """obj2 before obj10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def fmt_num(x: float) -> str:
    """Short, exact-looking number for labels: 40.0 -> 40, 0.1 -> 0.1."""
    return f"{x:g}"


def _sortable(v: Any) -> tuple[int, Any]:
    if v is POOLED:
        return (0, 0)
    if v is None:
        return (1, 0)
    if isinstance(v, int | float):
        return (2, float(v))
    return (3, str(v))


# What an episode stored before a knob existed ran with, where that differs from the knob's
# default: such rows are labelled with it, so that they are told apart from new rows.
# before f0e1013: every frame; before track_drive_mm: every frame while the pusher drove
LEGACY_ESTIMATOR: dict[str, Any] = {"track_step_deg": 0, "track_drive_mm": 0.0}


def estimator_changes(estimator_json: str) -> dict[str, Any]:
    """The estimator settings that differ from comexp's defaults (keys added later count;
    a key missing from an older row counts as its `LEGACY_ESTIMATOR` value, if any)."""
    try:
        est = json.loads(estimator_json)
    except (TypeError, ValueError):
        return {"estimator": estimator_json}
    est = {**LEGACY_ESTIMATOR, **est}
    return {k: v for k, v in sorted(est.items()) if _DEFAULT_ESTIMATOR.get(k, object()) != v}


@dataclass(frozen=True)
class Condition:
    """One value per `CONDITION_COLUMNS` entry (`POOLED` where a view pooled that column)."""

    key: tuple[Any, ...]

    def __post_init__(self) -> None:
        if len(self.key) != len(CONDITION_COLUMNS):
            raise ValueError(f"a condition has {len(CONDITION_COLUMNS)} values, got {self.key}")

    @classmethod
    def of(cls, row: Mapping[str, Any], pool: Iterable[str] = ()) -> Condition:
        pooled = set(pool)
        return cls(tuple(POOLED if c in pooled else row.get(c) for c in CONDITION_COLUMNS))

    def __getattr__(self, name: str) -> Any:
        if name in CONDITION_COLUMNS:
            return self.key[CONDITION_COLUMNS.index(name)]
        raise AttributeError(name)

    def __getitem__(self, name: str) -> Any:
        return self.key[CONDITION_COLUMNS.index(name)]

    def values(self) -> dict[str, Any]:
        return dict(zip(CONDITION_COLUMNS, self.key, strict=True))

    def pooling(self, columns: Iterable[str]) -> Condition:
        """This condition with `columns` pooled (a figure's panel, the paper's table)."""
        cols = set(columns)
        pairs = zip(CONDITION_COLUMNS, self.key, strict=True)
        return Condition(tuple(POOLED if c in cols else v for c, v in pairs))

    def sort_key(self) -> tuple[Any, ...]:
        return tuple(_sortable(v) for v in self.key)

    def __lt__(self, other: Condition) -> bool:
        return self.sort_key() < other.sort_key()

    @property
    def floor_label(self) -> str:
        fx, fy = self.mu_floor_x, self.mu_floor_y
        if fx is POOLED or fy is POOLED:
            return f"{self.floor}" if self.floor is not POOLED else "all floors"
        if fx == fy:
            return f"{self.floor} mu_floor={fmt_num(fx)}"
        return f"{self.floor} mu_floor_x={fmt_num(fx)} mu_floor_y={fmt_num(fy)}"

    def extras(self) -> list[str]:
        """Parts beyond the core: the rotation source, non-default knobs and protocol, and any
        condition column added later."""
        out: list[str] = []
        est = self.estimator
        if est is not POOLED and est is not None:
            changes = estimator_changes(est)
            source = changes.pop("rotation_source", _DEFAULT_ESTIMATOR["rotation_source"])
            out.append(f"rotation {source}")
            out += [f"{k}={_short(v)}" for k, v in changes.items()]
        for c in CONDITION_COLUMNS:
            if c in CORE_COLUMNS or c == "estimator":
                continue
            v = self[c]
            if v is POOLED:
                continue
            if c in PROTOCOL_DEFAULTS:
                if v is not None and not _same(v, PROTOCOL_DEFAULTS[c]):
                    out.append(f"{c}={_short(v)}")
            elif v not in (None, ""):
                out.append(f"{c}={_short(v)}")
        return out

    def label(self) -> str:
        """Human-readable and unique: every column that differs from the defaults is named."""
        parts = []
        if self.backend is not POOLED:
            parts.append(str(self.backend))
        if self.floor is not POOLED:
            parts.append(f"floor {self.floor_label}")
        if self.mu_pusher is not POOLED:
            parts.append(f"mu_pusher={fmt_num(self.mu_pusher)}")
        if self.speed_cm_s is not POOLED:
            parts.append(f"speed {fmt_num(self.speed_cm_s)} cm/s")
        if self.izz_scale is not POOLED:
            parts.append(f"Izz x{fmt_num(self.izz_scale)}")
        return ", ".join(parts + self.extras())

    def slug(self) -> str:
        """File-name-safe, unique per condition: readable core plus a hash of the rest when any
        of it differs from the defaults."""
        bits = []
        for c, tag in (
            ("backend", ""),
            ("floor", ""),
            ("mu_floor_x", "fx"),
            ("mu_floor_y", "fy"),
            ("mu_pusher", "p"),
            ("speed_cm_s", "v"),
            ("izz_scale", "izz"),
        ):
            v = self[c]
            if v is not POOLED:
                bits.append(tag + (fmt_num(v) if isinstance(v, float | int) else str(v)))
        text = "_".join(bits)
        rest = [p for p in self.extras() if not p.startswith("rotation vision")]
        if rest:
            text += "_" + hashlib.sha256(repr(self.key).encode()).hexdigest()[:8]
        return re.sub(r"[^A-Za-z0-9_.-]", "-", text)


def _same(a: Any, b: Any) -> bool:
    try:
        return abs(float(a) - float(b)) < 1e-9
    except (TypeError, ValueError):
        return a == b


def _short(v: Any) -> str:
    if isinstance(v, float):
        return fmt_num(v)
    if isinstance(v, list):
        return "[" + ",".join(_short(x) for x in v) + "]"
    return str(v)


# --------------------------------------------------------------------------- the grouping rule
def group_episodes(
    rows: Iterable[Mapping[str, Any]], pool: Iterable[str] = ()
) -> dict[Condition, list[dict[str, Any]]]:
    """Episodes by condition, in condition order. The one grouping rule of comexp: rows differ
    in a condition when any `CONDITION_COLUMNS` value differs, except the columns in `pool`,
    which a view pools on purpose (and must say so)."""
    pool = tuple(pool)
    unknown = [c for c in pool if c not in CONDITION_COLUMNS]
    if unknown:
        raise ValueError(f"cannot pool unknown condition column(s): {', '.join(unknown)}")
    groups: dict[Condition, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        groups[Condition.of(r, pool)].append(dict(r))
    return {c: groups[c] for c in sorted(groups)}


def condition_of(row: Mapping[str, Any]) -> Condition:
    """The condition of one episode row (for a notebook: ``df.apply(condition_of, axis=1)``)."""
    return Condition.of(row)


def pooled_values(rows: Sequence[Mapping[str, Any]], pool: Iterable[str]) -> dict[str, tuple]:
    """Distinct values of each pooled column within a group (what a header says was pooled).
    Floor frictions pooled together stay (mu_x, mu_y) pairs, index-aligned: (0.1, 1) and
    (1, 0.1) are the aniso grid, (0.1, 0.1) and (1, 1) the iso one."""
    pool = tuple(pool)
    out = {c: tuple(sorted({r[c] for r in rows}, key=_sortable)) for c in pool}
    if "mu_floor_x" in out and "mu_floor_y" in out:
        pairs = sorted({(r["mu_floor_x"], r["mu_floor_y"]) for r in rows})
        out["mu_floor_x"] = tuple(a for a, _ in pairs)
        out["mu_floor_y"] = tuple(b for _, b in pairs)
    return out


@dataclass(frozen=True)
class ErrorStats:
    n: int
    mean: float
    std: float  # sample std, ddof = 1 (NaN for n < 2)
    max: float
    min: float

    @classmethod
    def of(cls, values: Sequence[float]) -> ErrorStats:
        nan = float("nan")
        if not len(values):
            return cls(0, nan, nan, nan, nan)
        a = np.asarray(values, dtype=float)
        std = float(a.std(ddof=1)) if len(a) > 1 else nan
        return cls(len(a), float(a.mean()), std, float(a.max()), float(a.min()))


def ok_error(r: Mapping[str, Any]) -> float | None:
    """The episode's error when it counts (finished, finite), else None."""
    e = r.get("error_cm")
    if r.get("status") == "ok" and e is not None and math.isfinite(e):
        return float(e)
    return None


@dataclass(frozen=True)
class ConditionTable:
    condition: Condition
    rows: tuple[tuple[str, ErrorStats, int], ...]  # (object, stats over ok episodes, n failed)
    overall: ErrorStats
    failures: dict[str, int] = field(default_factory=dict)  # reason -> count
    pooled: dict[str, tuple[Any, ...]] = field(default_factory=dict)  # column -> values pooled
    # the distinct combinations of the pooled columns' values (a full grid or not)
    combos: frozenset[tuple[Any, ...]] = frozenset()

    @property
    def n_failed(self) -> int:
        return sum(self.failures.values())

    def failure_text(self) -> str:
        if not self.failures:
            return "no failed episodes"
        reasons = ", ".join(f"{r} {n}" for r, n in sorted(self.failures.items()))
        return f"{self.n_failed} failed episode(s) excluded: {reasons}"

    def pooled_text(self) -> str:
        return "; ".join(
            f"{c} pooled over {{{', '.join(_short(v) for v in vs)}}}"
            for c, vs in self.pooled.items()
        )


# --------------------------------------------------------------------------- aggregation
def condition_tables(
    db: ResultsDB, flt: EpisodeFilter | None = None, *, pool: Iterable[str] = ()
) -> list[ConditionTable]:
    """One table per condition among the episodes that `flt` selects, in condition order."""
    return tables_from_rows(db.episodes(flt, columns=EPISODE_COLUMNS, order_by_id=False), pool)


def tables_from_rows(
    rows: Iterable[Mapping[str, Any]], pool: Iterable[str] = ()
) -> list[ConditionTable]:
    pool = tuple(pool)
    return [
        _table(cond, group, pooled_values(group, pool))
        for cond, group in group_episodes(rows, pool).items()
    ]


def _table(
    cond: Condition, rows: list[dict[str, Any]], pooled: dict[str, tuple[Any, ...]]
) -> ConditionTable:
    errors: dict[str, list[float]] = defaultdict(list)
    failed: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    for r in rows:
        e = ok_error(r)
        if e is not None:
            errors[r["object"]].append(e)
        else:
            errors.setdefault(r["object"], [])
            failed[r["object"]] += 1
            reasons[r["failure"] or ("no_error" if r["status"] == "ok" else "unknown")] += 1
    objects = sorted(errors, key=natural_key)
    table_rows = tuple((o, ErrorStats.of(errors[o]), failed[o]) for o in objects)
    overall = ErrorStats.of([e for o in objects for e in errors[o]])
    combos = frozenset(tuple(r[c] for c in pooled) for r in rows)
    return ConditionTable(cond, table_rows, overall, dict(reasons), pooled, combos)


# --------------------------------------------------------------------------- the paper
def paper_mean_cm(table: ConditionTable) -> float | None:
    """The paper's all-objects mean when `table` is the paper's condition (its floor's friction
    grid, both Izz scales, 0.2 kg, 3 cm pushes, vision, the paper's estimator values, 40 or
    4 cm/s, all pooled as in Tables II/III); None otherwise."""
    c = table.condition
    if c.floor not in paper.FLOOR_PAIRS or tuple(table.pooled) != PAPER_POOL:
        return None
    # the whole grid, every combination: (mu_x, mu_y) x mu_pusher x Izz
    grid = {
        (fx, fy, mp, izz)
        for (fx, fy) in paper.FLOOR_PAIRS[c.floor]
        for mp in paper.PUSHER_MU[c.floor]
        for izz in paper.IZZ_SCALES
    }
    if {tuple(float(v) for v in combo) for combo in table.combos} != grid:
        return None
    if not (_same(c.mass_kg, paper.MASS_KG) and _same(c.push_length_cm, paper.PUSH_LENGTH_CM)):
        return None
    try:
        est = json.loads(c.estimator)
    except (TypeError, ValueError):
        return None
    if est.get("rotation_source") != paper.ROTATION_SOURCE:
        return None
    if any(est.get(k) != v for k, v in paper.ESTIMATOR.items()):
        return None
    return paper.ALL_OBJECTS_MEAN_CM.get((c.floor, float(c.speed_cm_s)))


def paper_tables(
    db: ResultsDB, flt: EpisodeFilter | None = None
) -> dict[Condition, dict[float, ConditionTable]]:
    """Tables II/III: per condition with frictions and Izz pooled (as the paper does), per
    speed side by side, per object. Keyed by the condition with speed pooled too."""
    rows = db.episodes(flt, columns=EPISODE_COLUMNS, order_by_id=False)
    out: dict[Condition, dict[float, ConditionTable]] = defaultdict(dict)
    for cond, group in group_episodes(rows, PAPER_POOL).items():
        pooled = pooled_values(group, PAPER_POOL)
        out[cond.pooling(("speed_cm_s",))][float(cond.speed_cm_s)] = _table(cond, group, pooled)
    return dict(out)


def paper_markdown(tables: dict[Condition, dict[float, ConditionTable]], *, digits: int = 3) -> str:
    """Speeds side by side (fastest first, "dynamic" then "quasi-static"), as in the paper;
    a "paper" row where the condition is the paper's."""
    parts = []
    for cond, by_speed in tables.items():
        speeds = sorted(by_speed, reverse=True)
        objects = sorted({o for t in by_speed.values() for o, _, _ in t.rows}, key=natural_key)
        header = ["object"] + [f"{c} @{fmt_num(v)}" for v in speeds for c in STAT_COLUMNS]
        body = []
        for o in [*objects, ALL_OBJECTS]:
            row = [o if o != ALL_OBJECTS else f"**{ALL_OBJECTS}**"]
            for v in speeds:
                t = by_speed[v]
                stats = t.overall if o == ALL_OBJECTS else _stats_for(t, o)
                row += _stat_cells(stats, digits)
            body.append(row)
        marks = [paper_mean_cm(by_speed[v]) for v in speeds]
        if any(m is not None for m in marks):
            row = ["paper (all objects)"]
            for m in marks:
                row += ["", _cell(m, digits) if m is not None else "", "", "", ""]
            body.append(row)
        failed = "; ".join(f"{fmt_num(v)} cm/s: {by_speed[v].failure_text()}" for v in speeds)
        pooled = by_speed[speeds[0]].pooled_text()
        parts.append(
            f"### {cond.label()}\n\nerror_cm over ok episodes; speeds in cm/s; {pooled}\n\n"
            f"{markdown_table(header, body)}\n\n{failed}\n"
        )
    return "\n".join(parts) if parts else "no episodes stored for this selection\n"


def _stats_for(t: ConditionTable, obj: str) -> ErrorStats:
    for o, s, _ in t.rows:
        if o == obj:
            return s
    return ErrorStats.of([])


# --------------------------------------------------------------------------- formatting
def _cell(x: float, digits: int) -> str:
    return "" if not math.isfinite(x) else f"{x:.{digits}f}"


def _stat_cells(s: ErrorStats, digits: int) -> list[str]:
    return [str(s.n)] + [_cell(getattr(s, c), digits) for c in STAT_COLUMNS[1:]]


def markdown_table(header: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    """The one Markdown table writer (reports, `comexp-db`, the bench): cells as given, with
    a `|` or a line break inside a cell escaped so the table stays one row per line."""

    def cell(text: str) -> str:
        return str(text).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def fmt_value(v: Any) -> str:
    """A stored value as a table shows it: floats short (`fmt_num`), None blank."""
    if isinstance(v, float):
        return fmt_num(v)
    return "" if v is None else str(v)


def table_markdown(t: ConditionTable, *, digits: int = 3) -> str:
    """A condition heading, the per-object table (error in cm) and the excluded failures."""
    body = [[o, *_stat_cells(s, digits), str(nf)] for o, s, nf in t.rows]
    body.append([f"**{ALL_OBJECTS}**", *_stat_cells(t.overall, digits), str(t.n_failed)])
    header = ["object", *STAT_COLUMNS, "failed"]
    pooled = f"; {t.pooled_text()}" if t.pooled else ""
    return (
        f"### {t.condition.label()}\n\nerror_cm over ok episodes (std: sample, ddof=1){pooled}"
        f"\n\n{markdown_table(header, body)}\n\n{t.failure_text()}\n"
    )


def _csv_value(v: Any) -> str:
    if v is POOLED:
        return "*"
    return "" if v is None else _plain(v)


def tables_csv(tables: Sequence[ConditionTable], *, digits: int = 6) -> str:
    """Flat CSV: every condition column, then object, n, mean, std, max, min, n_failed."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*CONDITION_COLUMNS, "object", *STAT_COLUMNS, "n_failed"])
    for t in tables:
        prefix = [_csv_value(v) for v in t.condition.key]
        for o, s, nf in t.rows:
            w.writerow([*prefix, o, *_stat_cells(s, digits), nf])
        w.writerow([*prefix, ALL_OBJECTS, *_stat_cells(t.overall, digits), t.n_failed])
    return buf.getvalue()


def summary_markdown(tables: Sequence[ConditionTable], *, digits: int = 3) -> str:
    header = ["condition", "n ok", "failed", "mean", "std", "max", "min", "failures"]
    body = []
    for t in tables:
        s = t.overall
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(t.failures.items()))
        body.append(
            [
                t.condition.label(),
                str(s.n),
                str(t.n_failed),
                *(_cell(getattr(s, c), digits) for c in STAT_COLUMNS[1:]),
                reasons,
            ]
        )
    table = markdown_table(header, body)
    return f"## Summary: error_cm per condition (std: sample, ddof=1)\n\n{table}\n"


def summary_csv(tables: Sequence[ConditionTable], *, digits: int = 6) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*CONDITION_COLUMNS, "n_ok", "n_failed", "mean", "std", "max", "min", "failures"])
    for t in tables:
        reasons = ";".join(f"{k}:{v}" for k, v in sorted(t.failures.items()))
        stats = _stat_cells(t.overall, digits)
        w.writerow(
            [*(_csv_value(v) for v in t.condition.key), stats[0], t.n_failed, *stats[1:], reasons]
        )
    return buf.getvalue()


# JSON (`comexp-db ... --format json`): the same rows as the CSV, as records with typed values
# (numbers as numbers, null for a missing value or NaN); a pooled column is left out of the
# condition and listed under "pooled".
def json_number(x: Any) -> Any:
    """A float for JSON: None for NaN and infinities (strict JSON has neither)."""
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def condition_record(cond: Condition) -> dict[str, Any]:
    """A condition's columns (pooled ones left out) and its label; the estimator settings as
    an object, not as the stored JSON text."""
    out: dict[str, Any] = {"condition": cond.label()}
    for c, v in cond.values().items():
        if v is POOLED:
            continue
        if c == "estimator" and isinstance(v, str):
            with contextlib.suppress(ValueError):
                v = json.loads(v)
        out[c] = json_number(v)
    return out


def _stats_record(s: ErrorStats) -> dict[str, Any]:
    return {c: json_number(getattr(s, c)) for c in STAT_COLUMNS}


def _pooled_record(t: ConditionTable) -> dict[str, Any]:
    return {"pooled": {c: [json_number(v) for v in vs] for c, vs in t.pooled.items()}}


def tables_records(tables: Sequence[ConditionTable]) -> list[dict[str, Any]]:
    """`tables_csv` as records: per condition and object (and `all`), the error statistics."""
    out = []
    for t in tables:
        cond = condition_record(t.condition) | (_pooled_record(t) if t.pooled else {})
        for o, stats, nf in (*t.rows, (ALL_OBJECTS, t.overall, t.n_failed)):
            out.append(cond | {"object": o} | _stats_record(stats) | {"n_failed": nf})
    return out


def summary_records(tables: Sequence[ConditionTable]) -> list[dict[str, Any]]:
    """`summary_csv` as records: one per condition, the failures by reason."""
    out = []
    for t in tables:
        stats = _stats_record(t.overall)
        n_ok = stats.pop("n")
        out.append(
            condition_record(t.condition)
            | {"n_ok": n_ok, "n_failed": t.n_failed}
            | stats
            | {"failures": dict(sorted(t.failures.items()))}
        )
    return out


def paper_records(tables: dict[Condition, dict[float, ConditionTable]]) -> list[dict[str, Any]]:
    """`paper_markdown` as records: per condition (frictions and Izz pooled), speed and object
    (and `all`, with the paper's all-objects mean where the condition is the paper's)."""
    out = []
    for by_speed in tables.values():
        for speed in sorted(by_speed, reverse=True):
            t = by_speed[speed]
            cond = condition_record(t.condition) | _pooled_record(t)
            for o, stats, nf in t.rows:
                out.append(cond | {"object": o} | _stats_record(stats) | {"n_failed": nf})
            out.append(
                cond
                | {"object": ALL_OBJECTS}
                | _stats_record(t.overall)
                | {"n_failed": t.n_failed, "paper_mean": json_number(paper_mean_cm(t))}
            )
    return out


def summary_text(tables: Sequence[ConditionTable]) -> str:
    """A few printable lines: one per condition."""
    if not tables:
        return "no episodes stored for this selection"
    lines = []
    for t in tables:
        s = t.overall
        if s.n == 0:
            err = "no ok episodes"
        elif s.n == 1:
            err = f"error {s.mean:.3f} cm (one episode)"
        else:
            err = f"error {s.mean:.3f} +- {s.std:.3f} cm (mean +- sample std)"
        lines.append(f"{t.condition.label()}: {s.n} ok, {t.n_failed} failed, {err}")
    return "\n".join(lines)


def _plain(v: Any) -> str:
    if isinstance(v, float):
        return fmt_num(v) if v == round(v, 12) else repr(v)
    return str(v)


# --------------------------------------------------------------------------- job reports
def write_job_reports(
    db: ResultsDB,
    out_dir: str | Path,
    keys: Sequence[str],
    *,
    job: str = "",
    files: bool = True,
) -> tuple[list[Path], str]:
    """Markdown + CSV per condition and a combined summary into `out_dir` (the Hydra job dir),
    over this job's own episodes only (its grid's `keys`), whoever stored them; the summary's
    text. `files` False: the text only (a job that ran nothing writes no new reports)."""
    rows = db.episodes_by_keys(keys, columns=EPISODE_COLUMNS)
    tables = tables_from_rows(rows)
    header = (
        f"this job's episodes only: {len(rows)} of its {len(set(keys))} grid episodes stored"
        + (f" ({job})" if job else "")
    )
    text = f"report: {header}\n{summary_text(tables)}"
    if not files:
        return [], text
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    for t in tables:
        md = out / f"errors_{t.condition.slug()}.md"
        md.write_text(f"{header}\n\n{table_markdown(t)}")
        cs = out / f"errors_{t.condition.slug()}.csv"
        cs.write_text(tables_csv([t]))
        paths += [md, cs]
    summary_md = out / "summary.md"
    summary_md.write_text(
        f"# CoM estimation error\n\n{header}\n\n"
        + summary_markdown(tables)
        + "\n"
        + "\n".join(table_markdown(t) for t in tables)
    )
    summary_cs = out / "summary.csv"
    summary_cs.write_text(summary_csv(tables))
    paths += [summary_md, summary_cs]
    return paths, text
