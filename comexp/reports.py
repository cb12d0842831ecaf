"""Aggregated error tables in the form of the paper's Tables II and III.

One table per friction-and-speed condition (backend, floor, mu_floor_x, mu_floor_y, mu_pusher,
speed_cm_s): per object n / mean / std / max / min of ``error_cm`` over the episodes that
finished (``status = ok``), an all-objects row, and the failed episodes that were left out,
counted by reason, so that a low mean can never hide a high failure rate.

std is the population standard deviation (numpy's default, ddof=0): it is defined for n = 1 and
is what the paper's numpy/OpenCV tooling would print.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from comexp.db import EpisodeFilter, ResultsDB

CONDITION_FIELDS = ("backend", "floor", "mu_floor_x", "mu_floor_y", "mu_pusher", "speed_cm_s")
STAT_COLUMNS = ("n", "mean", "std", "max", "min")
ALL_OBJECTS = "all"
# Columns that make a different method or protocol: rows differing in them are never pooled.
VARIANT_FIELDS = ("estimator", "push_length_cm", "recenter_beyond_cm")
_EPISODE_COLUMNS = (*CONDITION_FIELDS, *VARIANT_FIELDS, "object", "status", "failure", "error_cm")


def natural_key(name: str) -> list[Any]:
    """obj2 before obj10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def fmt_num(x: float) -> str:
    """Short, exact-looking number for labels: 40.0 -> 40, 0.1 -> 0.1."""
    return f"{x:g}"


@dataclass(frozen=True, order=True)
class Condition:
    """A friction and speed condition; `estimator` is set only when variants must be told apart."""

    backend: str
    floor: str
    mu_floor_x: float
    mu_floor_y: float
    mu_pusher: float
    speed_cm_s: float
    estimator: str = ""

    @property
    def floor_label(self) -> str:
        if self.mu_floor_x == self.mu_floor_y:
            return f"{self.floor} mu_floor={fmt_num(self.mu_floor_x)}"
        return (
            f"{self.floor} mu_floor_x={fmt_num(self.mu_floor_x)} "
            f"mu_floor_y={fmt_num(self.mu_floor_y)}"
        )

    def label(self) -> str:
        text = (
            f"{self.backend}, floor {self.floor_label}, mu_pusher={fmt_num(self.mu_pusher)}, "
            f"speed {fmt_num(self.speed_cm_s)} cm/s"
        )
        return text + (f", estimator {self.estimator}" if self.estimator else "")

    def slug(self) -> str:
        """File-name-safe, unique per condition."""
        text = (
            f"{self.backend}_{self.floor}_fx{fmt_num(self.mu_floor_x)}_fy{fmt_num(self.mu_floor_y)}"
            f"_p{fmt_num(self.mu_pusher)}_v{fmt_num(self.speed_cm_s)}"
        )
        if self.estimator:
            text += "_est" + hashlib.sha256(self.estimator.encode()).hexdigest()[:8]
        return re.sub(r"[^A-Za-z0-9_.-]", "-", text)

    def values(self) -> dict[str, Any]:
        d: dict[str, Any] = {f: getattr(self, f) for f in CONDITION_FIELDS}
        if self.estimator:
            d["estimator"] = self.estimator
        return d


@dataclass(frozen=True)
class ErrorStats:
    n: int
    mean: float
    std: float
    max: float
    min: float

    @classmethod
    def of(cls, values: Sequence[float]) -> ErrorStats:
        if not values:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan)
        a = np.asarray(values, dtype=float)
        return cls(len(a), float(a.mean()), float(a.std()), float(a.max()), float(a.min()))


@dataclass(frozen=True)
class ConditionTable:
    condition: Condition
    rows: tuple[tuple[str, ErrorStats, int], ...]  # (object, stats over ok episodes, n failed)
    overall: ErrorStats
    failures: dict[str, int] = field(default_factory=dict)  # reason -> count

    @property
    def n_failed(self) -> int:
        return sum(self.failures.values())

    def failure_text(self) -> str:
        if not self.failures:
            return "no failed episodes"
        reasons = ", ".join(f"{r} {n}" for r, n in sorted(self.failures.items()))
        return f"{self.n_failed} failed episode(s) excluded: {reasons}"


# --------------------------------------------------------------------------- aggregation
def condition_tables(db: ResultsDB, flt: EpisodeFilter | None = None) -> list[ConditionTable]:
    """One table per condition among the episodes that `flt` selects, in condition order."""
    return tables_from_rows(db.episodes(flt, columns=_EPISODE_COLUMNS, order_by_id=False))


