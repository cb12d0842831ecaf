"""Failures a developer can act on: `retry=failed` reruns a job's failed episodes in place (each
row replaced, never duplicated), a job prints its failures by kind and the first one's message,
a job whose every episode failed exits non-zero, `comexp-db episodes` shows why an episode
failed; and bad input is one line in the user's words (the key they typed, the file they
named), written nowhere."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from test_cli import SCRIPTED, comexp_in_process, rows

from comexp.cli.query import main as comexp_db
from comexp.episode.task import EpisodeResult
from comexp.experiment.config import prepare_job
from comexp.experiment.grid import expand_grid
from comexp.results.store import ResultsDB

TINY = ["backend=planar", "grid.objects=[l_shape]", "grid.coms_per_object=1", "grid.izz_scales=[1]"]
TINY += ["pusher.mu=[1.0]"]


def _grid(db: Path) -> list:
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", [*TINY, f"db={db}"], return_hydra_config=True)
    job = prepare_job(cfg)
    return expand_grid(job.cfg, job.objects, estimator=job.estimator)


def test_retry_failed_reruns_the_failed_episodes_in_place(tmp_path: Path, local_ray) -> None:
    """Two grid episodes stored as failed (as a crashed or timed-out run leaves them): a rerun
    leaves them (and says how to retry); `retry=failed` runs them again and replaces each row
    in place, its id kept, no key stored twice."""
    db = tmp_path / "results" / "r.db"
    db.parent.mkdir()
    specs = _grid(db)
    assert len(specs) == 2
    failed = [
        EpisodeResult(s, "failed", "timeout", None, None, 0, (), 1.0, detail="hung") for s in specs
    ]
    with ResultsDB(db) as handle:
        handle.add_results(handle.start_sweep(command_line="a crashed job"), failed)
    ids = rows(db, "select id from episodes order by id")
    r = comexp_in_process(tmp_path, *TINY, f"db={db}")
    assert r.returncode == 0, r.stderr
    assert "all 2 episodes already stored (2 failed: retry=failed reruns them)" in r.stdout
    r = comexp_in_process(tmp_path, *TINY, f"db={db}", "retry=failed")
    assert r.returncode == 0, r.stderr
    assert "2 already stored, 2 to run (2 failed, retried)" in r.stdout + r.stderr
    assert rows(db, "select id, status from episodes order by id") == [(i, "ok") for (i,) in ids]
    assert rows(db, "select count(*), count(distinct episode_key) from episodes") == [(2, 2)]
    assert rows(db, "select count(*) from pushes")[0][0] >= 2  # the new results' pushes
    r = comexp_in_process(tmp_path, *TINY, f"db={db}", "retry=failed")
    assert r.returncode == 0 and "all 2 episodes already stored\n" in r.stdout, r.stdout


def test_a_job_whose_every_episode_failed_says_why_and_exits_non_zero(
    tmp_path: Path, local_ray, capsys
) -> None:
    args = [
        "grid.objects=[t_shape]",
        "grid.coms_per_object=1",
        "grid.izz_scales=[1]",
        "pusher.mu=[1.0]",
        "db=results/f.db",
        *SCRIPTED,
        "+backend.options.faults=true",
    ]
    r = comexp_in_process(tmp_path, *args)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "(2 failed: tipped 2)" in r.stdout
    assert "first failure: t_shape com 0: tipped (push 0: tipped)" in r.stdout
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("comexp: error: scripted iso 40 cm/s: every episode failed (t_shape")
    capsys.readouterr()
    assert comexp_db(["--db", str(tmp_path / "results" / "f.db"), "episodes"]) == 0
    out = capsys.readouterr().out
    assert "| detail |" in out.splitlines()[0] and "push 0: tipped" in out


@pytest.mark.parametrize(
    ("arg", "line"),
    [
        (
            "grid.objectz=[x]",
            "grid.objectz: no such key; grid has: com_margin_cm, coms_per_object, izz_scales, "
            "objects",
        ),
        ("grid.objects=l_shape", "grid.objects: expects a list, e.g. grid.objects=[a,b]"),
        ("speed=abc", "speed: expects a number, got 'abc'"),
        ("grid.coms_per_object=x", "grid.coms_per_object: expects a whole number, got 'x'"),
        ("+nokey=1", "nokey: no such key; the config has: backend, camera, db"),
        ("retry=all", "retry must be failed (or unset), got 'all'"),
        ("db=/nonexistent/dir/x.db", "db: cannot create '/nonexistent/dir/x.db': the folder"),
    ],
)
def test_bad_input_is_one_line_in_the_users_words(tmp_path: Path, arg: str, line: str) -> None:
    r = comexp_in_process(tmp_path, "backend=planar", arg)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith(f"comexp: error: {line}"), r.stderr
    assert list(tmp_path.iterdir()) == []
    assert not Path("/nonexistent").exists()


def test_comexp_db_names_the_file_that_is_no_database_and_where_db_goes(tmp_path, capsys):
    bad = tmp_path / "notes.db"
    bad.write_text("not a database\n")
    assert comexp_db(["--db", str(bad), "summary"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"comexp-db: error: {bad}: not a comexp results database (SQLite: ")
    with pytest.raises(SystemExit) as exit_:
        comexp_db(["summary", "--db", str(bad)])
    assert exit_.value.code == 2
    assert "--db goes before the command: comexp-db --db DB COMMAND" in capsys.readouterr().err


def test_a_job_that_runs_nothing_writes_no_new_reports(tmp_path: Path, local_ray) -> None:
    args = [*TINY, "db=results/n.db"]
    assert comexp_in_process(tmp_path, *args).returncode == 0
    again = comexp_in_process(tmp_path, *args)
    assert again.returncode == 0 and "all 2 episodes already stored" in again.stdout
    assert "reports (" not in again.stdout
    assert len(list((tmp_path / "results" / "runs").glob("*/summary.md"))) == 1
