"""The maintained benchmarks: bench/ holds the scripts docs/performance.md's table names (at
most ten) and the helpers they share (bench/common.py, not a script); each script runs on a
tiny input and prints its figures, and a bench that measures other physics than the job's,
or whose episodes all fail, is caught here before it prints figures that mean nothing. The
scripts are plain clients of the package: they patch nothing (they time and record through
the episode loop's phase timer, the push they hand it, and subclasses of the backends'
classes) and import no other script than bench/common.py.

Most scripts run in this process (`runpy`, as `python bench/X.py` would: the imports are paid
once for the suite); the Ray-backed runs and a second checkout's child processes are `slow`,
with a cheaper check of the same script in the default suite."""

from __future__ import annotations

import ast
import collections
import itertools
import json
import os
import re
import runpy
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
HELPERS = "common.py"  # what the scripts share: not a script
# scripts that measure nothing: the docs' tables from their data, a study's database as text
TOOLS = {"docs_tables.py", "study_report.py"}
sys.path.insert(0, str(BENCH))  # as `python bench/X.py` has it

from common import job_backend_options, job_simulator, job_specs  # noqa: E402

from comexp.backends.physics_settings import physics_identity  # noqa: E402
from comexp.experiment.config import load_backend  # noqa: E402

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


def bench_scripts() -> list[str]:
    """The scripts in bench/: every file but the shared helpers."""
    return sorted(p.name for p in BENCH.iterdir() if p.is_file() and p.name != HELPERS)


# --- what bench/ holds ---------------------------------------------------------------------


def test_bench_holds_the_scripts_docs_performance_names_at_most_ten():
    named = bench_table()
    on_disk = bench_scripts()
    assert (BENCH / HELPERS).is_file()
    assert len(named) == len(set(named)), "a script named twice in the table"
    assert sorted(named) == on_disk, "bench/ and docs/performance.md's table differ"
    benchmarks = [n for n in on_disk if n not in TOOLS]
    assert len(benchmarks) <= 10, "bench/ keeps at most ten maintained benchmarks"


def test_every_bench_script_has_a_smoke_test():
    """Each script in bench/ is run by a test of this module (its file name in the code)."""
    source = Path(__file__).read_text()
    for name in bench_scripts():
        assert source.count(f'"{name}"') >= 1 or f"import {name[:-3]}\n" in source, name


def _imported_names(tree: ast.AST) -> tuple[set[str], set[str]]:
    """The top-level modules a file imports, and the names its imports bind."""
    modules, bound = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {a.name.split(".")[0] for a in node.names}
            bound |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module:
                modules.add(node.module.split(".")[0])
            bound |= {a.asname or a.name for a in node.names}
    return modules, bound


def _assigned_through(tree: ast.AST, names: set[str]) -> list[str]:
    """Attribute assignments and deletions (`x.y = ...`, `del x.y.z`) whose root is one of
    `names`: what an imported module, class or function would be patched by."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign | ast.Delete):
            targets = node.targets
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            targets = [node.target]
        else:
            continue
        for t in targets:
            root = t
            while isinstance(root, ast.Attribute):
                root = root.value
            if t is not root and isinstance(root, ast.Name) and root.id in names:
                found.append(f"line {node.lineno}: {ast.unparse(t)}")
    return found


def test_bench_scripts_are_plain_clients():
    """No bench file patches the package (no `setattr`, no assignment to an attribute of
    anything it imported, no test-style patching), edits the module path, or imports another
    script: what scripts share is bench/common.py's. (compare_checkouts.py's child program,
    a string run in another checkout, may import that checkout's older helpers.)"""
    scripts = {p.stem for p in BENCH.glob("*.py")} - {Path(HELPERS).stem}
    for path in sorted(BENCH.glob("*.py")):
        text = path.read_text()
        for word in ("setattr(", "sys.path", "monkeypatch"):
            assert word not in text, f"bench/{path.name} uses {word}"
        tree = ast.parse(text)
        modules, bound = _imported_names(tree)
        assert not modules & scripts, f"bench/{path.name} imports {sorted(modules & scripts)}"
        patched = _assigned_through(tree, bound)
        assert not patched, f"bench/{path.name} assigns to what it imported: {patched}"


