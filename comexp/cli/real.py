"""`comexp-real`: the estimators and the physics on recorded pushes of real objects
(docs/real_robot.md).

    comexp-real estimate DIR [--estimator NAME] [--format md|csv|json] [--pixel-mm MM]
    comexp-real replay DIR [--backend NAME] [--path recorded|ideal] [--mu-floor X --mu-pusher Y]
                           [--format md|csv|json]
    comexp-real force DIR [--sliding-mm-s V] [--format md|csv|json]

Each reads every push under DIR (`comexp.real.logs.read_pushes`: the MIT pushing dataset's
layout or the plain CSV layout). `estimate` prints one record per object: its CoM estimated
from its pushes, the error against the true CoM, and the paper's region from the same pushes.
`replay` drives each push on a backend (`comexp.real.replay`) and prints one record per push,
then a summary line against the do-nothing prediction; without `--mu-floor`/`--mu-pusher` each
surface's friction is fitted once on its pushes (on planar). `force` reads the recorded
contact force of each push (`comexp.real.force`) and the pusher's friction from the sliding
ones. Any error (a bad log, an unknown
estimator or backend, a parameter the physics needs) is one line, `comexp-real: error: ...`,
and exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from comexp.cli.arguments import nonnegative_float, positive_float
from comexp.experiment.config import load_backend, make_simulator
from comexp.real.estimate import (
    DEFAULT_PIXEL_M,
    RECORD_FIELDS,
    ObjectEstimate,
    check_estimator,
    estimate_all,
)
from comexp.real.force import SLIDING_M_S, contact_force, friction_by_speed
from comexp.real.logs import read_pushes
from comexp.real.replay import PATHS, Surface, fit_surface, replay_all, summarise, surface_of
from comexp.sim.simulator import Simulator

PROG = "comexp-real"


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad command line in one line (no usage dump), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog.split()[0]}: error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="CoM estimation on recorded pushes of real objects.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    e = sub.add_parser("estimate", help="every object's CoM from its recorded pushes")
    e.add_argument("dir", metavar="DIR", help="a folder of recorded pushes (either layout)")
    e.add_argument(
        "--estimator",
        default="paper",
        metavar="NAME",
        help="paper (default), magnitude, motion, fit (the CoM whose replays reproduce the "
        "pushes), or a plug-in module:Class",
    )
    e.add_argument("--format", choices=("md", "csv", "json"), default="md")
    e.add_argument(
        "--pixel-mm",
        type=positive_float,
        default=DEFAULT_PIXEL_M * 1000.0,
        metavar="MM",
        help=f"grid spacing of the CoM region (default {DEFAULT_PIXEL_M * 1000:g} mm)",
    )
    e.add_argument(
        "--max-angle-deg",
        type=positive_float,
        default=None,
        metavar="DEG",
        help="use only pushes within DEG of the contact normal (default: every push)",
    )
    r = sub.add_parser("replay", help="each recorded push driven on a physics backend")
    r.add_argument("dir", metavar="DIR", help="a folder of recorded pushes (either layout)")
    r.add_argument(
        "--backend", default="planar", metavar="NAME", help="planar (default), pybullet, mujoco"
    )
    r.add_argument(
        "--path",
        choices=PATHS,
        default="recorded",
        help="the pusher's recorded path (default) or the idealised straight push",
    )
    r.add_argument("--mu-floor", type=positive_float, metavar="MU", help="the floor's friction")
    r.add_argument("--mu-pusher", type=positive_float, metavar="MU", help="the pusher's friction")
    r.add_argument("--format", choices=("md", "csv", "json"), default="md")
    r.add_argument(
        "--by",
        choices=("object", "speed"),
        help="a summary line per object or per pusher speed too",
    )
    f = sub.add_parser("force", help="the recorded contact force and the pusher's friction")
    f.add_argument("dir", metavar="DIR", help="a folder of recorded pushes (either layout)")
    f.add_argument(
        "--sliding-mm-s",
        type=nonnegative_float,
        default=SLIDING_M_S * 1000.0,
        metavar="V",
        help="a sample slides when the pusher moves along the outline at least this fast "
        f"relative to the object (default {SLIDING_M_S * 1000:g} mm/s)",
    )
    f.add_argument("--format", choices=("md", "csv", "json"), default="md")
    return p


def _md_value(key: str, v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        digits = {"paper_region_cm2": 1, "paper_region_miss_mm": 1, "pixel_mm": 1}.get(key, 3)
        return f"{v:.{digits}f}"
    return str(v)


def format_records(records: Sequence[dict[str, Any]], fmt: str) -> str:
    """The records as a Markdown table (plus the mean error), CSV or a JSON list."""
    if fmt == "json":
        return json.dumps(list(records), indent=2) + "\n"
    if fmt == "csv":
        out = io.StringIO()
        w = csv.DictWriter(out, fieldnames=RECORD_FIELDS, lineterminator="\n")
        w.writeheader()
        w.writerows({k: "" if v is None else v for k, v in r.items()} for r in records)
        return out.getvalue()
    lines = ["| " + " | ".join(RECORD_FIELDS) + " |", "|" + "---|" * len(RECORD_FIELDS)]
    for r in records:
        lines.append("| " + " | ".join(_md_value(k, r[k]) for k in RECORD_FIELDS) + " |")
    errors = [r["error_cm"] for r in records if r["error_cm"] is not None]
    if errors:
        lines.append("")
        lines.append(
            f"mean error {sum(errors) / len(errors):.3f} cm over {len(errors)} objects "
            f"({records[0]['estimator']}, {sum(r['pushes'] for r in records)} pushes)"
        )
    return "\n".join(lines) + "\n"


def _progress(e: ObjectEstimate) -> None:
    """A line on stderr per object done (the fit takes tens of seconds an object)."""
    error = "" if e.error_cm is None else f", {e.error_cm:.3f} cm from the true CoM"
    print(f"{e.object}: {e.estimator} from {e.pushes} pushes{error}", file=sys.stderr)


def _estimate(args: argparse.Namespace) -> str:
    check_estimator(args.estimator)  # before reading: a typo fails at once
    rec = read_pushes(args.dir)
    pixel_m = args.pixel_mm / 1000.0
    sim = make_simulator("planar") if args.estimator == "fit" else None
    try:
        results = estimate_all(
            rec, args.estimator, pixel_m, args.max_angle_deg, sim, on_object=_progress
        )
    finally:
        if sim is not None:
            sim.close()
    return format_records([r.record() for r in results], args.format)


REPLAY_MD = (
    ("object", "object"),
    ("speed_mm_s", "mm/s"),
    ("angle_to_normal_deg", "angle (deg)"),
    ("turn_recorded_deg", "turn rec. (deg)"),
    ("turn_simulated_deg", "turn sim. (deg)"),
    ("position_error_mm", "position error (mm)"),
    ("stay_error_mm", "stays: error (mm)"),
    ("status", "status"),
    ("push", "push"),
)


def _surfaces(args: argparse.Namespace, rec, planar: Simulator) -> dict[str, Surface]:
    """Each surface's friction: given, else fitted once on its pushes (stderr says so)."""
    names = sorted({surface_of(p) for p in rec.pushes})
    if (args.mu_floor is None) != (args.mu_pusher is None):
        raise ValueError("give both --mu-floor and --mu-pusher, or neither (to fit them)")
    if args.mu_floor is not None:
        return {n: Surface(n, args.mu_floor, args.mu_pusher) for n in names}
    out = {}
    for name in names:
        pushes = [p for p in rec.pushes if surface_of(p) == name]
        print(f"surface {name}: fitting its friction on planar ({len(pushes)} pushes)...",
              file=sys.stderr)  # fmt: skip
        surface, loss = fit_surface(planar, rec.objects, pushes, name, args.path)
        print(
            f"surface {name}: friction fitted on planar over its {len(pushes)} pushes: "
            f"mu_floor {surface.mu_floor:g}, mu_pusher {surface.mu_pusher:g} "
            f"(the figures over their goals: {loss:.2f})",
            file=sys.stderr,
        )
        out[name] = surface
    return out


