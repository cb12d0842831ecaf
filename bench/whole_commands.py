"""Whole `comexp` commands, timed as a user waits for them: a small job's fixed cost, a small
job on 1 and 2 workers, a whole study.

    .venv/bin/python bench/whole_commands.py first-job [--runs 3] [--old CHECKOUT] [--kept]
    .venv/bin/python bench/whole_commands.py scaling [--rounds 3] [--kept]
    .venv/bin/python bench/whole_commands.py study --backend planar [--kept]

`first-job`: the README's first job (`comexp backend=planar 'grid.objects=[l_shape]'
grid.coms_per_object=2`, 16 planar episodes), `--runs` times, each in a fresh folder with a
fresh database (every run runs its episodes), its output read as it arrives: the seconds from
the command's start to its first log line (imports, compose, grid), to the kernels ready, to
the last worker ready, to the episodes run, to the reports written, and to its exit; the
median of each. Then, in one Python process, `comexp.run` of the same job twice (the second
in a process that already ran one). `--old CHECKOUT` runs the same in that checkout's venv
too, alternated run by run (the machine's load hits both alike), with the ratios old / new.

`scaling`: 200 quasi-static pybullet episodes (`backend=pybullet speed=4
grid.coms_per_object=5 'grid.izz_scales=[1]' 'pusher.mu=[1.0]'`) as whole commands with
`workers=1` and `workers=2`, alternated over `--rounds`, fresh databases: each round's
speed-up of the whole command and of its episodes (the `ran N episodes in T s` line), and
their medians.

`study`: `comexp -m floor=iso,aniso speed=40,4 backend=B` once per backend: the whole
command, its jobs' episodes, and the floor the episodes set: their own time (`wall_s`) summed
over the study and shared by the workers, which no fixed cost of a job can go below.

`--kept` runs the new side's commands on a kept Ray (`comexp-ray start`, in a folder of the
bench's own, stopped at the end) after one untimed run of the same command has left its
workers warm there; without it every command starts a Ray of its own (a kept Ray the user
runs is not used). Every figure is printed; `--json docs/data/NAME.json` also writes the
table docs/performance.md shows (`bench/docs_tables.py render`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from common import write_table

FIRST_JOB = ["backend=planar", "grid.objects=[l_shape]", "grid.coms_per_object=2"]
SCALING_JOB = [
    "backend=pybullet", "speed=4", "grid.coms_per_object=5", "grid.izz_scales=[1]",
    "pusher.mu=[1.0]",
]  # fmt: skip
STUDY = ["-m", "floor=iso,aniso", "speed=40,4"]
# (phase, the output line that ends it); a phase whose line is missing takes no time
PHASES = (
    ("imports, compose, grid", re.compile(r"\d+ episodes, \d+ already stored")),
    ("kernels", re.compile(r"kernels ready|loading the compiled kernels")),
    ("Ray and workers", re.compile(r"worker \d+ ready")),
    ("episodes", re.compile(r": ran \d+ episodes")),
    ("reports", re.compile(r"^reports \(")),
)
RAN = re.compile(r": ran (\d+) episodes in ([\d.]+) s")
NOTEBOOK = r"""
import sys, time, comexp
args = sys.argv[1:]
t0 = time.perf_counter(); comexp.run([*args, "db=results/n1.db"]); first = time.perf_counter() - t0
t0 = time.perf_counter(); comexp.run([*args, "db=results/n2.db"])
second = time.perf_counter() - t0
print(f"NOTEBOOK {first:.3f} {second:.3f}")
"""


class Side:
    """A checkout's Python, and the kept-Ray folder its commands see (a kept Ray, or none)."""

    def __init__(self, python: Path, ray_dir: Path) -> None:
        self.python, self.ray_dir = python, ray_dir

    def env(self) -> dict[str, str]:
        return {
            **os.environ, "PYTHONUNBUFFERED": "1", "COMEXP_PROGRESS": "log",
            "COMEXP_RAY_DIR": str(self.ray_dir),
        }  # fmt: skip

    def command(self, args: Sequence[str], cwd: Path) -> tuple[dict[str, float], str]:
        """One whole command, its output read as it arrives: each phase's end and the exit
        (s), and the output."""
        cmd = [str(self.python), "-c", "from comexp.cli.run import main; main()", *args]
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            cmd, cwd=cwd, env=self.env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True,
        )  # fmt: skip
        ends: dict[str, float] = {}
        lines = []
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            now = time.perf_counter() - t0
            for name, pattern in PHASES:
                if pattern.search(line):
                    ends[name] = now  # the last such line: the last worker, the kernels' end
        if proc.wait() != 0:
            tail = "".join(lines[-5:])
            raise SystemExit(f"`comexp {' '.join(args)}` failed in {cwd}:\n{tail}")
        ends["exit"] = time.perf_counter() - t0
        return ends, "".join(lines)

    def notebook(self, args: Sequence[str], cwd: Path) -> tuple[float, float]:
        out = subprocess.run(
            [str(self.python), "-c", NOTEBOOK, *args], cwd=cwd, capture_output=True, text=True,
            env=self.env(),
        )  # fmt: skip
        m = re.search(r"NOTEBOOK ([\d.]+) ([\d.]+)", out.stdout)
        if m is None:
            raise SystemExit(f"comexp.run failed: {out.stderr.strip().splitlines()[-1:]}")
        return float(m[1]), float(m[2])


