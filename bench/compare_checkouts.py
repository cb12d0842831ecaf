"""This checkout against another one: CPU per episode, and whether the results are the same.

    git worktree add /tmp/old 229c094 && make -C /tmp/old install
    .venv/bin/python bench/compare_checkouts.py --old /tmp/old --backend planar --speed 4 \\
        --floor aniso --episodes 24 [--rounds 2]

Each round runs the same strided slice of the job's episodes (`episode_profile.strided`, every
object and condition) in a fresh process of each checkout's own venv, old then new, one
worker in process, tracking on as the job has it. CPU time (`time.process_time`, the
process's own: robust to other load on a shared machine) is summed over the episodes after a
warm-up episode per object (Numba's cache, MuJoCo's renderers). The ratio old / new of each
round is printed, and the episodes' results (estimate, status, every push's measured and true
rotation) are compared: `identical` counts episodes equal to the last bit; where they differ
the mean errors and the per-push tracking error (|measured - true| rotation) of each side
are printed, so a change that moves results shows by how much.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

# A pool worker's thread pools, for either checkout: Ray sets OMP_NUM_THREADS=1 in its workers,
# and a worker runs OpenCV on one thread (`comexp.workers.actor.use_one_cpu`, which an older
# checkout lacks: OpenCV reads this variable when it loads)
WORKER_THREADS = {"OMP_NUM_THREADS": "1", "OPENCV_FOR_THREADS_NUM": "1"}

# Runs inside a checkout's venv, with that checkout's bench/ on the path.
_CHILD = r"""
import json, sys, time
sys.path.insert(0, "bench")
from episode_profile import engine_stdout_silenced, job_backend_options, job_specs, strided
from comexp.experiment.episode import run_episode
from comexp.experiment.simulator import make_simulator
backend, floor, out = sys.argv[1], sys.argv[2], sys.argv[5]
speed, n, extra = float(sys.argv[3]), int(sys.argv[4]), sys.argv[6:]
specs = strided(job_specs(backend, floor, speed, extra), n)
sim = make_simulator(backend, **job_backend_options(backend, floor, speed, extra))
rows = []
with engine_stdout_silenced(True):
    first = {}
    for s in specs:
        first.setdefault(s.object, s)
    for s in first.values():
        run_episode(s, sim)
    cpu = time.process_time()
    for s in specs:
        r = run_episode(s, sim)
        rows.append({
            "status": r.status, "error_cm": r.error_cm, "est": r.est_com_cm,
            "pushes": [[p.rotation_deg, p.rotation_true_deg] for p in r.pushes],
        })
    cpu = time.process_time() - cpu
sim.close()
json.dump({"cpu_s": cpu, "rows": rows}, open(out, "w"))
"""


def run_child(tree: Path, args: argparse.Namespace, extra: list[str]) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        out = f.name
    cmd = [str(tree / ".venv/bin/python"), "-c", _CHILD, args.backend, args.floor,
           str(args.speed), str(args.episodes), out, *extra]  # fmt: skip
    subprocess.run(cmd, cwd=tree, check=True, env={**os.environ, **WORKER_THREADS})
    return json.loads(Path(out).read_text())


def tracking_error(rows: list[dict]) -> np.ndarray:
    return np.array(
        [abs(m - t) for r in rows for m, t in r["pushes"] if m is not None and t is not None]
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, required=True, help="the other checkout (with .venv)")
    ap.add_argument("--new", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--backend", choices=("planar", "pybullet", "mujoco"), default="planar")
    ap.add_argument("--floor", choices=("iso", "aniso"), default="iso")
    ap.add_argument("--speed", type=float, default=40.0)
    ap.add_argument("--episodes", type=int, default=24)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument(
        "--new-override", action="append", default=[], help="e.g. camera.renderer=engine"
    )
    args = ap.parse_args()
    print(f"{args.backend} {args.floor} {args.speed:g} cm/s, {args.episodes} episodes, "
          f"old {args.old} / new {args.new} {' '.join(args.new_override)}")  # fmt: skip
    ratios = []
    for k in range(args.rounds):
        old = run_child(args.old, args, [])
        new = run_child(args.new, args, args.new_override)
        n = len(new["rows"])
        ratios.append(old["cpu_s"] / new["cpu_s"])
        print(f"round {k + 1}: CPU ms/episode old {old['cpu_s'] / n * 1e3:.0f}, "
              f"new {new['cpu_s'] / n * 1e3:.0f}: old / new {ratios[-1]:.2f}")  # fmt: skip
    same = sum(a == b for a, b in zip(old["rows"], new["rows"], strict=True))
    print(f"old / new CPU: {' '.join(f'{r:.2f}' for r in ratios)}")
    print(f"identical episodes: {same} of {n}")
    if same < n:
        for name, d in (("old", old), ("new", new)):
            err = [r["error_cm"] for r in d["rows"] if r["error_cm"] is not None]
            te = tracking_error(d["rows"])
            print(f"{name}: mean error {np.mean(err):.4f} cm over {len(err)} ok; tracking "
                  f"|measured - true| mean {te.mean():.3f} p95 {np.percentile(te, 95):.3f} "
                  f"max {te.max():.3f} deg over {len(te)} pushes")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
