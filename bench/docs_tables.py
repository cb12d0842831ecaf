"""The docs' tables of figures, generated: figures that change with the code live as data under
docs/data/ (JSON: the table, the command that measured it, and the code version, machine and
date it was measured with), never typed into prose; this script writes such data and fills the
docs' generated blocks from it.

    .venv/bin/python bench/docs_tables.py render              # every block from docs/data/
    .venv/bin/python bench/docs_tables.py knobs               # the knob table (from the code)
    .venv/bin/python bench/docs_tables.py results --db results/planar.db --db results/pybullet.db \\
        --db results/mujoco.db                                # the study's means per backend

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
import datetime
import json
import os
import platform
import re
import subprocess
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from omegaconf import MISSING

from comexp.experiment.config import config_keys
from comexp.results.claims import CLAIM_COLUMNS, claims_records
from comexp.results.paper import ALL_OBJECTS_MEAN_CM
from comexp.results.reports import ok_error
from comexp.results.store import ResultsDB

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "data"
DOCS = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
BLOCK = re.compile(
    r"(<!-- generated: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S
)


def machine() -> dict[str, Any]:
    """What the figures were measured on: CPU model, cores, Python."""
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if "model name" in ln), model)
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "python": platform.python_version()}


def code_version() -> dict[str, Any]:
    rev = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return {"comexp": metadata.version("comexp"), "git": rev + ("+changes" if dirty else "")}


def write_table(
    name: str,
    columns: Sequence[str],
    rows: Sequence[Sequence[Any]],
    command: str,
    **provenance: Any,
) -> Path:
    """docs/data/NAME.json: the table, the command that measured it, and its provenance (the
    code version, machine and date; `provenance`: more, e.g. the studies' own revisions)."""
    DATA.mkdir(parents=True, exist_ok=True)
    path = DATA / f"{name}.json"
    meta = {**code_version(), "machine": machine(), "date": datetime.date.today().isoformat()}
    meta.update(provenance)
    data = {"meta": meta, "command": command, "columns": list(columns), "rows": list(rows)}
    path.write_text(json.dumps(data, indent=1, default=float) + "\n")
    return path


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


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("render", help="fill every generated block from docs/data/")
    sub.add_parser("knobs", help="the knob table, from the structured config")
    res = sub.add_parser("results", help="the study's means, from its databases")
    res.add_argument("--db", action="append", required=True)
    args = ap.parse_args(argv)
    if args.command == "results":
        print(results(args.db))
    for path in render():
        print(f"updated {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