def tables_from_rows(rows: Iterable[dict[str, Any]]) -> list[ConditionTable]:
    rows = list(rows)

    def variant(r: dict[str, Any]) -> str:
        est, push, recenter = (r.get(f) for f in VARIANT_FIELDS)
        return f"{est} push_length_cm={push} recenter_beyond_cm={recenter}"

    variants = {variant(r) for r in rows}
    groups: dict[Condition, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        est = variant(r) if len(variants) > 1 else ""
        cond = Condition(*(r[f] for f in CONDITION_FIELDS), estimator=est)
        groups[cond].append(r)
    return [_table(cond, groups[cond]) for cond in sorted(groups)]


def _table(cond: Condition, rows: list[dict[str, Any]]) -> ConditionTable:
    errors: dict[str, list[float]] = defaultdict(list)
    failed: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    for r in rows:
        if r["status"] == "ok" and r["error_cm"] is not None and math.isfinite(r["error_cm"]):
            errors[r["object"]].append(float(r["error_cm"]))
        else:
            errors.setdefault(r["object"], [])
            failed[r["object"]] += 1
            reasons[r["failure"] or ("no_error" if r["status"] == "ok" else "unknown")] += 1
    objects = sorted(errors, key=natural_key)
    table_rows = tuple((o, ErrorStats.of(errors[o]), failed[o]) for o in objects)
    overall = ErrorStats.of([e for o in objects for e in errors[o]])
    return ConditionTable(cond, table_rows, overall, dict(reasons))


@dataclass(frozen=True)
class SummaryRow:
    condition: Condition
    stats: ErrorStats
    n_failed: int
    failures: dict[str, int]


def summary_rows(tables: Sequence[ConditionTable]) -> list[SummaryRow]:
    return [SummaryRow(t.condition, t.overall, t.n_failed, t.failures) for t in tables]


# --------------------------------------------------------------------------- formatting
def _cell(x: float, digits: int) -> str:
    return "" if not math.isfinite(x) else f"{x:.{digits}f}"


def _stat_cells(s: ErrorStats, digits: int) -> list[str]:
    return [str(s.n)] + [_cell(getattr(s, c), digits) for c in STAT_COLUMNS[1:]]


def _md_table(header: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in body]
    return "\n".join(lines)


def table_markdown(t: ConditionTable, *, digits: int = 3) -> str:
    """A condition heading, the per-object table (error in cm) and the excluded failures."""
    body = [[o, *_stat_cells(s, digits), str(nf)] for o, s, nf in t.rows]
    body.append([f"**{ALL_OBJECTS}**", *_stat_cells(t.overall, digits), str(t.n_failed)])
    header = ["object", *STAT_COLUMNS, "failed"]
    return (
        f"### {t.condition.label()}\n\nerror_cm over ok episodes\n\n"
        f"{_md_table(header, body)}\n\n{t.failure_text()}\n"
    )


def _condition_header(tables: Sequence[ConditionTable]) -> list[str]:
    extra = ["estimator"] if any(t.condition.estimator for t in tables) else []
    return [*CONDITION_FIELDS, *extra]


def tables_csv(tables: Sequence[ConditionTable], *, digits: int = 6) -> str:
    """Flat CSV: condition columns, then object, n, mean, std, max, min, n_failed."""
    cond_cols = _condition_header(tables)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*cond_cols, "object", *STAT_COLUMNS, "n_failed"])
    for t in tables:
        cv = t.condition.values()
        prefix = [_plain(cv.get(c, "")) for c in cond_cols]
        for o, s, nf in t.rows:
            w.writerow([*prefix, o, *_stat_cells(s, digits), nf])
        w.writerow([*prefix, ALL_OBJECTS, *_stat_cells(t.overall, digits), t.n_failed])
    return buf.getvalue()


def summary_markdown(tables: Sequence[ConditionTable], *, digits: int = 3) -> str:
    header = ["condition", "n ok", "failed", "mean", "std", "max", "min", "failures"]
    body = []
    for r in summary_rows(tables):
        s = r.stats
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(r.failures.items()))
        body.append(
            [
                r.condition.label(),
                str(s.n),
                str(r.n_failed),
                *(_cell(getattr(s, c), digits) for c in STAT_COLUMNS[1:]),
                reasons,
            ]
        )
    return f"## Summary: error_cm per condition\n\n{_md_table(header, body)}\n"