def _replay(args: argparse.Namespace) -> str:
    load_backend(args.backend)  # an unknown backend fails before the logs are read
    rec = read_pushes(args.dir)
    planar = make_simulator("planar")
    sim = planar if args.backend == "planar" else make_simulator(args.backend)
    try:
        surfaces = _surfaces(args, rec, planar)
        replayed = replay_all(sim, rec.objects, rec.pushes, surfaces, args.path, args.backend)
    finally:
        planar.close()
        sim.close()
    records = [r.record() for r in replayed]
    summary = f"{args.backend}, {args.path} path: {summarise(replayed).line()}"
    if args.by is not None:
        groups: dict[Any, list] = {}
        for r in replayed:
            key = r.object if args.by == "object" else round(r.speed_mm_s)
            groups.setdefault(key, []).append(r)
        unit = " mm/s" if args.by == "speed" else ""
        for key in sorted(groups):
            summary += f"\n  {key}{unit}: {summarise(groups[key]).line()}"
    return _with_summary(records, args.format, summary, REPLAY_MD)


def _with_summary(
    records: Sequence[dict[str, Any]],
    fmt: str,
    summary: str,
    md_columns: Sequence[tuple[str, str]],
) -> str:
    """Per-push records as JSON or CSV (the summary on stderr), or as a Markdown table of
    `md_columns` followed by the summary."""
    if fmt == "json":
        print(summary, file=sys.stderr)
        return json.dumps(list(records), indent=2) + "\n"
    if fmt == "csv":
        print(summary, file=sys.stderr)
        out = io.StringIO()
        w = csv.DictWriter(out, fieldnames=list(records[0]), lineterminator="\n")
        w.writeheader()
        w.writerows({k: "" if v is None else v for k, v in r.items()} for r in records)
        return out.getvalue()
    lines = ["| " + " | ".join(h for _, h in md_columns) + " |", "|" + "---|" * len(md_columns)]
    for r in records:
        cells = [_md_value(k, r[k]) if k != "push" else f"`{r[k]}`" for k, _ in md_columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join([*lines, "", summary]) + "\n"


FORCE_MD = (
    ("object", "object"),
    ("speed_mm_s", "mm/s"),
    ("angle_to_normal_deg", "angle (deg)"),
    ("samples", "samples"),
    ("force_from_normal_deg", "force from normal (deg)"),
    ("force_n", "force (N)"),
    ("torque_mean_nmm", "mean torque (N mm)"),
    ("sliding_samples", "sliding samples"),
    ("friction", "friction"),
    ("push", "push"),
)


def _force(args: argparse.Namespace) -> str:
    rec = read_pushes(args.dir)
    if all(p.force is None for p in rec.pushes):
        raise ValueError(
            f"{args.dir}: no push records a force (the dataset's ft_wrench, or the plain "
            "layout's force_x_n and force_y_n columns)"
        )
    sliding = args.sliding_mm_s / 1000.0
    found = [contact_force(p, rec.objects[p.object_name], sliding) for p in rec.pushes]
    forces = [f for f in found if f is not None]
    if not forces:
        raise ValueError(f"{args.dir}: no push has a force reading while in contact")
    lines = []
    for g in friction_by_speed(forces):
        label = "all" if g.speed_mm_s is None else f"  {g.speed_mm_s} mm/s"
        value = "-" if g.mu_pusher is None else f"{g.mu_pusher:.3f}"
        lines.append(
            f"{label}: {g.pushes} pushes, {g.slid} that slid, the pusher's friction {value}"
        )
    summary = (
        f"contact force read on {len(forces)} of {len(rec.pushes)} pushes; the pusher's "
        "friction: the median over the pushes that slid of |tan| of the force's angle from the "
        f"normal while the pusher slid along the outline (at least {args.sliding_mm_s:g} mm/s)\n"
        + "\n".join(lines)
    )
    return _with_summary([f.record() for f in forces], args.format, summary, FORCE_MD)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        text = {"replay": _replay, "estimate": _estimate, "force": _force}[args.command](args)
    except ValueError as e:  # RecordedPushError included: one line naming the file
        print(f"{PROG}: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