@pytest.mark.parametrize("backend", ["planar", "pybullet", "mujoco"])
def test_bench_pools_run_the_physics_the_episodes_name(backend):
    """bench/scaling.py and bench/memory.py start their pools with these options; without
    them every worker refused every episode as `physics_mismatch`, and the benches printed
    the timings of 200 refusals."""
    spec = job_specs(backend)[0]
    target = load_backend(backend)._target_
    assert job_simulator(backend).target == target
    assert physics_identity(backend, target, options=job_backend_options(backend)) == spec.physics
    assert physics_identity(backend, target) != spec.physics or backend == "planar"


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
    # the loop's phases (its PhaseTimer), the engine's calls (a subclass of its class)
    shares = {k: figure(rf"\n{k} \(.*?\)\s+{{n}}%", out) for k in ("build", "push", "measure")}
    assert all(v > 0 for v in shares.values()) and sum(shares.values()) < 100.5
    physics = figure(r"\n  physics \(push - frames\)\s+{n}%", out)
    assert 0 < physics < figure(r"\npush \(the protocol\)\s+{n}%", out)
    assert figure(r"  tracking\s+[\d.]+%\s+[\d.]+\s+{n}", out) > 0  # frames per episode
    assert figure(r"sim\.build {n} ms", out) > 0 and figure(r"sim\.render_depth {n} ms", out) > 0
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
    assert "comexp/episode/loop.py:" in out and "(run_episode)" in out
    step = re.search(
        r"\n\s+([\d.]+)%\s+[\d.]+\s+[\d.]+\s+comexp\.backends\.planar_sim\._run_chunks "
        r"\(compiled\)",
        out,
    )
    assert step and 0 < float(step.group(1)) < 100


