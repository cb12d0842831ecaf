"""`comexp.run(overrides)`: the README's notebook example runs a tiny planar job through the job
service in this process and returns exactly the rows `comexp` itself stores for the same
overrides (this job's only), shows the job's output while it runs (log lines, the progress
bar's carriage-return updates) through `sys.stdout` / `sys.stderr`, a second call reuses the
first one's workers, and bad input is one ValueError that writes nothing."""

from __future__ import annotations

import os
import re
import sqlite3
import sys
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
from test_cli import comexp_in_process
from test_db import make_result

from comexp.api import load_results, run
from comexp.results.store import ResultsDB

README = Path(__file__).resolve().parents[1] / "README.md"
# what differs between two runs of one episode: where and when it ran, and how long it took
RUN_COLUMNS = {"id", "sweep_id", "wall_s", "worker", "created_at"}


def _readme_block() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    (block,) = [b for b in blocks if "comexp.run(" in b]
    return block


class Recorder:
    """A notebook's `sys.stdout` / `sys.stderr` stand-in: every write, with how many episodes
    the job had stored when it arrived (`stored_now`)."""

    def __init__(self, stored_now) -> None:
        self.stored_now = stored_now
        self.writes: list[tuple[int, str]] = []

    def write(self, text: str) -> int:
        self.writes.append((self.stored_now(), text))
        return len(text)

    def flush(self) -> None:
        pass

    def text(self) -> str:
        return "".join(t for _, t in self.writes)


def _overrides(block: str) -> list[str]:
    (args,) = re.findall(r"comexp\.run\(\s*(\[.*?\])\s*,?\s*\)", block, flags=re.S)
    return eval(args)  # noqa: S307 - a list literal of our own README


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, local_ray) -> Iterator[dict]:
    """The README example run in a fresh directory (whose database already holds another
    job's episode), and the command line with the same overrides in another one (its
    `main()` in this process, on the module's Ray, as `comexp.run`'s job)."""
    block = _readme_block()
    overrides = _overrides(block)
    nb, cli = tmp_path_factory.mktemp("notebook"), tmp_path_factory.mktemp("cli")
    db_arg = next(a for a in overrides if a.startswith("db="))
    nb_db = nb / db_arg.removeprefix("db=")
    nb_db.parent.mkdir(parents=True)
    with ResultsDB(nb_db) as db:
        db.add_results(db.start_sweep(command_line="another job"), [make_result()])
    cwd = os.getcwd()
    os.chdir(nb)
    scope: dict = {}

    def stored_now() -> int:
        with sqlite3.connect(nb_db) as c:
            return c.execute("select count(*) from episodes").fetchone()[0] - 1

    out, err = Recorder(stored_now), Recorder(stored_now)
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(sys, "stdout", out)
            mp.setattr(sys, "stderr", err)
            exec(compile(block, "README.md", "exec"), scope)  # noqa: S102 - our own document
    finally:
        os.chdir(cwd)
    r = comexp_in_process(cli, *overrides)
    assert r.returncode == 0, r.stderr
    yield {
        "df": scope["df"],
        "overrides": overrides,
        "nb_db": nb_db,
        "nb_dir": nb,
        "cli_db": cli / db_arg.removeprefix("db="),
        "out": out,
        "err": err,
    }


def test_run_returns_the_rows_the_command_line_stores(runs: dict) -> None:
    df: pd.DataFrame = runs["df"]
    cli = load_results(runs["cli_db"])
    assert len(df) == len(cli) == 2  # floor mu 0.1 and 1: this job's grid, not the other row
    assert list(df.columns) == list(cli.columns)
    same = [c for c in df.columns if c not in RUN_COLUMNS]
    pd.testing.assert_frame_equal(
        df[same].reset_index(drop=True), cli[same].reset_index(drop=True), check_exact=True
    )
    assert (df.status == "ok").all() and df.backend.eq("planar").all()
    # the same database writing: pushes too, and a sweep row with the command line
    stored = load_results(runs["nb_db"])
    assert len(stored) == 3 and list(df.id) == list(stored.id[1:])
    key = ["episode_key", "k"]

    def pushes(path: Path) -> pd.DataFrame:
        with sqlite3.connect(path) as c:
            q = "SELECT e.episode_key, p.* FROM pushes p JOIN episodes e ON e.id = p.episode_id"
            out = pd.read_sql_query(q, c)
        return out.drop(columns=["id", "episode_id"]).sort_values(key).reset_index(drop=True)

    nb_pushes = pushes(runs["nb_db"])
    nb_pushes = nb_pushes[nb_pushes.episode_key.isin(df.episode_key)].reset_index(drop=True)
    pd.testing.assert_frame_equal(nb_pushes, pushes(runs["cli_db"]), check_exact=True)
    sweeps = load_results(runs["nb_db"], "sweeps")
    assert sweeps.command_line.iloc[-1] == "comexp " + " ".join(
        f"'{a}'" if "[" in a else a for a in runs["overrides"]
    )
    assert list((runs["nb_dir"] / "results" / "runs").glob("*/summary.csv"))


