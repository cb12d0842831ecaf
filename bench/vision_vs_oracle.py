"""Vision against the oracle over whole studies: the mean CoM error with the camera's rotations
(`rotation_source=vision`) and with the true ones (`rotation_source=oracle`), per job and
study-wide, from two databases (read-only) of the same grid.

    .venv/bin/python bench/vision_vs_oracle.py --vision results/pybullet.db \\
        --oracle results/pybullet_oracle.db

The oracle's study is `comexp -m floor=iso,aniso speed=40,4 backend=B
estimator.rotation_source=oracle db=...`: the same episodes (same physics, CoMs and seeds),
only the rotation the estimator is given differs. Per job (backend, floor, speed): episodes
ok in each, the two means and their difference (vision - oracle), the mean of the paired
differences over the episodes ok in both (paired by object, CoM and every grid value) with
a 95% interval from the claims' two-level bootstrap (objects, then CoMs), and the share of
pushes turning more than 1 deg whose measured rotation has the true sign. Then the same
over the whole study.

`--reference-source vision` compares two vision runs instead (e.g. another tracking rule:
`--vision NEW --oracle OLD --reference-source vision`); jobs only in one database are left out.
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from typing import Any

from sqlalchemy import select

from comexp.results.claims import _bootstrap
from comexp.results.reports import CORE_COLUMNS, fmt_num, markdown_table
from comexp.results.schema import EPISODES, PUSHES
from comexp.results.store import ResultsDB

PAIR = (*CORE_COLUMNS, "object", "com_index")
JOB = ("backend", "floor", "speed_cm_s")


def load(url: str, source: str) -> tuple[dict[tuple, dict[str, Any]], list[dict[str, Any]]]:
    """Episodes by pairing key (only those with this rotation source), and their pushes."""
    cols = [EPISODES.c[c] for c in (*PAIR, "status", "error_cm", "rotation_source", "id")]
    with ResultsDB(url, readonly=True) as db, db.engine.connect() as conn:
        eps = [dict(m) for m in conn.execute(select(*cols)).mappings()]
        q = select(
            EPISODES.c.id,
            *(PUSHES.c[c] for c in ("k", "rotation_deg", "rotation_true_deg", "n_frames")),
            *(PUSHES.c[c] for c in ("contact_x_cm", "contact_y_cm", "dir_x", "dir_y", "decision")),
        ).join(PUSHES, PUSHES.c.episode_id == EPISODES.c.id)
        pushes = [dict(m) for m in conn.execute(q).mappings()]
    eps = [e for e in eps if e["rotation_source"] == source]
    if not eps:
        raise SystemExit(f"{url}: no episode with rotation_source={source}")
    by_key: dict[tuple, dict[str, Any]] = {}
    for e in eps:
        key = tuple(e[c] for c in PAIR)
        if key in by_key:
            raise SystemExit(f"{url}: two {source} episodes for {key}: one study per database")
        by_key[key] = e
    ids = {e["id"] for e in eps}
    return by_key, [p for p in pushes if p["id"] in ids]


def row(label: str, vis: list[dict], ora: list[dict], paired, pushes: list[dict]) -> list:
    ok_v = [e["error_cm"] for e in vis if e["status"] == "ok"]
    ok_o = [e["error_cm"] for e in ora if e["status"] == "ok"]
    # the study's own interval (`comexp-db claims`): two-level bootstrap, objects then CoMs
    diffs: dict = defaultdict(lambda: defaultdict(list))
    for v, o in paired:
        diffs[(v["object"], v["com_index"])]["d"].append(v["error_cm"] - o["error_cm"])
    mean, lo, hi, n = _bootstrap(diffs, lambda m: m["d"], seed=0)
    turning = [p for p in pushes if abs(p["rotation_true_deg"]) > 1.0]
    right = sum((p["rotation_deg"] > 0) == (p["rotation_true_deg"] > 0) for p in turning)
    mv, mo = statistics.fmean(ok_v), statistics.fmean(ok_o)
    return [
        label,
        f"{len(ok_v)} / {len(ok_o)}",
        f"{mv:.3f}",
        f"{mo:.3f}",
        f"{mv - mo:+.3f}",
        f"{mean:+.3f} [{lo:+.3f}, {hi:+.3f}] (n {n})",
        f"{100.0 * right / max(1, len(turning)):.2f}% of {len(turning)}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vision", required=True, help="file path or SQLAlchemy URL")
    ap.add_argument("--oracle", required=True, help="file path or SQLAlchemy URL")
    ap.add_argument(
        "--reference-source",
        default="oracle",
        choices=("oracle", "vision"),
        help="the rotation source of the --oracle database's episodes",
    )
    args = ap.parse_args()
    vis, vis_pushes = load(args.vision, "vision")
    ora, ora_pushes = load(args.oracle, args.reference_source)
    missing = set(vis) ^ set(ora)
    if missing:
        print(f"note: {len(missing)} episodes are in one database only (left out)")
    keys = sorted(set(vis) & set(ora), key=repr)
    push_of: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for side, pushes in (("v", vis_pushes), ("o", ora_pushes)):
        for p in sorted(pushes, key=lambda p: p["k"]):
            push_of[(side, p["id"])].append(p)
    jobs: dict[tuple, list[tuple]] = defaultdict(list)
    for k in keys:
        v = vis[k]
        jobs[tuple(v[c] for c in JOB)].append(k)
    out = []
    everything: list[tuple] = []
    for job in sorted(jobs, key=lambda j: (j[0], j[1], -j[2])):
        ks = jobs[job]
        everything += ks
        out.append(table_row(f"{job[0]} {job[1]} {fmt_num(job[2])} cm/s", ks, vis, ora, push_of))
    out.append(table_row("**whole study**", everything, vis, ora, push_of))
    head = ["job", "ok (vision / oracle)", "vision cm", "oracle cm", "difference cm"]
    head += ["paired difference cm [95% CI]", "sign right (|true| > 1 deg)", "frames per push"]
    head += ["episodes choosing other pushes"]
    print(markdown_table(head, out))


def table_row(label: str, ks: list[tuple], vis, ora, push_of) -> list:
    v = [vis[k] for k in ks]
    o = [ora[k] for k in ks]
    paired = [(a, b) for a, b in zip(v, o, strict=True) if a["status"] == b["status"] == "ok"]
    pushes = [p for e in v for p in push_of[("v", e["id"])]]
    frames = statistics.fmean(p["n_frames"] for p in pushes) if pushes else float("nan")
    choice = ("contact_x_cm", "contact_y_cm", "dir_x", "dir_y", "decision")
    other = sum(
        [tuple(p[c] for c in choice) for p in push_of[("v", a["id"])]]
        != [tuple(p[c] for c in choice) for p in push_of[("o", b["id"])]]
        for a, b in zip(v, o, strict=True)
    )
    return [*row(label, v, o, paired, pushes), f"{frames:.1f}", f"{other} of {len(v)}"]


if __name__ == "__main__":
    main()
