"""Summarise the reproduced study from its database (read-only) as Markdown: the all-objects
means beside the paper's, the influence of floor friction, pusher friction and Izz, failures,
vision accuracy, and cross-backend agreement of rotation signs on the same push.

    .venv/bin/python bench/study_report.py --db results/study.db > /tmp/study.md

The per-object Tables II-III come from `comexp-db --db results/study.db paper`.
"""

from __future__ import annotations

import argparse
import sqlite3
import statistics
from collections import defaultdict
from pathlib import Path

PAPER_MEAN_CM = {
    ("iso", 40.0): 0.63,
    ("iso", 4.0): 1.40,
    ("aniso", 40.0): 0.69,
    ("aniso", 4.0): 2.36,
}


def _connect(path: Path) -> sqlite3.Connection:
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    con.row_factory = sqlite3.Row
    return con


def _md(header: list[str], rows: list[list[object]]) -> str:
    def cell(v: object) -> str:
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def _mean(xs: list[float]) -> float:
    return statistics.fmean(xs) if xs else float("nan")


def headline(con: sqlite3.Connection) -> str:
    rows = []
    q = """SELECT backend, floor, speed_cm_s, COUNT(*) n,
                  SUM(status='ok') ok, AVG(CASE WHEN status='ok' THEN error_cm END) mean
           FROM episodes GROUP BY backend, floor, speed_cm_s
           ORDER BY backend, floor DESC, speed_cm_s DESC"""
    for r in con.execute(q):
        paper = PAPER_MEAN_CM.get((r["floor"], float(r["speed_cm_s"])), float("nan"))
        rows.append(
            [r["backend"], r["floor"], f"{r['speed_cm_s']:g}", r["n"], r["ok"], r["mean"], paper]
        )
    head = ["backend", "floor", "speed cm/s", "episodes", "ok", "mean error cm", "paper cm"]
    return _md(head, rows)


def influence(con: sqlite3.Connection, column: str, label: str) -> str:
    q = f"""SELECT backend, floor, {column} AS v, speed_cm_s, AVG(error_cm) mean, COUNT(*) n
            FROM episodes WHERE status='ok'
            GROUP BY backend, floor, v, speed_cm_s ORDER BY backend, floor DESC, v"""
    table: dict[tuple[str, str, str], dict[float, float]] = defaultdict(dict)
    for r in con.execute(q):
        table[(r["backend"], r["floor"], str(r["v"]))][float(r["speed_cm_s"])] = r["mean"]
    rows = [
        [b, f, v, d.get(40.0, float("nan")), d.get(4.0, float("nan"))]
        for (b, f, v), d in table.items()
    ]
    return _md(["backend", "floor", label, "mean @40 cm", "mean @4 cm"], rows)


def failures(con: sqlite3.Connection) -> str:
    q = """SELECT backend, floor, speed_cm_s, failure, COUNT(*) n FROM episodes
           WHERE status='failed' GROUP BY backend, floor, speed_cm_s, failure
           ORDER BY backend, floor DESC, speed_cm_s DESC, n DESC"""
    rows = [
        [r["backend"], r["floor"], f"{r['speed_cm_s']:g}", r["failure"], r["n"]]
        for r in con.execute(q)
    ]
    total = con.execute(
        "SELECT backend, COUNT(*), SUM(status='failed') FROM episodes GROUP BY backend"
    )
    tail = "; ".join(f"{b}: {f} of {n} failed ({100.0 * f / n:.2f}%)" for b, n, f in total)
    return (
        _md(["backend", "floor", "speed cm/s", "failure", "episodes"], rows) if rows else "none"
    ) + f"\n\n{tail}"


