"""The `comexp` command as users run it: the installed config tree from any directory,
one-line errors that write nothing, runs on the tests' own backend (planar episodes, plugged in
from tests/conf as a user's backend is) that store, resume and survive Ctrl-C, and the two
example commands of the brief.

The installed script runs in a child process where the process matters (--help and --cfg,
a bad run and multirun, Ctrl-C, joining a cluster); the other cases call the script's own
`main()` in this process (`comexp_in_process`), the jobs on one local Ray for the module
(`local_ray`, as a multirun's jobs share one), which saves each case its Python and Hydra
imports and its Ray start.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

TESTS_DIR = str(Path(__file__).resolve().parent)
# the tests' backend (tests/scripted_backend.py), from the tests' config directory
SCRIPTED = (f"hydra.searchpath=[file://{TESTS_DIR}/conf]", "backend=scripted")
SMALL = ["grid.coms_per_object=1", "grid.izz_scales=[1]", "pusher.mu=[1.0]"]


def _command() -> list[str]:
    script = Path(sys.executable).with_name("comexp")
    return [str(script)] if script.exists() else [sys.executable, "-m", "comexp.cli.run"]


def _env(**extra: str) -> dict[str, str]:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("HYDRA_FULL_ERROR", "RAY_ADDRESS") and not k.startswith("RAY_AUTH")
    }
    env.update(PYTHONPATH=TESTS_DIR, RAY_USAGE_STATS_ENABLED="0", **extra)
    return env


def comexp(cwd: Path, *args: str, timeout: float = 300, **env: str):
    return subprocess.run(
        [*_command(), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=_env(**env),
    )


@dataclass
class Ran:
    """What `comexp_in_process` saw: the fields of `subprocess.CompletedProcess` tests read."""

    returncode: int
    stdout: str
    stderr: str


def comexp_in_process(cwd: Path, *args: str, **env: str) -> Ran:
    """`comexp ARGS` through the console script's own `main()` in this process: the same
    argument parsing, Hydra composition, validation callback and one-line error reporting,
    without the ~2 s of Python and Hydra imports a child process pays. A job that runs uses
    the Ray this process has started (the `local_ray` fixture), else starts one. Everything
    `main` touches is put back: cwd, argv, environment, Hydra's global state, the root
    logger and its handlers' filters.
    """
    from hydra.core.global_hydra import GlobalHydra

    import comexp.cli.run as cli

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved = (os.getcwd(), sys.argv[:], dict(os.environ), root.handlers[:], root.level)
    os.environ.update(_env(**env))
    for k in [k for k in os.environ if k not in _env(**env)]:  # what _env leaves out
        del os.environ[k]
    sys.argv = ["comexp", *args]
    os.chdir(cwd)
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                cli.main()
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
    finally:
        cwd0, sys.argv, env0, handlers, level = saved
        os.chdir(cwd0)
        os.environ.clear()
        os.environ.update(env0)
        root.handlers[:] = handlers
        root.setLevel(level)
        for h in handlers:
            h.filters[:] = [f for f in h.filters if type(f).__name__ != "RedactFilter"]
        cli._show_jobs = None
        GlobalHydra.instance().clear()
    return Ran(code, out.getvalue(), err.getvalue())


def rows(db: Path, sql: str) -> list[tuple]:
    with sqlite3.connect(db) as c:
        return c.execute(sql).fetchall()


# --- the installed config tree ---------------------------------------------------------------


def test_help_and_cfg_work_from_any_directory(tmp_path: Path) -> None:
    r = comexp(tmp_path, "--help")
    assert r.returncode == 0, r.stderr
    assert "backend: mujoco, planar, pybullet" in r.stdout and "floor: aniso, iso" in r.stdout
    assert "l_shape" in r.stdout  # the object group ships with the package
    r = comexp(tmp_path, "--cfg", "job", "floor=aniso", "speed=4")
    assert r.returncode == 0, r.stderr
    cfg = yaml.safe_load(r.stdout)
    assert cfg["speed"] == 4.0 and cfg["floor"]["orientations"] == ["xy", "yx"]
    assert cfg["estimator"]["theta_T"] == 1.0 and cfg["workers"] is None
    assert list(tmp_path.iterdir()) == []


# --- bad input: one line, non-zero exit, nothing written ----------------------------------------


BAD_INPUT = [
    (["speed=-4"], "speed"),
    (["speed=abc"], "speed"),
    (["floor.mu=[-0.1]"], "floor.mu"),
    (["pusher.mu=[-1]"], "pusher.mu"),
    (["grid.objects=[no_such_object]"], "no_such_object"),
    (["grid.coms_per_object=0"], "grid.coms_per_object"),
    (["estimator.theta_T=-1"], "estimator.theta_T"),
    (["estimator.method=bayes"], "estimator.method"),
    (["db=/proc/comexp/results.db"], "db"),
    (["backend=bullet3"], "backend"),
    (["floor=wood"], "floor"),
    (["-m", "speed=40,-4"], "speed"),
    (["-m", "backend=pybullet,bullet3"], "backend"),
    (["ray.address=127.0.0.9:9"], "ray.address: cannot reach 127.0.0.9:9"),
    (["-m", "speed=40,4", "ray.address=127.0.0.9:9"], "127.0.0.9:9"),
    (["ray.address=ray://127.0.0.9:10001"], "ray.address"),
    (["ray.address=head-without-port"], "ray.address"),
]


def _assert_bad_input(r: Ran | subprocess.CompletedProcess, tmp_path: Path, needle: str) -> None:
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("comexp: error: "), r.stderr
    assert needle in lines[0]
    assert "Traceback" not in r.stdout + r.stderr
    assert list(tmp_path.iterdir()) == []  # no database, no Hydra output folder


@pytest.mark.parametrize(("args", "needle"), BAD_INPUT)
def test_bad_input_is_one_line_and_writes_nothing(
    tmp_path: Path, args: list[str], needle: str
) -> None:
    r = comexp_in_process(tmp_path, *args, "db=results/x.db" if "db=" not in args[0] else "seed=0")
    _assert_bad_input(r, tmp_path, needle)


@pytest.mark.parametrize(("args", "needle"), [BAD_INPUT[0], BAD_INPUT[12]])
def test_bad_input_through_the_console_script(tmp_path: Path, args: list[str], needle: str) -> None:
    """The installed `comexp` script in a child process: a run and a multirun (the cases
    above call the same `main` in this process)."""
    r = comexp(tmp_path, *args, "db=results/x.db")
    _assert_bad_input(r, tmp_path, needle)


# An unclosed bracket: PyYAML reports it where the next key starts (line 2, column 1).
MALFORMED = "outline_cm: [[0, 0], [10, 0]\nheight_cm: 2\n"
GOOD = "outline_cm: [[0, 0], [9, 0], [0, 6]]\nheight_cm: 2\n"


def _user_conf(tmp_path: Path) -> Path:
    conf = tmp_path / "myconf"
    (conf / "object").mkdir(parents=True)
    (conf / "object" / "bad.yaml").write_text(MALFORMED)
    (conf / "object" / "good.yaml").write_text(GOOD)
    return conf


@pytest.mark.parametrize(
    "args",
    [
        ["grid.objects=[bad]"],
        [],  # every object of the group, built-in and the user's
        ["-m", "grid.objects=[bad]", "speed=40,4"],
    ],
)
def test_malformed_object_file_is_one_line_with_its_position(
    tmp_path: Path, args: list[str]
) -> None:
    conf = _user_conf(tmp_path)
    r = comexp_in_process(tmp_path, "--config-dir", str(conf), *args, "db=results/x.db", *SCRIPTED)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("comexp: error: object 'bad': "), r.stderr
    assert f"malformed YAML in {conf / 'object' / 'bad.yaml'}, line 2, column 1: " in lines[0]
    assert "(while parsing a flow sequence at line 1, column 13)" in lines[0]
    assert "Traceback" not in r.stdout + r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["myconf"]  # no results/, no database


@pytest.mark.parametrize("args", [["floor=mine"], ["-m", "floor=iso,mine"]])
def test_malformed_group_file_hydra_composes_is_one_line(tmp_path: Path, args: list[str]) -> None:
    group = "floor"  # read by Hydra while composing, as experiment/ and the primary config
    conf = tmp_path / "myconf"
    (conf / group).mkdir(parents=True)
    (conf / group / "mine.yaml").write_text("name: iso\nmu: [0.1, 1.0\n")
    r = comexp_in_process(tmp_path, "--config-dir", str(conf), *args, "db=results/x.db")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    where = f"malformed YAML in {conf / group / 'mine.yaml'}, line 3, column 1: "
    assert lines[0].startswith(f"comexp: error: {where}"), lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["myconf"]


# --- `--cfg` with `-m` ----------------------------------------------------------------------------


def test_no_hydra_internals() -> None:
    """Public Hydra APIs only (compose, callbacks, the override parser): nothing imports
    `hydra._internal` or replaces Hydra's methods, so hydra-core is not pinned below 1.4."""
    import ast

    root = Path(__file__).resolve().parents[1]
    found = []
    for folder in ("comexp", "backends", "workers"):
        for path in (root / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                found += [f"{path.name}: {n}" for n in names if n.startswith("hydra._internal")]
    assert found == []


def test_cfg_with_multirun_prints_every_jobs_config(tmp_path: Path) -> None:
    r = comexp_in_process(tmp_path, "-m", "floor=iso,aniso", "speed=40,4", "--cfg", "job")
    assert r.returncode == 0, r.stderr
    docs = list(yaml.safe_load_all(r.stdout))
    assert [(d["floor"]["name"], d["speed"]) for d in docs] == [
        ("iso", 40.0),
        ("iso", 4.0),
        ("aniso", 40.0),
        ("aniso", 4.0),
    ]
    assert all("hydra" not in d for d in docs)
    assert r.stdout.startswith("# job 0: floor=iso speed=40\n")
    # one package of each job's config, and Hydra's node with each job's own output folder
    r = comexp_in_process(
        tmp_path, "--multirun", "floor=iso,aniso", "--cfg", "job", "-p", "floor.name"
    )
    assert r.returncode == 0, r.stderr
    assert list(yaml.safe_load_all(r.stdout)) == ["iso", "aniso"]
    r = comexp_in_process(tmp_path, "-m", "speed=40,4", "--cfg", "all", "--resolve")
    assert r.returncode == 0, r.stderr
    outs = [d["hydra"]["runtime"]["output_dir"] for d in yaml.safe_load_all(r.stdout)]
    assert [Path(o).name for o in outs] == ["0_pybullet_iso_speed40.0", "1_pybullet_iso_speed4.0"]
    assert list(tmp_path.iterdir()) == []  # printing creates no output folder


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["-m", "speed=40,abc", "--cfg", "job"], "speed"),
        (["-m", "speed=40,4", "--cfg", "job", "-p", "nope"], "nope"),
        (["-m", "speed=40,4", "--info"], "Only one of"),
    ],
)
def test_cfg_with_multirun_bad_input_is_one_line(
    tmp_path: Path, args: list[str], needle: str
) -> None:
    r = comexp_in_process(tmp_path, *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("comexp: error: ") and needle in lines[0]
    assert r.stdout == "" and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("address", ["127.0.0.9:9", "192.0.2.1:6379"])
def test_an_unreachable_ray_address_fails_fast(tmp_path: Path, address: str) -> None:
    """Refused (nothing listens) or unanswered (TEST-NET, packets dropped): one line naming
    the address well within 30 s, where Ray alone retries for minutes; nothing written."""
    t0 = time.monotonic()
    r = comexp_in_process(tmp_path, f"ray.address={address}", *SMALL, "db=results/x.db", *SCRIPTED)
    wall_s = time.monotonic() - t0
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("comexp: error: ray.address: ") and address in lines[0]
    assert wall_s < 30, f"took {wall_s:.1f} s"
    assert list(tmp_path.iterdir()) == []  # no database, no Hydra output folder


def test_a_port_that_is_no_ray_head_fails_in_one_line(tmp_path: Path) -> None:
    """Something listens but is no Ray GCS (a wrong port): `ray start` would retry forever;
    comexp gives up at its first failed GCS connection, exits 1 in one line naming the
    address, and writes no sweep, and its join node leaves no process or temp dir behind."""
    server = socket.socket()
    server.bind(("127.0.0.5", 0))
    server.listen(8)  # accepts (the kernel completes the handshake), never answers
    address = f"127.0.0.5:{server.getsockname()[1]}"
    tmp = tempfile.mkdtemp(prefix="cxj-", dir="/tmp")  # short: Ray's socket paths
    try:
        t0 = time.monotonic()
        r = comexp(tmp_path, f"ray.address={address}", *SMALL, "db=x.db", *SCRIPTED, TMPDIR=tmp)
        wall_s = time.monotonic() - t0
        leftover = os.listdir(tmp)
    finally:
        server.close()
        shutil.rmtree(tmp, ignore_errors=True)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith("comexp: error: cannot join the Ray cluster at " + address)
    assert wall_s < 30, f"took {wall_s:.1f} s"
    assert rows(tmp_path / "x.db", "select count(*) from sweeps") == [(0,)]
    assert leftover == []
    assert not _pids_naming(tmp)


def _pids_naming(needle: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if needle.encode() in (d / "cmdline").read_bytes():
                    out.append(int(d.name))
            except OSError:
                continue
    return out


# --- runs with a fake runner ---------------------------------------------------------------------


def test_run_stores_resumes_and_finds_user_objects(tmp_path: Path, local_ray) -> None:
    conf = tmp_path / "myconf" / "object"
    conf.mkdir(parents=True)
    (conf / "my_tri.yaml").write_text("outline_cm: [[0, 0], [9, 0], [0, 6]]\nheight_cm: 2\n")
    # A broken file beside it is not read when not selected (Hydra lists a group's files
    # without parsing them): it must not block a run that does not use it.
    (conf / "broken.yaml").write_text(MALFORMED)
    args = [
        "--config-dir",
        str(tmp_path / "myconf"),
        "grid.objects=[my_tri,l_shape]",
        "grid.izz_scales=[1]",
        "floor.mu=[1.0]",
        "pusher.mu=[1.0]",
        "db=results/t.db",
    ]
    r = comexp_in_process(tmp_path, *args, "grid.coms_per_object=2", *SCRIPTED)
    assert r.returncode == 0, r.stderr
    db = tmp_path / "results" / "t.db"
    assert rows(db, "select object, count(*) from episodes group by object") == [
        ("l_shape", 2),
        ("my_tri", 2),
    ]
    summaries = list((tmp_path / "results" / "runs").glob("*/summary.md"))
    assert len(summaries) == 1 and "my_tri" in summaries[0].read_text()
    # rerun with one more CoM per object: only the 2 new episodes run
    r = comexp_in_process(tmp_path, *args, "grid.coms_per_object=3", *SCRIPTED)
    assert r.returncode == 0, r.stderr
    assert "4 already stored, 2 to run" in r.stdout + r.stderr, r.stdout + r.stderr
    assert rows(db, "select count(*), count(distinct sweep_id) from episodes") == [(6, 2)]
    assert rows(db, "select count(*) from sweeps") == [(2,)]
    # nothing left to do: no new sweep, no Ray
    r = comexp_in_process(tmp_path, *args, "grid.coms_per_object=3", *SCRIPTED)
    assert r.returncode == 0 and "all 6 episodes already stored" in r.stdout
    assert rows(db, "select count(*) from sweeps") == [(2,)]


def test_estimator_method_reaches_the_stored_episodes(tmp_path: Path, local_ray) -> None:
    """`estimator.method` on the command line is the episodes' estimator (and their identity):
    the two methods on the same grid are two sets of episodes, told apart in the database."""
    args = [*SMALL, "floor.mu=[1.0]", "grid.objects=[rect_8x5]", "db=results/m.db"]
    for method in ("magnitude", "paper"):
        r = comexp_in_process(tmp_path, *args, f"estimator.method={method}", *SCRIPTED)
        assert r.returncode == 0, r.stderr
        assert "0 already stored" in r.stdout + r.stderr, r.stdout + r.stderr
    got = rows(tmp_path / "results" / "m.db", "select estimator from episodes order by id")
    assert [json.loads(e)["method"] for (e,) in got] == ["magnitude", "paper"]


def test_aniso_multirun_example(tmp_path: Path, local_ray) -> None:
    r = comexp_in_process(
        tmp_path, "-m", "floor=aniso", "speed=40,4", *SMALL, "db=results/a.db", *SCRIPTED
    )
    assert r.returncode == 0, r.stderr
    db = tmp_path / "results" / "a.db"
    got = rows(
        db,
        "select speed_cm_s, mu_floor_x, mu_floor_y, count(*) from episodes "
        "group by 1, 2, 3 order by 1, 2",
    )
    assert got == [
        (4.0, 0.1, 1.0, 20),
        (4.0, 1.0, 0.1, 20),
        (40.0, 0.1, 1.0, 20),
        (40.0, 1.0, 0.1, 20),
    ]
    assert rows(db, "select count(*) from sweeps") == [(2,)]
    jobs = sorted(p.parent.name for p in (tmp_path / "results" / "multirun").glob("*/*/summary.md"))
    assert len(jobs) == 2 and "speed40" in jobs[0] and "speed4.0" in jobs[1]
    # the second job ran on the first job's two workers (`job_pool`), which then closed
    by_job = rows(db, "select count(distinct sweep_id), count(distinct worker) from episodes")
    assert by_job == [(2, 2)]
    from comexp.workers import pool

    assert pool._kept is None


def test_interrupted_run_keeps_results_and_resumes(tmp_path: Path, local_ray) -> None:
    args = [
        *SMALL,
        "floor.mu=[1.0]",
        "db=results/i.db",
        "execution.batch_size=2",
        *SCRIPTED,
        "+backend.options.build_sleep_s=0.4",
    ]
    proc = subprocess.Popen(
        [*_command(), *args],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        # a suite started in the background (`nohup make test &`) inherits SIGINT ignored, and
        # so would comexp: it then ran to the end and exited 0 (seen in a .ci/run so started)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    db = tmp_path / "results" / "i.db"
    deadline = time.monotonic() + 120
    stored = 0
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.3)
        if db.exists():
            try:
                stored = rows(db, "select count(*) from episodes")[0][0]
            except sqlite3.OperationalError:
                continue  # schema still being created
            if stored >= 4:
                break
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    kept = rows(db, "select count(*) from episodes")[0][0]
    assert 4 <= kept < 20  # what finished was stored, before the end
    r = comexp_in_process(tmp_path, *args)
    assert r.returncode == 0, r.stderr
    assert f"{kept} already stored, {20 - kept} to run" in r.stdout + r.stderr
    assert rows(db, "select count(*), count(distinct object) from episodes") == [(20, 20)]


# --- the real thing ----------------------------------------------------------------------


@pytest.mark.slow
def test_smoke_example_with_pybullet(tmp_path: Path) -> None:
    r = comexp(
        tmp_path,
        "backend=pybullet",
        "floor=iso",
        "speed=40",
        *SMALL,
        "floor.mu=[1.0]",
        "db=results/smoke.db",
        timeout=900,
    )
    assert r.returncode == 0, r.stderr
    db = tmp_path / "results" / "smoke.db"
    (n, ok, mean_err) = rows(
        db, "select count(*), sum(status = 'ok'), avg(error_cm) from episodes"
    )[0]
    assert n == 20 and ok >= 15
    assert mean_err < 3.0  # cm: an estimator that works at all beats the footprint size


def test_the_planar_reference_runs_a_job_with_real_episodes(
    tmp_path: Path, local_ray, monkeypatch
) -> None:
    """`backend=planar` behind the same command line: real physics, perception and estimator,
    stored with the planar physics identity; the job's first episode fills the kernel cache
    in a child before Ray is asked for (workers/kernel_cache.py)."""
    import comexp.experiment.job as job
    import comexp.workers.kernel_cache as kernel_cache
    from comexp.results.store import ResultsDB

    calls: list[tuple] = []
    warm, ensure = job.warm_kernel_cache, job.ensure_ray

    def warm_up(simulator, spec, **kw):
        calls.append(("warm", simulator.name, spec.object, dict(simulator.options)))
        return warm(simulator, spec, **kw)

    def ensure_ray(*a, **kw):
        calls.append(("ray",))
        return ensure(*a, **kw)

    monkeypatch.setattr(kernel_cache, "_warmed", set())
    monkeypatch.setattr(job, "warm_kernel_cache", warm_up)
    monkeypatch.setattr(job, "ensure_ray", ensure_ray)
    r = comexp_in_process(
        tmp_path,
        "backend=planar",
        "grid.objects=[rect_8x5]",
        *SMALL,
        "floor.mu=[1.0]",
        "db=results/p.db",
    )
    assert r.returncode == 0, r.stderr
    assert "planar iso 40 cm/s: ran 1 episodes" in r.stdout, r.stdout
    assert calls == [("warm", "planar", "rect_8x5", {}), ("ray",)], calls
    assert "planar: kernels ready in" in r.stdout, r.stdout
    with ResultsDB(tmp_path / "results" / "p.db", readonly=True) as db:
        (row,) = db.episodes(columns=["backend", "status", "error_cm", "physics"])
    assert row["backend"] == "planar" and row["status"] == "ok", row
    assert row["physics"].startswith("planar/planar-")
    assert row["error_cm"] < 3.0
