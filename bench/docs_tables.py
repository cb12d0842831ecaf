"""The docs' tables of figures, generated: figures that change with the code live as data under
docs/data/ (JSON: the table, the command that measured it, and the code version, machine and
date it was measured with), never typed into prose; this script writes such data and fills the
docs' generated blocks from it.

    .venv/bin/python bench/docs_tables.py render              # every block from docs/data/
    .venv/bin/python bench/docs_tables.py knobs               # the knob table (from the code)
    .venv/bin/python bench/docs_tables.py results --db results/planar.db --db results/pybullet.db \\
        --db results/mujoco.db                                # the study's means per backend
    .venv/bin/python bench/docs_tables.py real --data ../shared/data/mit-push-train
                                                              # docs/real_robot.md's tables
    .venv/bin/python bench/docs_tables.py methods --db results/fit.db --db results/motion.db
                                                              # estimators paired, per condition

A generated block in README.md or docs/*.md is

    <!-- generated: NAME -->
    ...the table, replaced on every render...
    <!-- end generated -->

and is filled from docs/data/NAME.json (`{"meta": {...}, "command": "...", "columns": [...],
"rows": [[...], ...]}`), or, for `knobs`, from the structured config itself
(`comexp.experiment.config.config_keys`). The bench scripts that measure the docs' figures
write their JSON with `--json docs/data/NAME.json` (`write_table`), then `render` fills the
blocks. A block whose data is missing says which command makes it.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from common import DATA, write_table
from omegaconf import MISSING

from comexp.experiment.config import config_keys
from comexp.experiment.grid import PINNED_VERSIONS
from comexp.results.claims import CLAIM_COLUMNS, claims_records
from comexp.results.paper import ALL_OBJECTS_MEAN_CM
from comexp.results.reports import ok_error
from comexp.results.store import ResultsDB

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
BLOCK = re.compile(
    r"(<!-- generated: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S
)


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
    return "" if v is None else str(v).replace("|", "\\|")


def markdown(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "".join("| " + " | ".join(_cell(c) for c in r) + " |\n" for r in rows)


def block_body(name: str) -> str:
    """What block `name` holds: its table and the command that measures it."""
    if name == "knobs":
        return knobs_markdown()
    path = DATA / f"{name}.json"
    if not path.exists():
        return f"(no data yet: docs/data/{name}.json; see this page for the command)\n"
    data = json.loads(path.read_text())
    where = f"docs/data/{name}.json"
    return (
        markdown(data["columns"], data["rows"])
        + f"\nMeasured by `{data['command']}` ({where} records the code version, machine and "
        "date).\n"
    )


def knobs_markdown() -> str:
    """Every key `comexp --cfg job` prints, its default and its meaning."""
    rows = []
    for k in config_keys():
        group_set = k.key.startswith(("backend.", "floor."))  # the chosen option's values
        default = "(the option's)" if k.default == MISSING or group_set else json.dumps(k.default)
        rows.append((f"`{k.key}`", f"`{default}`", k.help))
    return markdown(("key", "default", "meaning"), rows)


def render(docs: Sequence[Path] = DOCS) -> list[Path]:
    """Fill every generated block of `docs`; the files that changed."""
    changed = []
    for doc in docs:
        text = doc.read_text()
        new = BLOCK.sub(lambda m: m.group(1) + block_body(m["name"]) + m.group(4), text)
        if new != text:
            doc.write_text(new)
            changed.append(doc)
    return changed


def results(dbs: Sequence[str]) -> Path:
    """`results-means`: each study database's all-objects mean error per floor and speed,
    beside the paper's where the condition is the paper's."""
    by_cond: dict[tuple[str, float], dict[str, float]] = {}
    backends: list[str] = []
    studies = []
    for url in dbs:
        with ResultsDB(url, readonly=True) as db:
            rows = db.episodes(columns=["backend", "floor", "speed_cm_s", "status", "error_cm"])
            revs = sorted({str(s.get("git_rev")) for s in db.sweeps()})
        studies.append({"db": str(url), "git": revs, "episodes": len(rows)})
        for r in rows:
            if r["backend"] not in backends:
                backends.append(r["backend"])
        groups: dict[tuple[str, str, float], list[float]] = {}
        for r in rows:
            e = ok_error(r)
            if e is not None:
                groups.setdefault((r["backend"], r["floor"], r["speed_cm_s"]), []).append(e)
        for (b, fl, sp), errs in groups.items():
            by_cond.setdefault((fl, sp), {})[b] = sum(errs) / len(errs)
    out = []
    for (fl, sp), means in sorted(by_cond.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
        paper = ALL_OBJECTS_MEAN_CM.get((fl, float(sp)))
        out.append([f"{fl}, {sp:g} cm/s", *(means.get(b) for b in backends), paper])
    command = "python bench/docs_tables.py results " + " ".join(f"--db {d}" for d in dbs)
    columns = ["floor, speed", *backends, "paper"]
    write_table("results-claims", *claims(dbs), command, studies=studies)
    return write_table("results-means", columns, out, command, studies=studies)


def claims(dbs: Sequence[str]) -> tuple[list[str], list[list[Any]]]:
    """`results-claims`: each study's verdict on the paper's claims, with its 95% interval
    (`comexp-db claims`, the same computation)."""
    out = []
    for url in dbs:
        with ResultsDB(url, readonly=True) as db:
            records = claims_records(db.episodes(columns=CLAIM_COLUMNS))
        for c in records["claims"]:
            interval = f"[{c['low_cm']:.3f}, {c['high_cm']:.3f}]"
            out.append(
                [c["backend"], c["floor"], c["claim"], c["value_cm"], interval, c["verdict"]]
            )
    columns = ["backend", "floor", "claim", "value (cm)", "95% interval", "verdict"]
    return columns, out


NORMAL_PUSH_DEG = 5.0  # `--max-angle-deg` of the normal pushes (docs/real_robot.md)
# what pairs two estimators' episodes: the same scene under the same condition and physics
PAIR_KEY = ("backend", "physics", "floor", "speed_cm_s", "object", "com_index", "izz_scale")
PAIR_KEY += ("mu_floor_x", "mu_floor_y", "mu_pusher")


def estimator_label(estimator_json: str) -> str:
    """An episode's estimator as the tables name it: its method, the model's revision when it
    is not the one the code pins today (`PINNED_VERSIONS`), and what it was told rather than
    measured, e.g. `fit (fit-1+motion-3)`, `fit (true nuisances, true poses)`."""
    est = json.loads(estimator_json)
    method, version = est["method"], est.get("motion_version") or ""
    parts = []
    if version and version != PINNED_VERSIONS.get(method, version):
        parts.append(version)
    if est.get("nuisance_source", "fitted") == "oracle":
        parts.append("true nuisances")
    if est.get("rotation_source", "vision") == "oracle":
        parts.append("true poses")
    return f"{method} ({', '.join(parts)})" if parts else method


def methods(
    dbs: Sequence[str],
    name: str = "fit-methods",
    baseline: str = "motion",
    method: str | None = None,
    floor: str | None = None,
) -> Path:
    """`fit-methods` (or `name`): each estimator's mean error per backend, physics and condition
    (floor, speed) over the databases' episodes, and its paired difference from `baseline` (an
    `estimator_label`) on the same episodes (mean and 95% interval); `method`: that method's
    episodes only, every revision of it; `floor`: that floor's episodes only. Cost is
    episode_profile.py --estimators' (one process, the same episodes alternating): a job's
    wall times depend on what else ran."""
    cols = ["status", "error_cm", "estimator", *PAIR_KEY]
    found: dict[tuple[str, str, str, float, str], dict[tuple, float]] = {}
    for url in dbs:
        with ResultsDB(url, readonly=True) as db:
            for r in db.episodes(columns=cols):
                e = ok_error(r)
                if e is None:
                    continue
                if method and json.loads(r["estimator"])["method"] != method:
                    continue
                if floor and r["floor"] != floor:
                    continue
                label = estimator_label(r["estimator"])
                cond = (r["backend"], r["physics"], r["floor"], float(r["speed_cm_s"]), label)
                found.setdefault(cond, {})[tuple(r[k] for k in PAIR_KEY)] = e
    out = []
    order = sorted(found.items(), key=lambda kv: (kv[0][:3], -kv[0][3], kv[0][4]))
    for (backend, physics, fl, sp, label), eps in order:
        errs = np.array(list(eps.values()))
        base = found.get((backend, physics, fl, sp, baseline), {})
        paired = [eps[k] - base[k] for k in eps if k in base]
        diff = interval = None
        if label != baseline and len(paired) > 1:
            d = np.array(paired)
            half = 1.96 * d.std(ddof=1) / np.sqrt(len(d))
            diff, interval = float(d.mean()), f"[{d.mean() - half:.3f}, {d.mean() + half:.3f}]"
        row = [backend, f"{fl}, {sp:g} cm/s", label, len(errs), float(errs.mean())]
        out.append([*row, diff, interval])
    columns = ["backend", "floor, speed", "estimator", "episodes", "error (cm)"]
    columns += [f"- {baseline} (cm)", "95% interval"]
    args = [f"--name {name}"]
    args += [f"--baseline '{baseline}'"] if baseline != "motion" else []
    args += [f"--method {method}"] if method else []
    args += [f"--floor {floor}"] if floor else []
    args += [f"--db {d}" for d in dbs]
    command = "python bench/docs_tables.py methods " + " ".join(args)
    return write_table(name, columns, out, command)


def real(data: str) -> list[Path]:
    """docs/real_robot.md's tables: `comexp-real estimate` with each built-in estimator, and
    `comexp-real replay` (the friction fitted on planar, as the command does) on every backend,
    on the recorded pushes under `data`."""
    from comexp.experiment.config import make_simulator
    from comexp.real.estimate import estimate_all, usable_pushes
    from comexp.real.force import contact_force, friction_by_speed
    from comexp.real.logs import read_pushes
    from comexp.real.replay import (
        SIGN_MIN_TURN_DEG,
        fit_surface,
        friction_floor,
        geometry_spread,
        replay_all,
        summarise,
        surface_of,
    )

    rec = read_pushes(data)
    command = f"python bench/docs_tables.py real --data {data}"
    planar = make_simulator("planar")
    rows, fitted = [], {}
    for method in ("paper", "magnitude", "motion", "fit"):
        found = estimate_all(rec, method, simulator=planar)
        if method == "fit":  # each object with the CoM its pushes fit: a replay row below
            fitted = {e.object: replace(rec.objects[e.object], true_com_m=e.com_m) for e in found}
        for e in found:
            r = e.record()
            rows.append([method, e.object, e.pushes, r["error_cm"], r["paper_region_cm2"],
                         "yes" if e.paper_region_keeps_true_com else "no",
                         r["paper_region_miss_mm"]])  # fmt: skip
        errors = [e.error_cm for e in found if e.error_cm is not None]
        rows.append([method, "mean", sum(e.pushes for e in found),
                     sum(errors) / len(errors), None, None, None])  # fmt: skip
    columns = ["estimator", "object", "pushes", "error (cm)", "paper region (cm2)",
               "region keeps the true CoM", "region misses it by (mm)"]  # fmt: skip
    written = [write_table("real-estimate", columns, rows, command)]
    rows = []  # the normal pushes alone (docs/real_robot.md): the paper's region
    for e in estimate_all(rec, "paper", max_angle_deg=NORMAL_PUSH_DEG):
        # each normal push: how far its line passes from the true CoM, and whether the object
        # turned the way the push's torque about the CoM says
        obj, lines = rec.objects[e.object], []
        for _, pc in usable_pushes(rec.of(e.object), obj, NORMAL_PUSH_DEG):
            side = pc.line_offset_m(obj.true_com_m)
            lines.append((abs(side), pc.turn_deg, side * pc.turn_deg > 0))
        if not lines:
            continue
        nearest = min(lines)
        rows.append([e.object, e.pushes, "yes" if e.paper_region_keeps_true_com else "no",
                     e.paper_region_miss_mm, 1000 * nearest[0], nearest[1],
                     "yes" if nearest[2] else "no"])  # fmt: skip
    columns = ["object", "normal pushes", "region keeps the true CoM", "misses it by (mm)",
               "nearest push line to the CoM (mm)", "its turn (deg)",
               "turned as the CoM's side says"]  # fmt: skip
    written.append(write_table("real-estimate-normal", columns, rows, command))

    surfaces = {}
    for name in sorted({surface_of(p) for p in rec.pushes}):
        pushes = [p for p in rec.pushes if surface_of(p) == name]
        surfaces[name] = fit_surface(planar, rec.objects, pushes, name)[0]
    friction = ", ".join(
        f"{n}: floor {f.mu_floor:g}, pusher {f.mu_pusher:g}" for n, f in surfaces.items()
    )
    runs = [("planar", "recorded"), ("planar", "ideal"), ("pybullet", "recorded"),
            ("mujoco", "recorded")]  # fmt: skip
    rows, replayed = [], {}
    for backend, path in runs:
        sim = planar if backend == "planar" else make_simulator(backend)
        replayed[backend, path] = replay_all(sim, rec.objects, rec.pushes, surfaces, path, backend)
        s = summarise(replayed[backend, path])
        rows.append([backend, path, friction, s.pushes, s.failed,
                     f"{s.sign_right} of {s.turning}", s.turn_error_median_pct,
                     s.turn_error_median_deg, s.position_error_median_mm,
                     s.position_error_p90_mm])  # fmt: skip
        if sim is not planar:
            sim.close()
    s = summarise(replay_all(planar, fitted, rec.pushes, surfaces, "recorded", "planar"))
    rows.append(["planar", "recorded, each object's CoM fitted (`fit`)", friction, s.pushes,
                 s.failed, f"{s.sign_right} of {s.turning}", s.turn_error_median_pct,
                 s.turn_error_median_deg, s.position_error_median_mm,
                 s.position_error_p90_mm])  # fmt: skip
    s = summarise(replayed["planar", "recorded"])
    rows.append(["the object stays", "", "", s.pushes, 0, "-", 100.0,
                 s.stay_turn_error_median_deg, s.stay_position_error_median_mm,
                 s.stay_position_error_p90_mm])  # fmt: skip
    columns = ["backend", "pusher path", "friction (fitted)", "pushes", "failed",
               "turn sign right (> 2 deg)",
               "median turn error (% of the turn)", "median turn error (deg)",
               "median position error (mm)", "p90 position error (mm)"]  # fmt: skip
    written.append(write_table("real-replay", columns, rows, command, friction=friction))
    rows = []
    by_speed: dict[int, list] = {}
    for r in replayed["planar", "recorded"]:
        by_speed.setdefault(round(r.speed_mm_s), []).append(r)
    for speed in sorted(by_speed):
        s = summarise(by_speed[speed])
        rows.append([speed, s.pushes, f"{s.sign_right} of {s.turning}", s.turn_error_median_pct,
                     s.position_error_median_mm, s.position_error_p90_mm])  # fmt: skip
    columns = ["pusher speed (mm/s)", "pushes", "turn sign right (> 2 deg)",
               "median turn error (% of the turn)", "median position error (mm)",
               "p90 position error (mm)"]  # fmt: skip
    written.append(write_table("real-replay-speed", columns, rows, command, friction=friction))
    rows = []
    for amplitude_mm in (0.5, 1.0, 1.5):
        spread = geometry_spread(planar, rec.objects, rec.pushes, surfaces, amplitude_mm / 1000)
        pos = [g.position_mm for g in spread]
        turn = [
            g.turn_deg / abs(g.turn_recorded_deg) * 100.0
            for g in spread
            if abs(g.turn_recorded_deg) > SIGN_MIN_TURN_DEG
        ]
        rows.append([amplitude_mm, len(spread), float(np.median(turn)), float(np.median(pos)),
                     float(np.percentile(pos, 90))])  # fmt: skip
    columns = ["geometry off by (mm)", "pushes", "median turn change (% of the turn)",
               "median position change (mm)", "p90 position change (mm)"]  # fmt: skip
    written.append(write_table("real-replay-geometry", columns, rows, command, friction=friction))
    floor = friction_floor(planar, rec.objects, rec.pushes)
    s = summarise(replayed["planar", "recorded"])
    rows = [[f"one pair for the surface: the fitted one ({friction})",
             f"{s.sign_right} of {s.turning}", s.turn_error_median_pct,
             s.position_error_median_mm, s.position_error_p90_mm]]  # fmt: skip
    figures = [lambda s: s.turn_error_median_pct, lambda s: s.position_error_median_mm,
               lambda s: s.position_error_p90_mm]  # fmt: skip
    best = [f(floor.pairs[floor.best_pair(f)]) for f in figures]
    right = max(floor.pairs.values(), key=lambda s: s.sign_right)
    rows.append([f"one pair for the surface: each figure's best of the {len(floor.pairs)} pairs",
                 f"{right.sign_right} of {right.turning}", *best])  # fmt: skip
    for label, replays in (
        ("each push's own pair: its closest final position", floor.position),
        ("each push's own pair: its closest turn", floor.turn),
    ):
        s = summarise(replays)
        rows.append([label, f"{s.sign_right} of {s.turning}", s.turn_error_median_pct,
                     s.position_error_median_mm, s.position_error_p90_mm])  # fmt: skip
    columns = ["friction (planar, recorded path)", "turn sign right (> 2 deg)",
               "median turn error (% of the turn)", "median position error (mm)",
               "p90 position error (mm)"]  # fmt: skip
    grid = {"mu_floor": sorted({f for f, _ in floor.pairs}),
            "mu_pusher": sorted({p for _, p in floor.pairs})}  # fmt: skip
    written.append(write_table("real-replay-floor", columns, rows, command, **grid))
    planar.close()
    forces = [contact_force(p, rec.objects[p.object_name]) for p in rec.pushes]
    readings = friction_by_speed([f for f in forces if f is not None])
    rows = [["all" if g.speed_mm_s is None else g.speed_mm_s, g.pushes, g.slid, g.mu_pusher]
            for g in readings]  # fmt: skip
    columns = ["pusher speed (mm/s)", "pushes with a reading", "pushes that slid",
               "the pusher's friction"]  # fmt: skip
    written.append(write_table("real-force", columns, rows, command))
    print(f"fitted friction: {friction}")
    return written


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("render", help="fill every generated block from docs/data/")
    sub.add_parser("knobs", help="the knob table, from the structured config")
    res = sub.add_parser("results", help="the study's means, from its databases")
    res.add_argument("--db", action="append", required=True)
    me = sub.add_parser("methods", help="estimators paired per condition, from databases")
    me.add_argument("--db", action="append", required=True)
    me.add_argument("--name", default="fit-methods", help="docs/data/NAME.json")
    me.add_argument("--baseline", default="motion", help="the estimator the others pair with")
    me.add_argument("--method", help="this method's episodes only (every revision)")
    me.add_argument("--floor", choices=("iso", "aniso"), help="this floor's episodes only")
    rr = sub.add_parser("real", help="docs/real_robot.md's tables, from recorded pushes")
    rr.add_argument("--data", default="../shared/data/mit-push-train")
    args = ap.parse_args(argv)
    if args.command == "results":
        print(results(args.db))
    if args.command == "methods":
        print(methods(args.db, args.name, args.baseline, args.method, args.floor))
    if args.command == "real":
        for path in real(args.data):
            print(path)
    for path in render():
        print(f"updated {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