def vision_accuracy(con: sqlite3.Connection) -> str:
    q = """SELECT e.backend, e.speed_cm_s, ABS(p.rotation_deg - p.rotation_true_deg) err,
                  (p.rotation_deg > 0) = (p.rotation_true_deg > 0) same_sign,
                  ABS(p.rotation_true_deg) truth
           FROM pushes p JOIN episodes e ON e.id = p.episode_id
           WHERE e.rotation_source = 'vision'"""
    by: dict[tuple[str, float], list[tuple[float, int, float]]] = defaultdict(list)
    for r in con.execute(q):
        by[(r["backend"], float(r["speed_cm_s"]))].append((r["err"], r["same_sign"], r["truth"]))
    rows = []
    for (b, s), v in sorted(by.items()):
        errs = sorted(x[0] for x in v)
        big = [x for x in v if x[2] > 1.0]
        sign_ok = sum(x[1] for x in big) / len(big) if big else float("nan")
        p95 = errs[int(0.95 * (len(errs) - 1))]
        rows.append([b, f"{s:g}", len(errs), statistics.median(errs), p95, sign_ok])
    head = [
        "backend",
        "speed cm/s",
        "pushes",
        "median err deg",
        "p95 err deg",
        "sign right (|true| > 1 deg)",
    ]
    return _md(head, rows)


def cross_backend(con: sqlite3.Connection) -> str:
    """First push of the same episode on both engines (same object, CoM, Izz, frictions, speed,
    seed, hence the same start and, when perception agrees, the same contact)."""
    q = """SELECT e.backend, e.floor, e.mu_floor_x, e.mu_floor_y, e.mu_pusher, e.speed_cm_s,
                  e.izz_scale, e.object, e.com_index, p.contact_x_cm, p.contact_y_cm,
                  p.dir_x, p.dir_y, p.rotation_true_deg
           FROM pushes p JOIN episodes e ON e.id = p.episode_id WHERE p.k = 0"""
    first: dict[tuple, dict[str, tuple]] = defaultdict(dict)
    for r in con.execute(q):
        key = tuple(
            r[c]
            for c in (
                "floor",
                "mu_floor_x",
                "mu_floor_y",
                "mu_pusher",
                "speed_cm_s",
                "izz_scale",
                "object",
                "com_index",
            )
        )
        first[key][r["backend"]] = (
            r["contact_x_cm"],
            r["contact_y_cm"],
            r["dir_x"],
            r["dir_y"],
            r["rotation_true_deg"],
            key[4],
        )
    stats: dict[float, list[int]] = defaultdict(lambda: [0, 0, 0])
    for pair in first.values():
        if len(pair) != 2:
            continue
        a, b = pair["pybullet"], pair["mujoco"]
        same_push = (
            abs(a[0] - b[0]) < 0.2 and abs(a[1] - b[1]) < 0.2 and a[2] * b[2] + a[3] * b[3] > 0.999
        )
        if not same_push or min(abs(a[4]), abs(b[4])) <= 1.0:
            continue
        s = stats[a[5]]
        s[0] += 1
        s[1] += (a[4] > 0) == (b[4] > 0)
    rows = [
        [f"{sp:g}", n, agree, agree / n if n else float("nan")]
        for sp, (n, agree, _) in sorted(stats.items(), reverse=True)
    ]
    return _md(["speed cm/s", "same first push, both |rot| > 1 deg", "signs agree", "share"], rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", type=Path, default=Path("results/study.db"))
    args = ap.parse_args()
    con = _connect(args.db)
    print("## All-objects mean error beside the paper's\n")
    print(headline(con))
    print("\n## Influence of floor friction (mean error cm, ok episodes)\n")
    print(influence(con, "mu_floor_x || '/' || mu_floor_y", "mu_x/mu_y"))
    print("\n## Influence of pusher friction\n")
    print(influence(con, "mu_pusher", "pusher mu"))
    print("\n## Influence of Izz\n")
    print(influence(con, "izz_scale", "Izz scale"))
    print("\n## Failures\n")
    print(failures(con))
    print("\n## Vision: measured vs true rotation per push\n")
    print(vision_accuracy(con))
    print("\n## Cross-backend agreement: sign of the true rotation of the same first push\n")
    print(cross_backend(con))


if __name__ == "__main__":
    main()