def test_the_jobs_output_is_shown_while_it_runs(runs: dict) -> None:
    """Not only when the job ends: the job's first log line and its progress bar at 0/2 come
    before any episode is stored. The bar's updates keep their carriage returns (a notebook
    redraws the line), the printed results follow, and nothing goes to the caller's streams
    outside `sys.stdout` / `sys.stderr`."""
    out, err = runs["out"], runs["err"]
    first_log = next(i for i, (_, t) in enumerate(err.writes) if "to run" in t)
    assert err.writes[first_log][0] == 0, "the job's first log line came after it stored"
    bar = [(stored, t) for stored, t in err.writes if "\r" in t]
    assert bar, f"no progress bar on stderr: {err.text()!r}"
    assert re.search(r"\r[^\r\n]*0/2", err.text()) and re.search(r"\r[^\r\n]*2/2", err.text())
    assert bar[0][0] == 0 and "0/2" in bar[0][1], "the progress bar came after the job stored"
    assert re.search(r": ran 2 episodes in [\d.]+ s \(0 failed\), stored 2\n", out.text())
    assert "reports (" in out.text()


def test_a_rerun_returns_the_stored_rows_without_running(runs: dict, monkeypatch) -> None:
    monkeypatch.chdir(runs["nb_dir"])

    def no_pool(*args, **kwargs):
        raise AssertionError("nothing should run")

    monkeypatch.setattr("comexp.workers.pool.EpisodePool", no_pool)
    monkeypatch.setattr("comexp.experiment.job.job_pool", no_pool)
    again = run(runs["overrides"])
    assert list(again.id) == list(runs["df"].id)
    assert list(again.error_cm) == list(runs["df"].error_cm)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["backend=planar", "workers=0"], "workers must be a count >= 1 or auto, got 0"),
        (["backend=nope"], "unknown backend 'nope' (choose one of: mujoco, planar, pybullet)"),
        (["nokey=1"], "nokey: no such key; the config has: backend, camera, db"),
        (["speed=40,4"], "comexp.run runs one job; call it once per value of: ['speed=40,4']"),
        (["-m", "speed=4"], "comexp.run takes overrides only"),
    ],
)
def test_bad_input_is_one_value_error_and_writes_nothing(
    tmp_path: Path, monkeypatch, capsys, overrides: list[str], message: str
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError) as err:
        run([*overrides, "db=bad.db"])
    assert str(err.value).startswith(message) and "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []
    assert capsys.readouterr().err == ""  # the one line is the error's


def test_a_string_is_not_a_list_of_overrides() -> None:
    with pytest.raises(TypeError, match="a list of strings"):
        run("backend=planar")


def test_a_second_job_in_the_process_reuses_the_first_ones_workers(runs: dict, monkeypatch) -> None:
    """The notebook's next job on the same backend starts no Ray and no worker: the session
    and the pool of the job before are still up (`job_pool`)."""
    from comexp.workers import pool

    monkeypatch.chdir(runs["nb_dir"])
    overrides = [a for a in runs["overrides"] if not a.startswith("pusher.mu")]
    run([*overrides, "pusher.mu=[0.1]"])
    first = pool._kept[1]
    df = run([*overrides, "pusher.mu=[0.5]"])
    assert len(df) == 2 and (df.status == "ok").all()
    assert pool._kept[1] is first and first._slots  # the same pool, its workers up
