"""The maintained benchmarks: bench/ holds the scripts docs/performance.md's table names (at
most ten), each runs on a tiny input and prints its figures, and a bench that measures other
physics than the job's, or whose episodes all fail, is caught here before it prints figures
that mean nothing.

Most scripts run in this process (`runpy`, as `python bench/X.py` would: the imports are paid
once for the suite); the Ray-backed runs and a second checkout's child processes are `slow`,
with a cheaper check of the same script in the default suite."""

from __future__ import annotations

import collections
import itertools
import json
import os
import re
import runpy
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
sys.path.insert(0, str(BENCH))

from episode_profile import job_backend_options, job_specs  # noqa: E402

from comexp.experiment.simulator import physics_identity  # noqa: E402

NUMBER = r"([-+]?\d[\d,]*\.?\d*(?:e[-+]?\d+)?)"


def figure(pattern: str, text: str) -> float:
    """The number that `pattern`'s `{n}` stands for in `text` (the first match)."""
    m = re.search(pattern.replace("{n}", NUMBER), text)
    assert m, f"no {pattern!r} in:\n{text}"
    return float(m.group(1).replace(",", ""))


def run_bench(name: str, *args: str, monkeypatch: pytest.MonkeyPatch, capfd) -> str:
    """`python bench/<name> <args>` in this process; its standard output (fd 1: the scripts
    silence the engines' C++ prints at the descriptor)."""
    monkeypatch.setattr(sys, "argv", [str(BENCH / name), *args])
    capfd.readouterr()
    try:
        runpy.run_path(str(BENCH / name), run_name="__main__")
    except SystemExit as e:
        assert e.code in (None, 0), f"bench/{name} exited with {e.code}"
    return capfd.readouterr().out


def bench_table() -> list[str]:
    """The script names of docs/performance.md's table, in its order."""
    text = (ROOT / "docs" / "performance.md").read_text()
    head = text.index("| script | what it measures |")
    rows = text[head:].split("\n\n", 1)[0].splitlines()[2:]
    return [n for row in rows for n in re.findall(r"`bench/([\w.]+)`", row.split("|")[1])]


# --- what bench/ holds ---------------------------------------------------------------------


def test_bench_holds_the_scripts_docs_performance_names_at_most_ten():
    named = bench_table()
    on_disk = sorted(p.name for p in BENCH.iterdir() if p.is_file())
    assert len(named) == len(set(named)), "a script named twice in the table"
    assert sorted(named) == on_disk, "bench/ and docs/performance.md's table differ"
    assert len(on_disk) <= 10, "bench/ keeps at most ten maintained benchmarks"


def test_every_bench_script_has_a_smoke_test():
    """Each script of the table is run by a test of this module (its file name in the code)."""
    source = Path(__file__).read_text()
    for name in bench_table():
        assert source.count(f'"{name}"') >= 1 or f"import {name[:-3]}\n" in source, name


def test_docs_cite_removed_bench_scripts_with_the_commit_that_holds_them():
    """A figure measured with a script since removed says where git keeps it."""
    has_git = shutil.which("git") and (ROOT / ".git").exists()
    for doc in DOCS:
        text = doc.read_text()
        for name in sorted(set(re.findall(r"bench/([\w]+\.(?:py|sh))", text))):
            if (BENCH / name).exists():
                continue
            shown = re.findall(rf"git show ([0-9a-f]{{7,40}}):bench/{re.escape(name)}", text)
            assert shown, f"{doc.name} cites bench/{name}, which is gone, without `git show`"
            if has_git:
                for commit in set(shown):
                    r = subprocess.run(
                        ["git", "cat-file", "-e", f"{commit}:bench/{name}"],
                        cwd=ROOT,
                        capture_output=True,
                    )
                    assert r.returncode == 0, f"{doc.name}: {commit} holds no bench/{name}"


@pytest.mark.parametrize("backend", ["planar", "pybullet", "mujoco"])
def test_bench_pools_run_the_physics_the_episodes_name(backend):
    """bench/scaling.py and bench/memory.py start their pools with these options; without
    them every worker refused every episode as `physics_mismatch`, and the benches printed
    the timings of 200 refusals."""
    spec = job_specs(backend)[0]
    assert physics_identity(backend, options=job_backend_options(backend)) == spec.physics
    assert physics_identity(backend) != spec.physics or backend == "planar"