def test_step_cost_smoke(monkeypatch, capfd):
    """pybullet's engine step is its compiled chunk (`_compiled_steps`, timed by a subclass)
    in the pushes, less the friction kernel's replay; the module's call left as it is."""
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
    """planar's step is its compiled chunk (`advance` / `advance_chunks`, the friction solve
    inside, timed by a subclass): timed in the pushes, no separate kernel, and the module's
    call left as it is."""
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
    # a coarser grid's cost ratio is printed (a figure, not checked: timing is the bench's job,
    # and on a loaded machine two runs of a few milliseconds can come out either way)
    assert figure(r"\| 100 \| 2 \| 5 \| x{n} \|", out) > 0
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
    """tracking.py measures through a subclass of the backend's class, the loop's timer and
    the push it hands the loop: the package's names are as they were after the run."""
    import comexp.episode.loop as loop
    from comexp.method.tracking import PoseTracker

    names = dict(vars(loop))
    track = PoseTracker.track
    out = run_bench(
        "tracking.py",
        *("--backend", "planar", "--episodes", "1", "--fps", "0,30", "--full-frames"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    assert dict(vars(loop)) == names and PoseTracker.track is track
    assert figure(r"\|\s+0 fps \|\s+{n}/1", out) == 1
    assert figure(r"\|\s+30 fps \|\s+{n}/1", out) == 1
    assert figure(r"30 fps: tracking \(.*?\) {n} ms CPU per frame", out) > 0
    assert figure(r"30 fps: {n} tracking renders", out) > 0
    assert figure(r"30 full: {n} tracking renders", out) == figure(r"30 fps: {n} tracking", out)
    assert figure(r"30 fps: turn beyond the prediction .*? max [\d.]+ / [\d.]+ / {n} deg", out) < 30
    assert figure(r"30 full vs window: max \|rotation difference\| {n} deg", out) < 1e-6


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


def test_engine_agreement_steps_smoke(monkeypatch, capfd):
    out = run_bench(
        "engine_agreement.py",
        *("--steps-ms", "1", "0.5", "--pushes", "6", "--engines", "pybullet"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("pybullet | ")]
    assert {(r[1], r[2]) for r in rows} <= {(a, b) for a in ("1.000", "0.500")
                                            for b in ("0.100", "1.000")}  # fmt: skip
    assert {r[1] for r in rows} == {"1.000", "0.500"}
    assert all(int(r[3]) >= 1 and 0.0 <= float(r[4]) < 1.0 for r in rows)


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
        argv = ["compare_child.py", args.backend, args.floor, str(args.speed),
                str(args.episodes), str(out)]  # fmt: skip
        with monkeypatch.context() as m:
            m.chdir(tree)
            m.setattr(sys, "argv", [*argv, *extra])
            child = compile(compare_checkouts._CHILD, "compare_child.py", "exec")
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


def test_compare_checkouts_child_falls_back_to_an_older_layout():
    """The child program takes the first of its names that imports (an older checkout's
    modules and bench helpers), and names every failure when none does."""
    import compare_checkouts

    child: dict = {}
    exec(compile(compare_checkouts._CHILD, "compare_child.py", "exec"), child)  # noqa: S102
    first = child["first"]
    assert first("comexp_no_such_layout.loop:run_episode", "os.path:join") is os.path.join
    assert first("os:no_such_name", "os:sep") == os.sep
    with pytest.raises(ImportError, match=r"(?s)comexp_no_such_layout.*os:no_such_name"):
        first("comexp_no_such_layout:x", "os:no_such_name")
    assert child["helper"]("strided").__module__ == "common"  # this checkout's helpers


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
    from common import memory_kb

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        sampler = memory.TreeSampler(os.getpid(), 0.05).start()
        sampler.sample()
        sampler.stop()
        start = {child.pid: memory_kb(child.pid)["rss"]}
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
        (("scaling.py", "--episodes", "2", "--workers", "1"), r"Ray's start {n} s"),
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

    from comexp.method.estimator import EstimatorSettings
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


def test_docs_tables_fills_a_generated_block_from_its_data(tmp_path, monkeypatch):
    """`bench/docs_tables.py`: a block is filled from docs/data/NAME.json (its table and the
    command that measured it; the provenance stays in the file), the knob table from the
    structured config; a block without data says so."""
    import common
    import docs_tables

    monkeypatch.setattr(common, "DATA", tmp_path / "data")  # where `write_table` writes
    monkeypatch.setattr(docs_tables, "DATA", tmp_path / "data")  # where `render` reads
    path = docs_tables.write_table("demo", ["a", "b"], [[1, 0.5]], "python bench/demo.py")
    meta = json.loads(path.read_text())["meta"]
    assert {"comexp", "git", "machine", "date"} <= set(meta)
    doc = tmp_path / "page.md"
    block = "<!-- generated: {} -->\nold\n<!-- end generated -->\n"
    doc.write_text("x\n" + block.format("demo") + block.format("knobs") + block.format("none"))
    assert docs_tables.render([doc]) == [doc]
    text = doc.read_text()
    assert "| 1 | 0.500 |" in text and "Measured by `python bench/demo.py`" in text
    assert "| `grid.coms_per_object` | `10` |" in text and "old" not in text
    assert "(no data yet: docs/data/none.json" in text
    assert meta["git"] not in text  # provenance in the data file, not in the docs
    assert docs_tables.render([doc]) == []  # rendered again: nothing changes


def test_episode_profile_times_estimators_on_the_same_episodes(monkeypatch, capfd):
    """`episode_profile.py --estimators A,B`: one row per estimator over the same episodes,
    the first's cost ratio 1, both estimators' mean errors over the episodes both finished."""
    out = run_bench(
        "episode_profile.py",
        *("--backend", "planar", "--speed", "4", "--episodes", "2", "--estimators", "paper,fit"),
        monkeypatch=monkeypatch,
        capfd=capfd,
    )
    lines = out.strip().splitlines()
    assert lines[0].startswith("condition | estimator | episodes")
    paper, fit = (line.split(" | ") for line in lines[1:3])
    assert paper[1] == "paper" and fit[1] == "fit" and paper[2] == fit[2] == "2"
    assert float(paper[5]) == 1.0 and float(fit[5]) > 0


def test_docs_tables_pairs_estimators_on_the_same_episodes(tmp_path, monkeypatch):
    """`docs_tables.py methods`: per backend, condition and estimator the mean error, and the
    paired difference from motion on the episodes both ran (its 95% interval); an episode only
    one estimator ran is in its mean, not in the pair."""
    import common
    import docs_tables
    from test_db import make_result

    from comexp.method.estimator import EstimatorSettings
    from comexp.results.store import ResultsDB

    monkeypatch.setattr(common, "DATA", tmp_path / "data")
    url = f"sqlite:///{tmp_path / 'm.db'}"
    motion, fit = EstimatorSettings(method="motion"), EstimatorSettings(method="fit")
    rows = [make_result(com_index=i, error_cm=1.0 + 0.1 * i, estimator=motion) for i in range(4)]
    rows += [make_result(com_index=i, error_cm=0.5 + 0.1 * i, estimator=fit) for i in range(3)]
    rows += [make_result(com_index=9, error_cm=0.9, estimator=fit)]  # motion has no pair
    with ResultsDB(url) as db:
        db.add_results(None, rows)
    data = json.loads(docs_tables.methods([url]).read_text())
    by = {r[2]: r for r in data["rows"]}
    assert by["motion"][3] == 4 and by["motion"][4] == pytest.approx(1.15)
    assert by["motion"][5] is None
    assert by["fit"][3] == 4 and by["fit"][4] == pytest.approx((0.5 + 0.6 + 0.7 + 0.9) / 4)
    assert by["fit"][5] == pytest.approx(-0.5)  # paired on com_index 0-2 only
    assert by["fit"][6] == "[-0.500, -0.500]"
    assert data["command"] == f"python bench/docs_tables.py methods --name fit-methods --db {url}"


def test_docs_tables_pairs_a_model_with_its_previous_revision(tmp_path, monkeypatch):
    """`methods --baseline 'fit (REV)' --method fit`: an older revision of a pinned model is
    labelled with it and pairs with today's on the same episodes; other methods are left out,
    and with `--floor` other floors."""
    import common
    import docs_tables
    from test_db import make_result

    from comexp.experiment.grid import PINNED_VERSIONS
    from comexp.method.estimator import EstimatorSettings
    from comexp.results.store import ResultsDB

    monkeypatch.setattr(common, "DATA", tmp_path / "data")
    url = f"sqlite:///{tmp_path / 'r.db'}"
    old = EstimatorSettings(method="fit", motion_version="fit-0+old")
    new = EstimatorSettings(method="fit", motion_version=PINNED_VERSIONS["fit"])
    motion = EstimatorSettings(method="motion", motion_version=PINNED_VERSIONS["motion"])
    rows = [make_result(com_index=i, error_cm=1.0, estimator=old) for i in range(3)]
    rows += [make_result(com_index=i, error_cm=0.8 + 0.01 * i, estimator=new) for i in range(3)]
    rows += [make_result(com_index=i, error_cm=2.0, estimator=motion) for i in range(3)]
    aniso = dict(floor="aniso", mu_floor_x=1.0)
    rows += [make_result(com_index=i, error_cm=3.0, estimator=new, **aniso) for i in range(2)]
    with ResultsDB(url) as db:
        db.add_results(None, rows)
    path = docs_tables.methods([url], "rev", baseline="fit (fit-0+old)", method="fit", floor="iso")
    data = json.loads(path.read_text())
    by = {r[2]: r for r in data["rows"]}
    assert set(by) == {"fit", "fit (fit-0+old)"} and {r[1] for r in data["rows"]} == {
        "iso, 40 cm/s"
    }
    assert by["fit"][5] == pytest.approx(-0.19) and by["fit (fit-0+old)"][5] is None
    assert "--baseline 'fit (fit-0+old)' --method fit --floor iso" in data["command"]
    rows = json.loads(docs_tables.methods([url], "rev", method="fit").read_text())["rows"]
    assert [r[4] for r in rows if r[1] == "aniso, 40 cm/s"] == [3.0]  # no floor: every floor


# --- whole commands --------------------------------------------------------------------------


def test_whole_commands_splits_a_command_into_its_phases():
    """whole_commands.py's phases from the lines' arrival times: each phase its own share, a
    missing phase none (a kept Ray's warm workers load no kernels), the jobs' episode time
    from their `ran N episodes` lines."""
    import whole_commands

    ends = {"imports, compose, grid": 0.8, "Ray and workers": 1.0, "episodes": 1.3}
    ends.update({"reports": 1.5, "exit": 1.6})
    d = whole_commands.phase_durations(ends)
    assert d["kernels"] == 0.0 and d["Ray and workers"] == pytest.approx(0.2)
    assert d["exit"] == pytest.approx(0.1) and d["whole command"] == 1.6
    assert sum(v for k, v in d.items() if k != "whole command") == pytest.approx(1.6)
    out = "a: ran 1600 episodes in 25.3 s (0 failed)\nb: ran 16 episodes in 0.7 s (1 failed)\n"
    assert whole_commands.episodes_s(out) == pytest.approx(26.0)
    for name, pattern in whole_commands.PHASES:  # each phase's line as comexp prints it
        line = {
            "imports, compose, grid": "planar iso 40 cm/s: 16 episodes, 0 already stored, 16",
            "kernels": "planar: kernels ready in 0.8 s",
            "Ray and workers": "worker 1 ready: pid 7 on node 1.2.3.4",
            "episodes": "planar iso 40 cm/s: ran 16 episodes in 0.3 s (0 failed), stored 16",
            "reports": "reports (18 files): results/runs/x",
        }[name]
        assert pattern.search(line), name


@pytest.mark.slow
def test_whole_commands_times_the_first_job_on_a_kept_ray():
    r = subprocess.run(
        [sys.executable, str(BENCH / "whole_commands.py"), "first-job", "--runs", "1", "--kept"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    assert figure(r"\n\s+whole command\s+{n}", r.stdout) > 0
    assert re.search(r"new, kept Ray", r.stdout), r.stdout


def test_the_tables_name_what_an_estimator_was_given_rather_than_measured():
    """`estimator_label`: the method; an older revision; true nuisances and true poses (an
    evaluation's told values), so that such jobs never pool with the measured ones."""
    import docs_tables

    from comexp.experiment.grid import PINNED_VERSIONS

    label = docs_tables.estimator_label
    fit = PINNED_VERSIONS["fit"]
    assert label(json.dumps({"method": "fit", "motion_version": fit})) == "fit"
    assert label(json.dumps({"method": "fit", "motion_version": "fit-1+motion-3"})) == (
        "fit (fit-1+motion-3)"
    )
    told = {"method": "fit", "nuisance_source": "oracle", "rotation_source": "oracle"}
    assert label(json.dumps(told)) == "fit (true nuisances, true poses)"
    assert label(json.dumps({"method": "paper", "rotation_source": "vision"})) == "paper"
