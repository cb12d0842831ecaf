"""Summarise the reproduced study from its database (read-only) as Markdown: the all-objects
means beside the paper's, the influence of floor friction, pusher friction and Izz, failures,
vision accuracy, and cross-backend agreement of rotation signs on the same push.

    .venv/bin/python bench/study_report.py --db results/study.db > /tmp/study.md

Every section groups with `comexp.results.reports.group_episodes` (the rule the tables, job reports
and plots use) and names the columns it pools; the paper's value is shown only where the
condition is the paper's (`comexp.results.reports.paper_mean_cm`). Works on SQLite files and
PostgreSQL URLs. The per-object Tables II-III come from `comexp-db --db results/study.db paper`.
"""

from __future__ import annotations

import argparse
import statistics
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from typing import Any

from sqlalchemy import select

from comexp.results.reports import (
    CONDITION_COLUMNS,
    EPISODE_COLUMNS,
    FRICTION_COLUMNS,
    PAPER_POOL,
    Condition,
    fmt_num,
    group_episodes,
    markdown_table,
    ok_error,
    paper_mean_cm,
    tables_from_rows,
)
from comexp.results.schema import EPISODES, PUSHES
from comexp.results.store import ResultsDB

Rows = list[dict[str, Any]]


def _md(header: list[str], rows: list[list[object]]) -> str:
    def cell(v: object) -> str:
        if isinstance(v, float):
            return "" if v != v else f"{v:.3f}"
        return str(v)

    return markdown_table(header, [[cell(v) for v in r] for r in rows])


def _mean(xs: Sequence[float]) -> float:
    return statistics.fmean(xs) if xs else float("nan")


def headline(rows: Rows) -> str:
    """All-objects mean per condition, frictions and Izz pooled (the paper's table form)."""
    out = []
    for table in tables_from_rows(rows, PAPER_POOL):
        c, s = table.condition, table.overall
        paper = paper_mean_cm(table)
        out.append(
            [
                c.pooling(("speed_cm_s",)).label(),
                fmt_num(c.speed_cm_s),
                s.n + table.n_failed,
                s.n,
                s.mean,
                s.std,
                paper if paper is not None else "(not the paper's condition)",
            ]
        )
    head = ["condition (frictions, Izz pooled)", "speed cm/s", "episodes", "ok", "mean cm"]
    return _md([*head, "std cm (ddof=1)", "paper cm"], out)