# --- one in-process worker -----------------------------------------------------------------


def test_episode_profile_smoke(tmp_path, monkeypatch, capfd):
    dump = tmp_path / "eps.json"
    out = run_bench(
        "episode_profile.py",
        *("--backend", "planar", "--episodes", "1", "--raw-seconds", "0.01"),
        *("--dump", str(dump)),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert "status              {'ok': 1}" in out
    assert figure(r"CPU ms/episode\s+{n}", out) > 0
    assert figure(r"steps/s in pushes\s+{n}", out) > 0
    assert figure(r"physics \(sim.push\)\s+{n}%", out) > 0
    assert len(json.loads(dump.read_text())) == 1


def test_episode_profile_times_the_still_steps_jumped_against_stepped(monkeypatch, capfd):
    out = run_bench(
        "episode_profile.py",
        *("--backend", "pybullet", "--episodes", "2", "--still-jumps"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert figure(r"stepped / jumped {n}", out) > 0
    assert figure(r"jumped {n},", out) > 0
    assert "episode errors identical in" in out
    assert figure(r"true turn, jumped - stepped: max {n} deg", out) >= 0
    assert figure(r"tilt where a jump starts: max {n} deg", out) < 0.1  # StillJumps' bound


def test_episode_profile_cprofile_names_the_compiled_step(monkeypatch, capfd):
    out = run_bench(
        "episode_profile.py",
        *("--backend", "planar", "--episodes", "1", "--cprofile", "40"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert figure(r"CPU {n} ms/episode", out) > 0
    assert "episode.py:" in out and "(run_episode)" in out
    step = re.search(
        r"\n\s+([\d.]+)%\s+[\d.]+\s+[\d.]+\s+comexp\.backends\.planar_sim\._run_chunks "
        r"\(compiled\)",
        out,
    )
    assert step and 0 < float(step.group(1)) < 100


def test_step_cost_smoke(monkeypatch, capfd):
    """pybullet's engine step is its compiled chunk (`_push_steps_call`) timed in the pushes,
    less the friction kernel's replay; the module's call is put back afterwards."""
    from comexp.backends import pybullet_sim

    call = pybullet_sim._push_steps_call
    out = run_bench(
        "step_cost.py",
        *("--backend", "pybullet", "--episodes", "1", "--raw-steps", "20"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert pybullet_sim._push_steps_call is call
    step = figure(r"step inside a push\s+{n} us", out)
    parts = [figure(rf"{k}\s+{{n}} us", out) for k in ("engine's step", "friction kernel")]
    assert step > 0 and all(p > 0 for p in parts)
    assert figure(r"our Python\s+{n} us", out) == pytest.approx(step - sum(parts), abs=0.2)
    assert figure(r"resting scene: {n} us", out) > 0
    engine_floor = figure(r"\(the engine's steps in pushes \+ renders\): episode {n}x", out)
    model_floor = figure(r"\(\+ the friction kernel\): episode {n}x", out)
    assert engine_floor > model_floor > 1


def test_step_cost_planar_times_its_compiled_chunks(monkeypatch, capfd):
    """planar's step is its compiled chunk (`_run_call`, the friction solve inside): timed in
    the pushes, no separate kernel, and the module's call put back afterwards."""
    from comexp.backends import planar_sim

    call = planar_sim._run_call
    out = run_bench(
        "step_cost.py",
        *("--backend", "planar", "--episodes", "1", "--raw-steps", "20"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert planar_sim._run_call is call
    step = figure(r"step inside a push\s+{n} us", out)
    engine = figure(r"engine's step\s+{n} us", out)
    assert 0 < engine < step
    assert figure(r"friction kernel\s+{n} us", out) == 0
    assert "planar's is inside its step" in out
    assert figure(r"our Python\s+{n} us", out) == pytest.approx(step - engine, abs=0.2)
    # the tracker's work inside the pushes is perception: apart, not in the step
    assert 0 < figure(r"tracking in pushes {n} ms", out) < figure(r"the rest \(.*?\) {n} ms", out)
    engine_floor = figure(r"\(the engine's steps in pushes \+ renders\): episode {n}x", out)
    assert engine_floor == figure(r"\(\+ the friction kernel\): episode {n}x", out) > 1


def test_planar_speed_smoke(monkeypatch, capfd):
    out = run_bench("planar_speed.py", "--pushes", "2", monkeypatch=monkeypatch, capfd=capfd)
    assert figure(r"{n} pushes: ", out) == 2
    assert figure(r"pushes: {n} ms per push", out) > 0
    assert out.count(" ok ") == 2
    out = run_bench(
        "planar_speed.py", "--pushes", "2", "--self-noise", monkeypatch=monkeypatch, capfd=capfd
    )
    assert 0 <= figure(r"under a 1e-15 m nudge: {n} deg", out) < 0.1
    out = run_bench(
        "planar_speed.py", "--pushes", "2", "--resolutions", monkeypatch=monkeypatch, capfd=capfd
    )
    assert "| 400 | 1 | 5 | x1.00 | 0.000 | 0.000 | 0.0000 |" in out  # the default, itself
    assert figure(r"\| 100 \| 2 \| 5 \| x{n} \|", out) > 1.0  # coarser is cheaper
    out = run_bench(
        "planar_speed.py", "--pushes", "2", "--passes", monkeypatch=monkeypatch, capfd=capfd
    )
    assert figure(r"Newton pass over {n} samples", out) > 300
    assert figure(r"Newton pass over \d+ samples: {n} us", out) > 0
    assert figure(r"line search pass over \d+ samples: {n} us", out) > 0
    out = run_bench("planar_speed.py", "--convergence", monkeypatch=monkeypatch, capfd=capfd)
    rows = [r for r in out.splitlines() if r.startswith(("| 0.1 |", "| 1.0 |"))]
    assert len(rows) == 4
    for r in rows:  # the default near the finest (0.25 ms, every step: docs/physics.md, 1.0%)
        rot = [float(x) for x in r.strip("| ").split(" | ")[2:]]
        assert len(rot) == 7 and abs(rot[0] - rot[-1]) < 0.015 * abs(rot[-1])


def test_tracking_smoke(monkeypatch, capfd):
    """tracking.py wraps the episode's perception names and `PoseTracker.track` for good (a
    process of its own would not care): restored here after the run."""
    from tracking import SWAPPED

    import comexp.backends.planar_sim as planar_sim
    import comexp.experiment.episode as episode_module

    for k in SWAPPED:
        monkeypatch.setattr(episode_module, k, getattr(episode_module, k))
    monkeypatch.setattr(episode_module.PoseTracker, "track", episode_module.PoseTracker.track)
    monkeypatch.setattr(planar_sim, "render_prism_depth", planar_sim.render_prism_depth)
    out = run_bench(
        "tracking.py",
        *("--backend", "planar", "--episodes", "1", "--fps", "0,30"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert figure(r"\|\s+0 fps \|\s+{n}/1", out) == 1
    assert figure(r"\|\s+30 fps \|\s+{n}/1", out) == 1
    assert figure(r"30 fps: tracking \(.*?\) {n} ms CPU per frame", out) > 0
    assert figure(r"30 fps: {n} tracking renders", out) > 0


def test_engine_agreement_smoke(monkeypatch, capfd):
    out = run_bench(
        "engine_agreement.py",
        *("--pushes", "4", "--engines", "pybullet"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert figure(r"engine agreement: {n} first pushes", out) == 4
    row = next(line for line in out.splitlines() if line.startswith("| pybullet |"))
    assert figure(r"\| pybullet \| {n} \(0 pushes failed\)", row) >= 1
    assert 0 <= figure(r"\| {n}% \| [\d.]+% \|", row) < 100
    assert figure(r"\| [\d.]+% \| {n}% \|", row) > 50


def test_engine_agreement_tipping_smoke(monkeypatch, capfd):
    out = run_bench(
        "engine_agreement.py",
        *("--tipping", "--d-cm", "1.3", "0.3", "--engines", "pybullet"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    rows = [line for line in out.splitlines() if re.match(r"\| 0\.30 \| 40 \|", line)]
    assert rows == ["| 0.30 | 40 | tips over | tips over |"]
    assert figure(r"\| 1\.30 \| 4 \| stays up, {n} \|", out) < 1.0


# --- two checkouts ---------------------------------------------------------------------------


def test_compare_checkouts_smoke(tmp_path, monkeypatch, capfd):
    """The comparison on this checkout against itself, each side's child program run in this
    process (the real child processes: the slow test below)."""
    import compare_checkouts

    sides = iter(range(100))

    def child_here(tree: Path, args, extra: list[str]) -> dict:
        out = tmp_path / f"side{next(sides)}.json"
        argv = ["-c", args.backend, args.floor, str(args.speed), str(args.episodes), str(out)]
        with monkeypatch.context() as m:
            m.chdir(tree)
            m.setattr(sys, "argv", [*argv, *extra])
            m.setattr(sys, "path", list(sys.path))
            child = compile(compare_checkouts._CHILD, "compare_checkouts child", "exec")
            exec(child, {"__name__": "__main__"})  # noqa: S102 - the script's own child program
        return json.loads(out.read_text())

    monkeypatch.setattr(compare_checkouts, "run_child", child_here)
    monkeypatch.setattr(
        sys,
        "argv",
        ["compare_checkouts.py", "--old", str(ROOT), "--episodes", "1", "--rounds", "1"],
    )
    capfd.readouterr()
    assert compare_checkouts.main() == 0
    out = capfd.readouterr().out
    assert figure(r"identical episodes: {n} of 1", out) == 1
    assert figure(r"round 1: CPU ms/episode old {n}", out) > 0
    assert figure(r"old / new CPU: {n}", out) > 0


@pytest.mark.slow
def test_compare_checkouts_runs_each_checkout_in_its_venv():
    r = subprocess.run(
        [sys.executable, str(BENCH / "compare_checkouts.py"), "--old", str(ROOT)]
        + ["--episodes", "1", "--rounds", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert figure(r"identical episodes: {n} of 1", r.stdout) == 1


# --- the pool: Ray ---------------------------------------------------------------------------


def test_memory_samples_a_process_tree(capfd):
    """memory.py's sampler and report on this process and a child, without Ray."""
    import memory

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        sampler = memory.TreeSampler(os.getpid(), 0.05).start()
        sampler.sample()
        sampler.stop()
        start = {child.pid: memory.memory_kb(child.pid)["rss"]}
        o = {
            "backend": "pybullet",
            "episodes": 0,
            "workers": 1,
            "elapsed_s": 0.1,
            "stats": types.SimpleNamespace(failed=0, failures=collections.Counter()),
            "sampler": sampler,
            "worker_pids": [child.pid],
            "start_rss": start,
            "end_rss": start,
            "driver_maxrss_kb": 1,
        }
        capfd.readouterr()
        memory.report(o)
    finally:
        child.kill()
        child.wait()
    out = capfd.readouterr().out
    assert {os.getpid(), child.pid} <= set(sampler.procs)
    assert figure(r"peak total over the tree: PSS {n} MB", out) > 0
    assert figure(rf"worker {child.pid}: RSS after start {{n}} MB", out) > 0
    assert re.search(r"^driver ", out, re.M)


def test_scaling_reports_runs(capfd):
    """scaling.py's figures from two runs (made up), and its /proc CPU readings, without Ray."""
    import scaling

    busy, total = scaling.machine_cpu_s()
    assert 0 < busy <= total
    assert scaling._tree_cpu(os.getpid())[os.getpid()] > 0

    def run(workers: int, elapsed: float) -> scaling.Run:
        return scaling.Run(
            workers, 0.5, elapsed, 4.0 * workers, 0.01, 4.0, 0.1, 0.1, 2 * elapsed, 0, {},
            {"a": 0.5}, 1.0,
        )  # fmt: skip

    setup = {
        "hydra_grid_s": 0.1, "resume_query_s": 0.1, "kernels_and_ray_s": 2.1, "ray_start_s": 2.0
    }  # fmt: skip
    capfd.readouterr()
    scaling.report("pybullet", 8, setup, [run(1, 4.0), run(2, 2.5)])
    out = capfd.readouterr().out
    assert "results of 2 workers identical to 1: True" in out
    assert figure(r"\n\s+2\s+[\d.]+\s+[\d.]+s\s+[\d.]+s\s+[\d.]+\s+{n}", out) == 1.6  # speed-up

    # --rounds: each round's speed-up over its own first count, and their median
    runs = [run(1, 4.0), run(2, 2.5), run(1, 5.0), run(2, 2.5), run(1, 4.0), run(2, 2.0)]
    scaling.report("pybullet", 8, setup, runs, rounds=3)
    out = capfd.readouterr().out
    assert "speed-up of 2 workers over 1, per round: 1.60, 2.00, 2.00 (median 2.00)" in out
    rows = re.findall(r"\n\s+2\s+[\d.]+\s+[\d.]+s\s+[\d.]+s\s+[\d.]+\s+([\d.]+)", out)
    assert rows == ["1.60", "2.00", "2.00"]
    assert out.count("results of 2 workers identical to 1: True") == 3


@pytest.mark.slow
@pytest.mark.parametrize(
    "args, pattern",
    [
        (("memory.py", "--episodes", "1", "--workers", "1", "--interval", "0.2"),
         r"peak total over the tree: PSS {n} MB"),
        (("scaling.py", "--episodes", "2", "--workers", "1"), r"Ray start {n} s"),
    ],
    ids=["memory", "scaling"],
)  # fmt: skip
def test_pool_benches_run_a_job_through_ray(args, pattern):
    r = subprocess.run(
        [sys.executable, str(BENCH / args[0]), *args[1:]],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    assert figure(pattern, r.stdout) > 0
    assert re.search(r"failed episodes: 1w 0 |, 0 failed,", r.stdout), r.stdout


# --- study databases -------------------------------------------------------------------------


def small_study(path: Path, source: str, seed: int) -> list[float]:
    """3 objects x 3 CoMs x 2 speeds on two backends into `path`; the errors, in order."""
    from test_db import make_result

    from comexp.experiment.episode import EstimatorSettings
    from comexp.results.store import ResultsDB

    rng = np.random.default_rng(seed)
    est = EstimatorSettings(rotation_source=source)
    results = [
        make_result(
            object=o,
            com_index=c,
            backend=b,
            speed_cm_s=s,
            estimator=est,
            error_cm=float(rng.gamma(2.0, 0.3)),
        )  # fmt: skip
        for b, o, c, s in itertools.product(
            ("mujoco", "pybullet"), ("obj1", "obj2", "obj3"), range(3), (40.0, 4.0)
        )
    ]
    db = ResultsDB(path)
    try:
        db.add_results(db.start_sweep(job_name=source), results)
    finally:
        db.close()
    return [r.error_cm for r in results]


def test_study_report_smoke(tmp_path, monkeypatch, capfd):
    errors = small_study(tmp_path / "study.db", "vision", 0)
    out = run_bench(
        "study_report.py", "--db", str(tmp_path / "study.db"), monkeypatch=monkeypatch, capfd=capfd
    )
    pybullet_40 = errors[18::2]  # backend-major, speed innermost
    row = next(
        x for x in out.splitlines() if x.startswith("| pybullet, floor iso") and "| 40 |" in x
    )
    assert figure(r"\| 40 \| 9 \| 9 \| {n} \|", row) == pytest.approx(
        np.mean(pybullet_40), abs=6e-4
    )
    assert "## Cross-backend agreement" in out


def test_vision_vs_oracle_smoke(tmp_path, monkeypatch, capfd):
    vis = small_study(tmp_path / "vision.db", "vision", 0)
    ora = small_study(tmp_path / "oracle.db", "oracle", 1)
    out = run_bench(
        "vision_vs_oracle.py",
        *("--vision", str(tmp_path / "vision.db"), "--oracle", str(tmp_path / "oracle.db")),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    row = next(x for x in out.splitlines() if x.startswith("| **whole study** |"))
    assert "| 36 / 36 |" in row
    assert figure(r"\| 36 / 36 \| {n} \|", row) == pytest.approx(np.mean(vis), abs=6e-4)
    assert figure(r"\| 36 / 36 \| [\d.]+ \| {n} \|", row) == pytest.approx(np.mean(ora), abs=6e-4)
    assert figure(r"\| {n} \[", row) == pytest.approx(np.mean(vis) - np.mean(ora), abs=6e-4)
