"""Bad episodes never poison a sweep: per-episode time limit, failure reasons stored, counted
in the progress and the summary, and excluded from the error statistics (with the count).

The worker-level fakes below are runners handed to an `EpisodeWorker`; the command-line sweep
runs the tests' backend with its scripted faults (tests/scripted_backend.py). The cluster
faults (node, worker, driver killed; two sweeps on one file) are in `test_cluster.py`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from comexp.episode.task import EpisodeResult, EpisodeSpec
from comexp.sim.simulator import SimulatorSpec

TESTS_DIR = str(Path(__file__).resolve().parent)
FAKE = SimulatorSpec("fake", "test_workers.FakeSimulator")


# --- fakes (imported by the workers) --------------------------------------------------------


def _ok(spec: EpisodeSpec, error_cm: float, detail: str = "") -> EpisodeResult:
    return EpisodeResult(
        spec=spec,
        status="ok",
        failure=None,
        est_com_cm=spec.com_cm,
        error_cm=error_cm,
        n_pushes=5,
        pushes=(),
        wall_s=0.0,
        detail=detail,
    )


def hanging_run(spec: EpisodeSpec, sim: object) -> EpisodeResult:
    """Hangs when `spec.object == "hang"` (Python-level: a sleep, as a stuck stepping loop).
    Like `run_episode`, it turns every `Exception` into a failed result: the time limit must
    get through that."""
    try:
        if spec.object == "hang":
            while True:
                time.sleep(0.01)
        return _ok(spec, 0.5)
    except Exception as e:
        from comexp.workers.actor import failed_result

        return failed_result(spec, "error", repr(e), 0.0)


def c_hanging_run(spec: EpisodeSpec, sim: object) -> EpisodeResult:
    """Hangs with SIGALRM blocked, as an engine stuck inside one C call would (the Python
    handler never gets to run): only the watchdog can end it."""
    if spec.object == "hang":
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
        time.sleep(3600)
    return _ok(spec, 0.5)


def _specs(*objects: str) -> list[EpisodeSpec]:
    from test_workers import make_specs

    return [s for i, o in enumerate(objects) for s in make_specs(1, o, start=i)]


# --- the time limit in the worker (no Ray) --------------------------------------------------


def test_a_hanging_episode_times_out_and_the_worker_carries_on() -> None:
    from comexp.workers.actor import EpisodeWorker

    w = EpisodeWorker(FAKE, runner=hanging_run, episode_timeout_s=0.5)
    before = signal.getsignal(signal.SIGALRM)
    t0 = time.monotonic()
    out = w.run_batch(_specs("box", "hang", "box"))
    took = time.monotonic() - t0
    assert [r.status for r in out] == ["ok", "failed", "ok"]
    assert out[1].failure == "timeout" and "0.5 s" in out[1].detail
    assert 0.4 < out[1].wall_s < 2.0 and took < 3.0
    assert w._sim is not None  # rebuilt for the third episode: the hung one was dropped
    # nothing left behind in the process: no pending alarm, the old handler back
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
    assert signal.getsignal(signal.SIGALRM) == before
    time.sleep(0.7)  # a stray alarm or an armed watchdog would strike now
    assert w.run_one(_specs("box")[0]).status == "ok"
    w.close()


def test_no_time_limit_when_disabled() -> None:
    from comexp.workers.actor import EpisodeWorker

    w = EpisodeWorker(FAKE, runner=hanging_run)
    assert w.episode_timeout_s is None and w._watchdog is None
    assert w.run_one(_specs("box")[0]).status == "ok"


def test_a_hang_inside_c_code_ends_the_worker_process() -> None:
    """SIGALRM cannot interrupt it; the watchdog ends the process after the grace period
    (the pool then retries the batch and finally stores `worker_died`)."""
    code = (
        f"import sys; sys.path.insert(0, {TESTS_DIR!r})\n"
        "from comexp.workers.actor import EpisodeWorker\n"
        "from test_faults import FAKE, _specs, c_hanging_run\n"
        "w = EpisodeWorker(FAKE, runner=c_hanging_run, episode_timeout_s=0.5, kill_grace_s=0.5)\n"
        "print(w.run_one(_specs('box')[0]).status, flush=True)\n"
        "w.run_one(_specs('hang')[0])\n"
        "print('not reached', flush=True)\n"
    )
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 70, r.stderr
    assert r.stdout.split() == ["ok"]
    assert "episode hang com 0 still running" in r.stderr
    assert time.monotonic() - t0 < 30


def test_episode_timeout_is_validated(tmp_path: Path) -> None:
    from test_cli import comexp_in_process

    r = comexp_in_process(tmp_path, "execution.episode_timeout_s=0", "db=results/x.db")
    assert r.returncode == 2 and "execution.episode_timeout_s" in r.stderr
    assert list(tmp_path.iterdir()) == []


# --- end to end: failures stored, counted, excluded ---------------------------------------------


def _table_row(markdown: str, first_cell: str) -> list[str]:
    """The cells of the Markdown table row whose first cell starts with `first_cell`."""
    for line in markdown.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0].startswith(first_cell):
            return cells
    raise AssertionError(f"no row {first_cell!r} in:\n{markdown}")


def test_failed_episodes_are_stored_counted_and_excluded(tmp_path: Path, local_ray, capsys) -> None:
    """One sweep on the tests' backend with its faults on, where 12 of 14 episodes fail, two
    for each reason (physics reasons as the protocol reports them, a hang -> timeout, a worker
    killer -> worker_died). The sweep completes; the failures are stored with their reason,
    counted in progress and summary, and the error tables use only the 2 ok episodes (real
    planar episodes) and say how many were left out."""
    from test_cli import SCRIPTED, comexp_in_process, rows

    from comexp.cli.query import main as comexp_db

    objects = ["rect_8x5", "t_shape", "u_shape", "cross_12", "z_shape", "arrow", "l_shape"]
    r = comexp_in_process(
        tmp_path,
        f"grid.objects=[{','.join(objects)}]",
        "grid.coms_per_object=2",
        "grid.izz_scales=[1]",
        "floor.mu=[1.0]",
        "pusher.mu=[1.0]",
        "db=results/f.db",
        "execution.batch_size=2",
        "execution.max_retries=0",
        "execution.episode_timeout_s=1",
        *SCRIPTED,
        "+backend.options.faults=true",
    )
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "Traceback" not in out
    db = tmp_path / "results" / "f.db"
    got = rows(db, "select failure, count(*) from episodes where status='failed' group by 1")
    assert dict(got) == {
        "tipped": 2,
        "left_view": 2,
        "not_settled": 2,
        "sim_unstable": 2,
        "timeout": 2,
        "worker_died": 2,
    }
    assert rows(db, "select count(*), count(distinct episode_key) from episodes") == [(14, 14)]
    assert rows(
        db, "select count(*) from episodes where status='failed' and error_cm is not null"
    ) == [(0,)]
    ((n_ok, mean, lo, hi),) = rows(
        db,
        "select count(*), avg(error_cm), min(error_cm), max(error_cm) from episodes "
        "where status='ok'",
    )
    assert n_ok == 2
    # progress and the job's summary line count them
    assert "14/14 done, 12 failed" in out
    assert "ran 14 episodes" in out and "(12 failed: " in out
    for reason in ("tipped 2", "timeout 2", "worker_died 2", "not_settled 2"):
        assert reason in out
    # the tables: statistics of the 2 ok episodes, 12 excluded
    # `comexp-db` through its main() (its console script is run in test_dbcli.py)
    capsys.readouterr()
    code = comexp_db(["--db", str(db), "table"])
    t = capsys.readouterr()
    assert code == 0, t.err
    assert "12 failed episode(s) excluded" in t.out, t.out
    for reason in ("left_view 2", "sim_unstable 2", "timeout 2", "worker_died 2"):
        assert reason in t.out
    cells = _table_row(t.out, "**all**")
    assert cells[:2] == ["**all**", "2"] and cells[-1] == "12", t.out
    assert [float(c) for c in (cells[2], cells[4], cells[5])] == pytest.approx(
        [mean, hi, lo], abs=5e-4
    )
    assert _table_row(t.out, "l_shape")[-1] == "2"  # per object too
    # the job's own report in its output folder says the same
    (report,) = (tmp_path / "results" / "runs").glob("*/summary.md")
    assert "12 failed episode(s) excluded" in report.read_text()
    code = comexp_db(["--db", str(db), "summary"])
    s = capsys.readouterr()
    assert code == 0, s.err
    assert _table_row(s.out, "scripted")[1:3] == ["2", "12"], s.out


# --- the default local Ray: the driver killed -----------------------------------------------------


@pytest.mark.slow
def test_a_killed_local_driver_is_resumed_and_leaves_nothing_running(tmp_path: Path) -> None:
    """(c) without a cluster: SIGKILL a `comexp` that started its own Ray, part-way. The same
    command resumes (only the missing episodes), a third run stores nothing, the file is
    sound. Ray's fate sharing takes its gcs and raylet down with the driver; its agents can
    linger (Ray 2.60), in the driver's process group, which is how they are cleaned up."""
    from test_cli import SCRIPTED, _command, _env, rows

    ray_tmp = tempfile.mkdtemp(prefix="cxf-", dir="/tmp")  # Ray's temp dir: ours alone
    env = _env(TMPDIR=ray_tmp)
    args = [
        *SCRIPTED,
        "+backend.options.build_sleep_s=0.25",
        "grid.coms_per_object=2",
        "grid.izz_scales=[1]",
        "floor.mu=[1.0]",
        "pusher.mu=[1.0]",
        "execution.batch_size=2",
        "db=results/k.db",
    ]
    db = tmp_path / "results" / "k.db"
    groups: list[int] = []

    def run(*, strike_at: int | None = None) -> tuple[int, str]:
        p = subprocess.Popen(
            [*_command(), *args],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # its own process group: everything it starts is in it
        )
        groups.append(p.pid)
        if strike_at is not None:
            deadline = time.monotonic() + 180
            while p.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)
                try:
                    if rows(db, "select count(*) from episodes")[0][0] >= strike_at:
                        p.kill()
                        break
                except sqlite3.OperationalError:
                    continue
        out, _ = p.communicate(timeout=300)
        return p.returncode, out

    try:
        rc, out = run(strike_at=8)
        assert rc == -signal.SIGKILL, out
        kept = rows(db, "select count(*) from episodes")[0][0]
        assert 8 <= kept < 40 and rows(db, "pragma integrity_check") == [("ok",)]
        rc, out = run()
        assert rc == 0 and f"{kept} already stored, {40 - kept} to run" in out, out
        assert rows(db, "select count(*), count(distinct episode_key) from episodes") == [(40, 40)]
        n_sweeps = rows(db, "select count(*) from sweeps")
        rc, out = run()
        assert rc == 0 and "all 40 episodes already stored" in out, out
        assert rows(db, "select count(*) from sweeps") == n_sweeps
        assert rows(db, "pragma integrity_check") == [("ok",)]
        print(
            f"FAULT (c) local driver killed, same command rerun: expected 40, stored before "
            f"the fault {kept}, stored 40, duplicated 0, lost 0, integrity ok"
        )
    finally:
        for g in groups:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(g, signal.SIGKILL)
        shutil.rmtree(ray_tmp, ignore_errors=True)
