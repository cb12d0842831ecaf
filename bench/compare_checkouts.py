"""This checkout against another one: CPU per episode, and whether the results are the same.

    git worktree add /tmp/old 229c094 && make -C /tmp/old install
    .venv/bin/python bench/compare_checkouts.py --old /tmp/old --backend planar --speed 4 \\
        --floor aniso --episodes 24 [--rounds 2]

Each round runs the same strided slice of the job's episodes (`strided` of the checkout's own
bench helpers, every object and condition) in a fresh process of each checkout's own venv,
old then new, one worker in process, tracking on as the job has it. The other checkout may
be of an older layout (before bench/common.py and today's module names): the child program
tries today's names first, then the older ones (`_CHILD`). CPU time (`time.process_time`, the
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

# The child program: runs in a checkout's own venv as a file of its own (`run_child`), that
# checkout's bench/ on its PYTHONPATH, so that each checkout's own helpers choose and run its
# episodes. It copes with either layout, trying today's names first: bench/common.py, then an
# older checkout's bench/episode_profile.py (before bench/common.py); the episode loop in
# comexp.episode.loop, then comexp.experiment.episode, then comexp.episode; make_simulator in
# comexp.experiment.config, then comexp.experiment.simulator, then comexp.simulator.
_CHILD = r"""
import importlib, json, sys, time


def first(*names):
    # the first `module:attr` of `names` that imports; ImportError naming every failure
    failed = []
    for name in names:
        module, _, attr = name.partition(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as e:
            failed.append(f"{name}: {type(e).__name__}: {e}")
    raise ImportError("none of these imports:\n  " + "\n  ".join(failed))


def helper(name):
    # the checkout's own bench helper: bench/common.py, or bench/episode_profile.py before it
    return first(f"common:{name}", f"episode_profile:{name}")


def main(backend, floor, speed, n, out, extra):
    silenced, options, job_specs, strided = (
        helper(h) for h in ("engine_stdout_silenced", "job_backend_options", "job_specs", "strided")
    )
    run_episode = first(
        "comexp.episode.loop:run_episode",
        "comexp.experiment.episode:run_episode",
        "comexp.episode:run_episode",
    )
    make_simulator = first(
        "comexp.experiment.config:make_simulator",
        "comexp.experiment.simulator:make_simulator",
        "comexp.simulator:make_simulator",
    )
    specs = strided(job_specs(backend, floor, speed, extra), n)
    sim = make_simulator(backend, **options(backend, floor, speed, extra))
    rows = []
    with silenced(True):
        first_of_object = {}
        for s in specs:
            first_of_object.setdefault(s.object, s)
        for s in first_of_object.values():
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
    with open(out, "w") as f:
        json.dump({"cpu_s": cpu, "rows": rows}, f)


if __name__ == "__main__":
    a = sys.argv
    main(a[1], a[2], float(a[3]), int(a[4]), a[5], a[6:])
"""


def run_child(tree: Path, args: argparse.Namespace, extra: list[str]) -> dict:
    """The child program on checkout `tree`, in its venv, from a temp dir of its own: the
    checkout's bench/ is on the child's PYTHONPATH, nothing is written into the checkout."""
    with tempfile.TemporaryDirectory(prefix="comexp-compare-") as tmp:
        child, out = Path(tmp) / "compare_child.py", Path(tmp) / "out.json"
        child.write_text(_CHILD)
        cmd = [str(tree / ".venv/bin/python"), str(child), args.backend, args.floor,
               str(args.speed), str(args.episodes), str(out), *extra]  # fmt: skip
        paths = [str(tree / "bench"), os.environ.get("PYTHONPATH", "")]
        env = {**os.environ, **WORKER_THREADS, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}
        subprocess.run(cmd, cwd=tree, check=True, env=env)
        return json.loads(out.read_text())


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