def influence(
    rows: Rows, axis: Sequence[str], pool: Sequence[str], text: Callable[[Condition], str]
) -> str:
    """Mean error per value of the `axis` columns, speeds side by side; `pool` pooled."""
    groups = group_episodes(rows, pool)
    table: dict[tuple[str, str], dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for cond, group in groups.items():
        context = cond.pooling((*axis, "speed_cm_s")).label()
        errs = [e for r in group if (e := ok_error(r)) is not None]
        table[(context, text(cond))][float(cond.speed_cm_s)] += errs
    speeds = sorted({float(c.speed_cm_s) for c in groups}, reverse=True)
    out = [
        [ctx, v, *(_mean(d.get(s, [])) for s in speeds), *(len(d.get(s, [])) for s in speeds)]
        for (ctx, v), d in table.items()
    ]
    head = ["condition", "value"] + [f"mean @{fmt_num(s)} cm" for s in speeds]
    head += [f"n @{fmt_num(s)}" for s in speeds]
    return _md(head, out) + f"\n\npooled: {', '.join(pool) or 'nothing'}"


def failures(rows: Rows) -> str:
    out = []
    totals: Counter[str] = Counter()
    failed: Counter[str] = Counter()
    for table in tables_from_rows(rows, PAPER_POOL):
        c = table.condition
        totals[c.backend] += table.overall.n + table.n_failed
        failed[c.backend] += table.n_failed
        for reason, n in sorted(table.failures.items(), key=lambda kv: -kv[1]):
            out.append([c.pooling(("speed_cm_s",)).label(), fmt_num(c.speed_cm_s), reason, n])
    tail = "; ".join(
        f"{b}: {failed[b]} of {n} failed ({100.0 * failed[b] / n:.2f}%)"
        for b, n in sorted(totals.items())
    )
    body = _md(["condition", "speed cm/s", "failure", "episodes"], out) if out else "none"
    return f"{body}\n\n{tail}"


def _push_rows(db: ResultsDB) -> Rows:
    cols = [EPISODES.c[c] for c in (*CONDITION_COLUMNS, "object", "com_index", "status")]
    q = select(*cols, PUSHES).join(EPISODES, EPISODES.c.id == PUSHES.c.episode_id)
    with db.engine.connect() as conn:
        return [dict(m) for m in conn.execute(q).mappings()]


def vision_accuracy(pushes: Rows) -> str:
    out = []
    for cond, group in group_episodes(pushes, PAPER_POOL).items():
        if '"rotation_source":"vision"' not in cond.estimator:
            continue
        errs = sorted(abs(p["rotation_deg"] - p["rotation_true_deg"]) for p in group)
        big = [p for p in group if abs(p["rotation_true_deg"]) > 1.0]
        same = [(p["rotation_deg"] > 0) == (p["rotation_true_deg"] > 0) for p in big]
        p95 = errs[int(0.95 * (len(errs) - 1))]
        out.append(
            [
                cond.pooling(("speed_cm_s",)).label(),
                fmt_num(cond.speed_cm_s),
                len(errs),
                statistics.median(errs),
                p95,
                _mean(same) if same else float("nan"),
            ]
        )
    head = ["condition (frictions, Izz pooled)", "speed cm/s", "pushes", "median err deg"]
    return _md([*head, "p95 err deg", "sign right (|true| > 1 deg)"], out)


def cross_backend(pushes: Rows) -> str:
    """First push of the same episode on two engines: same condition but the backend (every
    other condition column equal), same object and CoM, hence the same start and, when
    perception agrees, the same contact."""
    first: dict[tuple[Any, ...], dict[str, dict[str, Any]]] = defaultdict(dict)
    for p in pushes:
        if p["k"] == 0:
            key = (Condition.of(p).pooling(("backend",)), p["object"], p["com_index"])
            first[key][p["backend"]] = p
    stats: dict[float, list[int]] = defaultdict(lambda: [0, 0])
    for (cond, _, _), pair in first.items():
        if len(pair) != 2:
            continue
        a, b = pair.values()
        same_push = (
            abs(a["contact_x_cm"] - b["contact_x_cm"]) < 0.2
            and abs(a["contact_y_cm"] - b["contact_y_cm"]) < 0.2
            and a["dir_x"] * b["dir_x"] + a["dir_y"] * b["dir_y"] > 0.999
        )
        ra, rb = a["rotation_true_deg"], b["rotation_true_deg"]
        if not same_push or min(abs(ra), abs(rb)) <= 1.0:
            continue
        s = stats[float(cond.speed_cm_s)]
        s[0] += 1
        s[1] += (ra > 0) == (rb > 0)
    rows = [
        [fmt_num(sp), n, agree, agree / n if n else float("nan")]
        for sp, (n, agree) in sorted(stats.items(), reverse=True)
    ]
    return _md(["speed cm/s", "same first push, both |rot| > 1 deg", "signs agree", "share"], rows)


def _floor_text(c: Condition) -> str:
    if c.mu_floor_x == c.mu_floor_y:
        return f"{c.floor} mu {fmt_num(c.mu_floor_x)}"
    return f"{c.floor} mu_x/mu_y {fmt_num(c.mu_floor_x)}/{fmt_num(c.mu_floor_y)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", default="results/study.db", help="file path or SQLAlchemy URL")
    args = ap.parse_args()
    with ResultsDB(args.db, readonly=True) as db:
        rows = db.episodes(columns=EPISODE_COLUMNS, order_by_id=False)
        pushes = _push_rows(db)
    print("## All-objects mean error beside the paper's\n")
    print(headline(rows))
    print("\n## Influence of floor friction (mean error cm, ok episodes)\n")
    floor_axis = ("mu_floor_x", "mu_floor_y")
    print(influence(rows, floor_axis, ("izz_scale", "mu_pusher"), _floor_text))
    print("\n## Influence of pusher friction\n")
    print(
        influence(rows, ("mu_pusher",), (*floor_axis, "izz_scale"), lambda c: fmt_num(c.mu_pusher))
    )
    print("\n## Influence of Izz\n")
    print(influence(rows, ("izz_scale",), FRICTION_COLUMNS, lambda c: fmt_num(c.izz_scale)))
    print("\n## Failures\n")
    print(failures(rows))
    print("\n## Vision: measured vs true rotation per push\n")
    print(vision_accuracy(pushes))
    print("\n## Cross-backend agreement: sign of the true rotation of the same first push\n")
    print(cross_backend(pushes))


if __name__ == "__main__":
    main()