def summary_csv(tables: Sequence[ConditionTable], *, digits: int = 6) -> str:
    cond_cols = _condition_header(tables)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*cond_cols, "n_ok", "n_failed", "mean", "std", "max", "min", "failures"])
    for r in summary_rows(tables):
        cv = r.condition.values()
        reasons = ";".join(f"{k}:{v}" for k, v in sorted(r.failures.items()))
        stats = _stat_cells(r.stats, digits)
        w.writerow(
            [*(_plain(cv.get(c, "")) for c in cond_cols), stats[0], r.n_failed, *stats[1:], reasons]
        )
    return buf.getvalue()


def summary_text(tables: Sequence[ConditionTable]) -> str:
    """A few printable lines: one per condition."""
    if not tables:
        return "no episodes stored for this selection"
    lines = []
    for r in summary_rows(tables):
        s = r.stats
        err = "no ok episodes" if s.n == 0 else f"error {s.mean:.3f} +- {s.std:.3f} cm"
        lines.append(f"{r.condition.label()}: {s.n} ok, {r.n_failed} failed, {err}")
    return "\n".join(lines)


def _plain(v: Any) -> str:
    if isinstance(v, float):
        return fmt_num(v) if v == round(v, 12) else repr(v)
    return str(v)


# --------------------------------------------------------------------------- paper form
def paper_tables(
    db: ResultsDB, flt: EpisodeFilter | None = None
) -> dict[tuple[str, str], dict[float, ConditionTable]]:
    """Tables II/III: per (backend, floor), per speed, per object, pooled over frictions."""
    rows = db.episodes(flt, columns=_EPISODE_COLUMNS, order_by_id=False)
    pooled: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        pooled[(r["backend"], r["floor"], r["speed_cm_s"])].append(r)
    out: dict[tuple[str, str], dict[float, ConditionTable]] = defaultdict(dict)
    for (backend, floor, speed), group in sorted(pooled.items()):
        nan = float("nan")
        cond = Condition(backend, floor, nan, nan, nan, speed)
        out[(backend, floor)][speed] = _table(cond, group)
    return dict(out)


def paper_markdown(
    tables: dict[tuple[str, str], dict[float, ConditionTable]], *, digits: int = 3
) -> str:
    """Speeds side by side (fastest first, "dynamic" then "quasi-static"), as in the paper."""
    parts = []
    for (backend, floor), by_speed in tables.items():
        speeds = sorted(by_speed, reverse=True)
        objects = sorted({o for t in by_speed.values() for o, _, _ in t.rows}, key=natural_key)
        header = ["object"] + [
            f"{c} @{fmt_num(v)}" for v in speeds for c in ("n", "mean", "std", "max", "min")
        ]
        body = []
        for o in [*objects, ALL_OBJECTS]:
            row = [o]
            for v in speeds:
                t = by_speed[v]
                stats = t.overall if o == ALL_OBJECTS else _stats_for(t, o)
                row += _stat_cells(stats, digits)
            body.append(row)
        failed = "; ".join(f"{fmt_num(v)} cm/s: {by_speed[v].failure_text()}" for v in speeds)
        parts.append(
            f"### {backend}, floor {floor} (all frictions pooled; error_cm, speeds in cm/s)\n\n"
            f"{_md_table(header, body)}\n\n{failed}\n"
        )
    return "\n".join(parts) if parts else "no episodes stored for this selection\n"


def _stats_for(t: ConditionTable, obj: str) -> ErrorStats:
    for o, s, _ in t.rows:
        if o == obj:
            return s
    return ErrorStats.of([])


# --------------------------------------------------------------------------- job reports
def write_job_reports(
    db: ResultsDB,
    out_dir: str | Path,
    *,
    backend: str | None = None,
    floor: str | None = None,
    speed_cm_s: float | None = None,
) -> tuple[list[Path], str]:
    """Markdown + CSV per condition and a combined summary into `out_dir` (the Hydra job dir)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    flt = EpisodeFilter(backend=backend, floor=floor, speed_cm_s=speed_cm_s)
    tables = condition_tables(db, flt)
    paths: list[Path] = []
    for t in tables:
        md = out / f"errors_{t.condition.slug()}.md"
        md.write_text(table_markdown(t))
        cs = out / f"errors_{t.condition.slug()}.csv"
        cs.write_text(tables_csv([t]))
        paths += [md, cs]
    summary_md = out / "summary.md"
    summary_md.write_text(
        f"# CoM estimation error\n\nselection: {flt.describe()}\n\n"
        + summary_markdown(tables)
        + "\n"
        + "\n".join(table_markdown(t) for t in tables)
    )
    summary_cs = out / "summary.csv"
    summary_cs.write_text(summary_csv(tables))
    paths += [summary_md, summary_cs]
    return paths, summary_text(tables)
