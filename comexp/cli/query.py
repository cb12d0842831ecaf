"""`comexp-db`: query the results database (read-only): tables, summary, episodes, sweeps, plots,
and one episode drawn (`show`).

The database is always opened read-only (SQLite `mode=ro`, PostgreSQL read-only transactions),
so a query can run beside a sweep that is writing and can never change stored results. Every
error is one line on stderr and a non-zero exit. A filter that matches nothing is not an error:
the result is empty (a CSV keeps its header), a note on stderr says why, and the exit is 0.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import json
import os
import re
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from sqlalchemy.exc import SQLAlchemyError

from comexp.cli.arguments import nonnegative_float, positive_float
from comexp.results.claims import CLAIM_COLUMNS, claims_markdown, claims_records
from comexp.results.filters import EpisodeFilter
from comexp.results.reports import (
    CORE_COLUMNS,
    condition_tables,
    fmt_value,
    json_number,
    markdown_table,
    paper_markdown,
    paper_records,
    paper_tables,
    summary_csv,
    summary_markdown,
    summary_records,
    table_markdown,
    tables_csv,
    tables_records,
)
from comexp.results.schema import EPISODES
from comexp.results.store import ResultsDB

DEFAULT_DB = os.path.join("results", "comexp.db")
EPISODE_DEFAULT_COLUMNS = (
    "id",
    "sweep_id",
    *CORE_COLUMNS,  # backend, floor, frictions, speed, Izz
    "object",
    "com_index",
    "error_cm",
    "n_pushes",
    "status",
    "failure",
    "wall_s",
)
SWEEP_COLUMNS = ("id", "started_at", "job_name", "git_rev", "n_episodes", "n_ok", "command_line")


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad command line in one line (no usage dump)."""

    def error(self, message: str) -> NoReturn:
        late = re.search(r"unrecognized arguments: .*?(--db)\b", message)
        if late:  # `comexp-db summary --db X`: the option belongs to comexp-db itself
            message = f"--db goes before the command: {self.prog.split()[0]} --db DB COMMAND ..."
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _int_at_least(minimum: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < minimum:
            op = "> 0" if minimum == 1 else f">= {minimum}"
            raise argparse.ArgumentTypeError(f"must be {op}: {text!r}")
        return v

    return parse


_pos_int = _int_at_least(1)
_nonneg_int = _int_at_least(0)


def _add_condition_filters(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("condition filters")
    g.add_argument("--backend", help="planar | pybullet | mujoco")
    g.add_argument("--floor", help="iso | aniso")
    g.add_argument("--speed", type=positive_float, metavar="CM_S", help="pushing speed, cm/s")
    g.add_argument(
        "--mu-floor", type=nonnegative_float, metavar="MU", help="isotropic floor: mu_x = mu_y = MU"
    )
    g.add_argument("--mu-floor-x", type=nonnegative_float, metavar="MU", help="floor mu along x")
    g.add_argument("--mu-floor-y", type=nonnegative_float, metavar="MU", help="floor mu along y")
    g.add_argument("--mu-pusher", type=nonnegative_float, metavar="MU", help="pusher friction")
    g.add_argument("--izz", type=positive_float, metavar="SCALE", help="Izz scale factor")
    g.add_argument("--object", help="object name")
    g.add_argument("--sweep", type=_pos_int, metavar="ID", help="sweep id")
    g.add_argument("--rotation-source", help="vision | oracle")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="comexp-db",
        description="Query the comexp results database (opened read-only).",
    )
    p.add_argument("--db", default=DEFAULT_DB, help=f"file path or SQLAlchemy URL ({DEFAULT_DB})")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    t = sub.add_parser("table", help="per-object error table for each matching condition")
    _add_condition_filters(t)
    t.add_argument("--format", choices=("md", "csv", "json"), default="md")

    s = sub.add_parser("summary", help="one row per condition: n ok, n failed, mean error")
    _add_condition_filters(s)
    s.add_argument("--format", choices=("md", "csv", "json"), default="md")

    pp = sub.add_parser(
        "paper", help="Tables II/III form: speeds side by side, frictions pooled, per floor"
    )
    _add_condition_filters(pp)
    pp.add_argument("--format", choices=("md", "json"), default="md")

    c = sub.add_parser(
        "claims", help="the paper's claims per study: paired differences, bootstrap 95%% CIs"
    )
    _add_condition_filters(c)
    c.add_argument("--seed", type=_nonneg_int, default=0, help="bootstrap seed (0)")
    c.add_argument("--format", choices=("md", "json"), default="md")

    e = sub.add_parser("episodes", help="list or export episodes")
    _add_condition_filters(e)
    e.add_argument("--com-index", type=_nonneg_int)
    e.add_argument("--status", choices=("ok", "failed"))
    e.add_argument("--failure", help="failure reason, e.g. tipped")
    e.add_argument("--limit", type=_pos_int)
    e.add_argument("--columns", help="comma-separated episode columns ('all' for every column)")
    e.add_argument("--format", choices=("md", "csv", "json"), default="md")

    w = sub.add_parser("sweeps", help="list sweeps (or show one with --show ID)")
    w.add_argument("--show", type=_pos_int, metavar="ID", help="print one sweep's config")
    w.add_argument("--format", choices=("md", "json"), default="md")

    pl = sub.add_parser("plot", help="draw the figures (PNG) into --out")
    _add_condition_filters(pl)
    pl.add_argument("--out", required=True, metavar="DIR")

    sh = sub.add_parser("show", help="draw one episode: outline, pushes, CoM region, CoMs")
    sh.add_argument("episode_id", type=_pos_int, metavar="EPISODE_ID")
    sh.add_argument("--out", required=True, metavar="FILE.png")
    return p


def _filter(args: argparse.Namespace) -> EpisodeFilter:
    try:
        return EpisodeFilter(
            backend=args.backend,
            floor=args.floor,
            speed_cm_s=args.speed,
            mu_floor=args.mu_floor,
            mu_floor_x=args.mu_floor_x,
            mu_floor_y=args.mu_floor_y,
            mu_pusher=args.mu_pusher,
            izz_scale=args.izz,
            object=args.object,
            com_index=getattr(args, "com_index", None),
            status=getattr(args, "status", None),
            failure=getattr(args, "failure", None),
            sweep_id=args.sweep,
            rotation_source=args.rotation_source,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None


_HINT_COLUMNS = {
    "backend": "backend",
    "floor": "floor",
    "speed_cm_s": "speed_cm_s",
    "mu_floor": "mu_floor_x",
    "mu_floor_x": "mu_floor_x",
    "mu_floor_y": "mu_floor_y",
    "mu_pusher": "mu_pusher",
    "izz_scale": "izz_scale",
    "object": "object",
    "failure": "failure",
    "sweep_id": "sweep_id",
    "rotation_source": "rotation_source",
}


def _no_match_note(db: ResultsDB, flt: EpisodeFilter) -> str | None:
    """None when episodes match; else one line naming the filters that match nothing on their
    own, with the stored choices (a note for stderr: an empty result is not an error)."""
    if db.count(flt) > 0:
        return None
    if db.count() == 0:
        return f"no episodes stored in {db.where}"
    hints = []
    for name, column in _HINT_COLUMNS.items():
        v = getattr(flt, name)
        if v is not None and db.count(EpisodeFilter(**{name: v})) == 0:
            stored = ", ".join(fmt_value(x) for x in db.distinct(column) if x is not None)
            hints.append(f"{name}={fmt_value(v)} matches nothing (stored: {stored})")
    detail = "; ".join(hints) if hints else "the filters match nothing together"
    return f"no episodes match {flt.describe()}: {detail}"


def _json_default(v: Any) -> Any:
    if isinstance(v, datetime.datetime | datetime.date):
        return v.isoformat()
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def _json_out(value: Any) -> str:
    """Strict JSON (NaN and infinities as null), one document, indented."""

    def clean(v: Any) -> Any:
        if isinstance(v, float):
            return json_number(v)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(value), indent=2, default=_json_default, allow_nan=False) + "\n"


def _rows_out(rows: Sequence[dict[str, Any]], columns: Sequence[str], fmt: str) -> str:
    if fmt == "json":
        return _json_out([{c: r[c] for c in columns} for r in rows])
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow(["" if r[c] is None else r[c] for c in columns])
        return buf.getvalue()
    return markdown_table(columns, [[fmt_value(r[c]) for c in columns] for r in rows]) + "\n"


def _first_line(text: str | None, width: int = 120) -> str:
    """A failure's detail in a table cell: its first line, cut at `width`."""
    line = (text or "").strip().splitlines()[0] if (text or "").strip() else ""
    return line if len(line) <= width else line[: width - 3] + "..."


def _episode_columns(spec: str | None) -> list[str]:
    if spec is None:
        return list(EPISODE_DEFAULT_COLUMNS)
    if spec.strip() == "all":
        return [c.name for c in EPISODES.c]
    cols = [c.strip() for c in spec.split(",") if c.strip()]
    unknown = [c for c in cols if c not in EPISODES.c]
    if unknown or not cols:
        known = ", ".join(c.name for c in EPISODES.c)
        raise CliError(
            f"unknown episode column(s) {', '.join(unknown) or '(none)'}; known: {known}"
        )
    return cols


def _note(text: str) -> None:
    print(f"comexp-db: note: {text}", file=sys.stderr)


def _run(args: argparse.Namespace, out: Any) -> None:
    if args.command == "show":
        _check_image_path(args.out)
    db = ResultsDB(args.db, readonly=True)
    if db.schema_note is not None:
        _note(db.schema_note)
    try:
        if args.command == "sweeps":
            _sweeps(db, args, out)
            return
        if args.command == "show":
            _show(db, args, out)
            return
        flt = _filter(args)
        note = _no_match_note(db, flt)
        if note is not None:
            _note(note)
        if args.command == "table":
            tables = condition_tables(db, flt)
            if args.format == "json":
                out.write(_json_out(tables_records(tables)))
            elif args.format == "csv":
                out.write(tables_csv(tables))
            else:
                out.write("\n".join(table_markdown(t) for t in tables))
        elif args.command == "summary":
            tables = condition_tables(db, flt)
            if args.format == "json":
                out.write(_json_out(summary_records(tables)))
            else:
                out.write(summary_csv(tables) if args.format == "csv" else summary_markdown(tables))
        elif args.command == "paper":
            ptables = paper_tables(db, flt)
            if args.format == "json":
                out.write(_json_out(paper_records(ptables)))
            else:
                out.write(paper_markdown(ptables))
        elif args.command == "claims":
            rows = db.episodes(flt, columns=CLAIM_COLUMNS)
            if args.format == "json":
                out.write(_json_out(claims_records(rows, seed=args.seed)))
            else:
                out.write(claims_markdown(rows, seed=args.seed))
        elif args.command == "episodes":
            cols = _episode_columns(args.columns)
            fetch = list(dict.fromkeys([*cols, "status", "detail"]))
            rows = db.episodes(flt, columns=fetch, limit=args.limit)
            if args.columns is None and any(r["status"] == "failed" for r in rows):
                cols = [*cols, "detail"]  # why they failed, by default where some did
                for r in rows:
                    r["detail"] = _first_line(r["detail"]) if r["status"] == "failed" else ""
            out.write(_rows_out(rows, cols, args.format))
        elif args.command == "plot":
            # on first use: matplotlib adds ~0.3 s to the start-up of every comexp-db command
            from comexp.results.plots import make_plots

            for path in make_plots(db, args.out, flt):
                out.write(f"{path}\n")
    finally:
        db.close()


def _check_image_path(path: str) -> None:
    from matplotlib.figure import Figure

    kinds = Figure().canvas.get_supported_filetypes()
    suffix = os.path.splitext(path)[1].lstrip(".").lower()
    if suffix not in kinds:
        raise CliError(f"--out {path!r}: name an image file ({', '.join(sorted(kinds))})")
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise CliError(f"--out {path!r}: directory {parent!r} does not exist")


def _show(db: ResultsDB, args: argparse.Namespace, out: Any) -> None:
    # on first use: matplotlib adds ~0.3 s to the start-up of every comexp-db command
    from comexp.results.plots import plot_episode

    row = db.episode(args.episode_id)
    plot_episode(row, db.pushes(args.episode_id), args.out)
    out.write(f"{args.out}\n")


def _sweeps(db: ResultsDB, args: argparse.Namespace, out: Any) -> None:
    sweeps = db.sweeps()
    if args.show is None:
        if not sweeps:
            _note(f"no sweeps stored in {db.where}")
        out.write(_rows_out(sweeps, SWEEP_COLUMNS, args.format))
        return
    match = [s for s in sweeps if s["id"] == args.show]
    if not match:
        raise CliError(f"no sweep with id {args.show} (stored: {len(sweeps)} sweeps)")
    s = match[0]
    if args.format == "json":  # every stored field: the config as its YAML text
        out.write(_json_out(s))
        return
    for key in ("id", "started_at", "job_name", "host", "git_rev", "command_line"):
        out.write(f"{key}: {fmt_value(s.get(key))}\n")
    out.write(f"episodes: {s['n_episodes']} ({s['n_ok']} ok)\n")
    out.write("versions:\n")
    for k, v in sorted((s.get("versions") or {}).items()):
        out.write(f"  {k}: {v}\n")
    out.write("config:\n")
    out.write("".join(f"  {line}\n" for line in (s.get("config") or "").splitlines()))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        _run(args, sys.stdout)
        sys.stdout.flush()
    except BrokenPipeError:  # e.g. `comexp-db episodes | head`
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except (CliError, ValueError, OSError, SQLAlchemyError) as exc:
        text = str(getattr(exc, "orig", None) or exc).strip().splitlines()
        line = text[0] if text else type(exc).__name__
        if line == "file is not a database":  # SQLite's words: say which file, and what
            line = f"{args.db}: not a comexp results database (SQLite: file is not a database)"
        print(f"comexp-db: error: {line}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: still one line; COMEXP_DEBUG=1 shows the traceback
        if os.environ.get("COMEXP_DEBUG") == "1":
            raise
        text = str(exc).strip().splitlines()
        detail = f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
        print(
            f"comexp-db: error: internal error ({detail}); COMEXP_DEBUG=1 shows where",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