@contextlib.contextmanager
def kept_ray(side: Side) -> Iterator[None]:
    """A kept Ray for `side`'s commands (`comexp-ray start` in its folder), stopped after."""
    cmd = [str(side.python), "-m", "comexp.cli.kept_ray"]
    start = subprocess.run([*cmd, "start"], env=side.env(), capture_output=True, text=True)
    if start.returncode != 0:
        raise SystemExit(f"comexp-ray start failed: {start.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run([*cmd, "stop"], env=side.env(), capture_output=True)


def phase_durations(ends: dict[str, float]) -> dict[str, float]:
    """Each phase's own seconds (a missing phase: 0), and the whole command."""
    out, last = {}, 0.0
    for name, _ in PHASES:
        end = ends.get(name, last)
        out[name] = end - last
        last = max(last, end)
    out["exit"] = ends["exit"] - last
    out["whole command"] = ends["exit"]
    return out


def episodes_s(output: str) -> float:
    """The seconds the command's jobs spent running episodes (their `ran N episodes` lines)."""
    return sum(float(m[2]) for m in RAN.finditer(output))


def _print(title: str, columns: Sequence[str], rows: Sequence[Sequence]) -> None:
    print(title)
    for row in [columns, *rows]:
        print("  ".join(f"{c:>10.3f}" if isinstance(c, float) else f"{c!s:>34}" for c in row))


def first_job(sides: dict[str, Side], runs: int, tmp: Path) -> tuple[list[str], list[list]]:
    timed: dict[str, list[dict[str, float]]] = {s: [] for s in sides}
    for side in sides.values():
        if _kept(side):
            (tmp / "warm").mkdir(exist_ok=True)
            side.command([*FIRST_JOB, "db=results/w.db"], tmp / "warm")  # leaves workers warm
    for i in range(runs):
        for name, side in sides.items():
            cwd = tmp / f"{name}-{i}".replace(" ", "_").replace(",", "")
            cwd.mkdir()
            timed[name].append(phase_durations(side.command([*FIRST_JOB, "db=r.db"], cwd)[0]))
    nb = {}
    for name, side in sides.items():
        cwd = tmp / f"{name}-notebook".replace(" ", "_").replace(",", "")
        cwd.mkdir()
        nb[name] = side.notebook(FIRST_JOB, cwd)
    names = [n for n, _ in PHASES] + ["exit", "whole command"]
    med = {s: {n: statistics.median(r[n] for r in timed[s]) for n in names} for s in sides}
    rows = [[n, *(med[s][n] for s in sides)] for n in names]
    rows.append(["comexp.run, first in a process", *(nb[s][0] for s in sides)])
    rows.append(["comexp.run, the next one", *(nb[s][1] for s in sides)])
    columns = ["phase (s, median)", *sides]
    if "old" in sides:
        columns.append("old / new")
        for row in rows:
            row.append(row[1] / row[2] if row[2] > 0 else None)
    _print(f"the README's first job (16 planar episodes), {runs} runs each", columns, rows)
    return columns, rows


def scaling(side: Side, rounds: int, tmp: Path) -> tuple[list[str], list[list]]:
    if _kept(side):
        (tmp / "warm").mkdir()
        side.command([*SCALING_JOB, "workers=2", "db=w.db"], tmp / "warm")
    whole: dict[int, list[float]] = {1: [], 2: []}
    eps: dict[int, list[float]] = {1: [], 2: []}
    for r in range(rounds):
        for workers in (1, 2):
            cwd = tmp / f"r{r}w{workers}"
            cwd.mkdir()
            ends, out = side.command([*SCALING_JOB, f"workers={workers}", "db=s.db"], cwd)
            whole[workers].append(ends["exit"])
            eps[workers].append(episodes_s(out))
            print(f"round {r + 1}, {workers} worker(s): whole command {ends['exit']:.2f} s, "
                  f"episodes {eps[workers][-1]:.2f} s", flush=True)  # fmt: skip
    columns = ["200 quasi-static pybullet episodes", "1 worker (s)", "2 workers (s)", "speed-up"]
    rows = []
    for what, t in (("whole command", whole), ("its episodes", eps)):
        ups = [a / b for a, b in zip(t[1], t[2], strict=True)]
        rows.append([f"{what}, median of {rounds}", statistics.median(t[1]),
                     statistics.median(t[2]), statistics.median(ups)])  # fmt: skip
        rows.append([f"{what}, each round's speed-up", None, None,
                     " ".join(f"{u:.2f}" for u in ups)])  # fmt: skip
    _print("whole commands, 1 and 2 workers alternated", columns, rows)
    return columns, rows


def study(side: Side, backends: Sequence[str], tmp: Path) -> tuple[list[str], list[list]]:
    columns = ["backend", "whole command (s)", "its jobs' episodes (s)", "fixed cost (s)",
               "episodes' own time / 2 workers (s)"]  # fmt: skip
    rows = []
    for backend in backends:
        cwd = tmp / f"study-{backend}"
        cwd.mkdir()
        ends, out = side.command([*STUDY, f"backend={backend}", "db=s.db"], cwd)
        ran = episodes_s(out)
        with sqlite3.connect(cwd / "s.db") as c:
            busy = c.execute("select sum(wall_s) from episodes").fetchone()[0] or 0.0
        rows.append([backend, ends["exit"], ran, ends["exit"] - ran, busy / 2])
        print(f"{backend}: whole command {ends['exit']:.1f} s, episodes {ran:.1f} s, "
              f"episodes' own time {busy:.1f} s over 2 workers", flush=True)  # fmt: skip
    _print("the whole study, per backend", columns, rows)
    return columns, rows


def _kept(side: Side) -> bool:
    return side.ray_dir.name == "kept"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    fj = sub.add_parser("first-job", help="the README's first job, phase by phase")
    fj.add_argument("--runs", type=int, default=3)
    fj.add_argument("--old", type=Path, help="another checkout (its .venv), run alternately")
    sc = sub.add_parser("scaling", help="200 pybullet episodes on 1 and 2 workers")
    sc.add_argument("--rounds", type=int, default=3)
    st = sub.add_parser("study", help="the whole study on each backend")
    st.add_argument("--backend", nargs="+", default=["planar"])
    for p in (fj, sc, st):
        p.add_argument("--kept", action="store_true", help="the new side on a kept Ray")
        p.add_argument("--json", type=Path, help="write the table (docs/data/NAME.json)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cxw-", dir="/tmp") as t:  # short: Ray's sockets
        tmp = Path(t)
        own = Side(Path(sys.executable), tmp / "own")
        kept = Side(Path(sys.executable), tmp / "kept")
        sides = {"new": own}
        if args.what == "first-job" and args.old is not None:
            sides = {"old": Side(args.old / ".venv" / "bin" / "python", tmp / "own"), **sides}
        with kept_ray(kept) if args.kept else contextlib.nullcontext():
            if args.what == "first-job":
                if args.kept:
                    sides["new, kept Ray"] = kept
                columns, rows = first_job(sides, args.runs, tmp)
            elif args.what == "scaling":
                columns, rows = scaling(kept if args.kept else own, args.rounds, tmp)
            else:
                columns, rows = study(kept if args.kept else own, args.backend, tmp)
    if args.json is not None:
        argv_text = " ".join(sys.argv[1:] if argv is None else argv)
        argv_text = re.sub(r"\s*--json \S+", "", argv_text)
        argv_text = re.sub(r"--old \S+", "--old OLD_CHECKOUT", argv_text)
        command = f"python bench/whole_commands.py {argv_text}"
        print(write_table(args.json.stem, columns, rows, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
