"""The fixed cost of a small job: where the seconds of the README's first job go.

    .venv/bin/python bench/job_overhead.py [--runs 3] [--old /path/to/other/checkout] [--json F]

Runs the README's first job (`comexp backend=planar 'grid.objects=[l_shape]'
grid.coms_per_object=2`, 16 planar episodes) as a whole command, `--runs` times, each in a fresh
folder with a fresh database (so every run runs its episodes), and reads its output as it
arrives: the seconds from the command's start to its first log line (imports, compose, grid),
to the kernels ready (`kernels ready`), to the last worker ready, to the episodes run, to the
reports written, and to its exit; the median of each. With `--old CHECKOUT` the same job runs
in that checkout's venv too, the two alternated run by run (the machine's load hits both
alike), and the ratios old / new are printed. Then, in one Python process, `comexp.run` of the
same job twice (the second in a process that already ran one: its workers kept).

Every figure is printed; `--json docs/data/job-overhead.json` also writes the table that
docs/performance.md shows (`bench/docs_tables.py render`).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from docs_tables import write_table

ROOT = Path(__file__).resolve().parents[1]
JOB = ["backend=planar", "grid.objects=[l_shape]", "grid.coms_per_object=2", "db=results/o.db"]
# (phase, the output line that ends it); a phase whose line is missing takes no time
PHASES = (
    ("imports, compose, grid", re.compile(r"\d+ episodes, \d+ already stored")),
    ("kernels", re.compile(r"kernels ready|loading the compiled kernels")),
    ("Ray and workers", re.compile(r"worker \d+ ready")),
    ("episodes", re.compile(r": ran \d+ episodes")),
    ("reports", re.compile(r"^reports \(")),
)
NOTEBOOK = r"""
import sys, time, comexp
args = sys.argv[1:]
t0 = time.perf_counter(); comexp.run(args); first = time.perf_counter() - t0
t0 = time.perf_counter(); comexp.run([*args[:-1], "db=results/o2.db"])
second = time.perf_counter() - t0
print(f"NOTEBOOK {first:.3f} {second:.3f}")
"""


def run_once(python: Path, cwd: Path) -> dict[str, float]:
    """One whole command, its output read as it arrives: each phase's end and the exit (s)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COMEXP_PROGRESS": "log"}
    cmd = [str(python), "-c", "from comexp.cli.run import main; main()", *JOB]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    ends: dict[str, float] = {}
    assert proc.stdout is not None
    for line in proc.stdout:
        now = time.perf_counter() - t0
        for name, pattern in PHASES:
            if pattern.search(line):
                ends[name] = now  # the last such line: the last worker, the kernels' end
    if proc.wait() != 0:
        raise SystemExit(f"the job failed in {cwd} (exit {proc.returncode})")
    ends["exit"] = time.perf_counter() - t0
    return ends


def durations(ends: dict[str, float]) -> dict[str, float]:
    """Each phase's own seconds (a missing phase: 0), and the whole command."""
    out, last = {}, 0.0
    for name, _ in PHASES:
        end = ends.get(name, last)
        out[name] = end - last
        last = max(last, end)
    out["exit"] = ends["exit"] - last
    out["whole command"] = ends["exit"]
    return out


def notebook(python: Path, cwd: Path) -> tuple[float, float]:
    out = subprocess.run(
        [str(python), "-c", NOTEBOOK, *JOB],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={**os.environ, "COMEXP_PROGRESS": "log"},
    )
    m = re.search(r"NOTEBOOK ([\d.]+) ([\d.]+)", out.stdout)
    if m is None:
        raise SystemExit(f"comexp.run failed: {out.stderr.strip().splitlines()[-1:]}")
    return float(m[1]), float(m[2])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--old", type=Path, help="another checkout (its .venv), run alternately")
    ap.add_argument("--json", type=Path, help="write the table (docs/data/job-overhead.json)")
    args = ap.parse_args()
    sides = {"new": Path(sys.executable)}
    if args.old is not None:
        sides = {"old": args.old / ".venv" / "bin" / "python", **sides}
    runs: dict[str, list[dict[str, float]]] = {s: [] for s in sides}
    with tempfile.TemporaryDirectory(prefix="comexp-overhead-") as tmp:
        for i in range(args.runs):
            for side, python in sides.items():
                cwd = Path(tmp) / f"{side}{i}"
                cwd.mkdir()
                runs[side].append(durations(run_once(python, cwd)))
        nb = {}
        for side, python in sides.items():
            (Path(tmp) / f"{side}-notebook").mkdir()
            nb[side] = notebook(python, Path(tmp) / f"{side}-notebook")
    names = [n for n, _ in PHASES] + ["exit", "whole command"]
    med = {s: {n: statistics.median(r[n] for r in runs[s]) for n in names} for s in sides}
    rows = [[n, *(med[s][n] for s in sides)] for n in names]
    rows.append(["comexp.run, first in a process", *(nb[s][0] for s in sides)])
    rows.append(["comexp.run, the next one", *(nb[s][1] for s in sides)])
    columns = ["phase (s, median)", *sides]
    if "old" in sides:
        columns.append("old / new")
        for row in rows:
            row.append(row[1] / row[2] if row[2] > 0 else None)
    print(f"the README's first job (16 planar episodes), {args.runs} runs each")
    for row in [columns, *rows]:
        print("  ".join(f"{c:>10.3f}" if isinstance(c, float) else f"{c!s:>30}" for c in row))
    if args.json is not None:
        command = "python bench/job_overhead.py" + (
            f" --runs {args.runs}" if args.runs != 3 else ""
        )
        print(write_table(args.json.stem, columns, rows, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
