"""PostgreSQL, against a real server: a job, its resume, two concurrent jobs, `comexp-db`
(read-only), replay, and the URL's password appearing nowhere.

The server is Debian's `postgresql` (binaries under /usr/lib/postgresql/*/bin), started by the
fixture on 127.0.0.1, on a free port, in a temporary directory, with fsync off; as root it runs
as the `postgres` user (the server refuses root). `make test` installs the package when root.
"""

from __future__ import annotations

import contextlib
import glob
import io
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_cli import SCRIPTED, Ran, comexp, comexp_in_process

from comexp.results.schema import SCHEMA_VERSION
from comexp.results.store import ResultsDB, redact_url

PASSWORD = "Pw-7f3kQz_s3cret"  # distinctive, so a grep for it cannot match anything else
USER = "comexp_test"
TINY = [
    "grid.objects=[square_7]",
    "grid.coms_per_object=1",
    "grid.izz_scales=[1]",
    "pusher.mu=[1.0]",
    "floor.mu=[0.1]",
    "workers=1",
]


def _pg_bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"))
    if found:
        return Path(found[-1]).parent
    pg_ctl = shutil.which("pg_ctl")
    return Path(pg_ctl).parent if pg_ctl else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class PgServer:
    def __init__(self, port: int) -> None:
        self.port = port

    def url(self, database: str, *, password: bool = True) -> str:
        auth = f"{USER}:{PASSWORD}" if password else USER
        return f"postgresql://{auth}@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        import psycopg

        with psycopg.connect(self.url("postgres"), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)


@pytest.fixture(scope="module")
def pg() -> Iterator[PgServer]:
    bindir = _pg_bin()
    if bindir is None:
        pytest.skip(
            "PostgreSQL server binaries not found (Debian: apt-get install postgresql; "
            "`make test` installs it when run as root)"
        )
    pytest.importorskip("psycopg", reason="psycopg 3 missing: pip install 'comexp[postgres]'")
    as_user: list[str] = []
    base = Path(tempfile.mkdtemp(prefix="comexp-pg-"))  # under /tmp: the postgres user can enter
    if os.geteuid() == 0:
        runuser = shutil.which("runuser")
        if runuser is None or subprocess.run(["id", "postgres"], capture_output=True).returncode:
            pytest.skip("running as root needs the `postgres` user and runuser to start a server")
        as_user = [runuser, "-u", "postgres", "--"]
        shutil.chown(base, "postgres")
    data, pwfile, log = base / "data", base / "pw", base / "server.log"
    pwfile.write_text(PASSWORD + "\n")
    if as_user:
        shutil.chown(pwfile, "postgres")
    port = _free_port()
    run = dict(check=True, capture_output=True, text=True, timeout=120)
    try:
        subprocess.run(
            [*as_user, str(bindir / "initdb"), "-D", str(data), "-U", USER, "--pwfile", str(pwfile)]
            + ["-A", "scram-sha-256", "-E", "UTF8", "--locale=C", "--no-sync"],
            **run,
        )
        opts = f"-h 127.0.0.1 -p {port} -F -c unix_socket_directories='' -c max_connections=50"
        subprocess.run(
            [*as_user, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log), "-o", opts]
            + ["-w", "-t", "60", "start"],
            **run,
        )
    except subprocess.CalledProcessError as exc:
        shutil.rmtree(base, ignore_errors=True)
        pytest.fail(f"could not start PostgreSQL: {exc.stderr or exc.stdout}")
    try:
        yield PgServer(port)
    finally:
        subprocess.run(
            [*as_user, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
            capture_output=True,
            timeout=60,
        )
        shutil.rmtree(base, ignore_errors=True)


def _grep_tree(root: Path, needle: str) -> list[str]:
    hits = []
    for p in root.rglob("*"):
        if p.is_file():
            try:
                if needle.encode() in p.read_bytes():
                    hits.append(str(p))
            except OSError:
                continue
    return hits


def _dbcli(*args: str) -> Ran:
    """`comexp-db ARGS` through its main() in this process (exit code, stdout, stderr); its
    console script is run in a child process by test_dbcli.py."""
    from comexp.cli.query import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return Ran(code, out.getvalue(), err.getvalue())


def test_job_resume_replay_and_no_password_anywhere(pg: PgServer, tmp_path: Path) -> None:
    import comexp as package  # the top-level API; `comexp` here is test_cli's runner

    url = pg.create_database("job")
    work = tmp_path / "work"
    work.mkdir()
    ray_tmp = Path(tempfile.mkdtemp(prefix="cxpg-"))  # short: Ray's socket paths must fit
    try:
        _job_and_checks(package, url, work, ray_tmp, tmp_path)
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)


def _job_and_checks(package, url: str, work: Path, ray_tmp: Path, tmp_path: Path) -> None:
    first = comexp(work, *TINY, f"db={url}", TMPDIR=str(ray_tmp))
    assert first.returncode == 0, first.stderr
    assert "ran 1 episodes" in first.stdout and "1 of its 1 grid episodes" in first.stdout
    # the resume as a multirun: Hydra's launcher lists each job's overrides, and saves
    # multirun.yaml beside the jobs
    # (through main() in this process: nothing left to run, no Ray)
    again = comexp_in_process(work, "-m", *TINY, f"db={url}")
    assert again.returncode == 0, again.stderr
    assert "all 1 episodes already stored" in again.stdout
    assert "#0 : " in again.stdout + again.stderr and "***" in again.stdout + again.stderr

    with ResultsDB(url, readonly=True) as db:
        (row,) = db.episodes()
        sweeps = db.sweeps()
        assert len(sweeps) == 1 and sweeps[0]["n_episodes"] == 1  # the resume stored nothing
        replayed = package.replay(db, row["id"])
        assert (replayed.status, replayed.error_cm) == (row["status"], row["error_cm"])
        assert replayed.est_com_cm == (row["est_com_x_cm"], row["est_com_y_cm"])
        stored_pushes = db.pushes(row["id"])
        assert [p.rotation_deg for p in replayed.pushes] == [
            p["rotation_deg"] for p in stored_pushes
        ]
        df = package.load_results(db)
        assert list(df["error_cm"]) == [row["error_cm"]]
        assert "square_7" in set(df["object"])

    outputs = [first.stdout, first.stderr, again.stdout, again.stderr]
    for argv in (
        ["summary"],
        ["table", "--format", "csv"],
        ["paper"],
        ["sweeps"],
        ["sweeps", "--show", "1"],
    ):
        r = _dbcli("--db", url, *argv)
        assert r.returncode == 0, r.stderr
        outputs += [r.stdout, r.stderr]
    r = _dbcli("--db", url, "show", str(row["id"]), "--out", str(tmp_path / "ep.png"))
    assert r.returncode == 0 and (tmp_path / "ep.png").read_bytes()[:4] == b"\x89PNG"
    assert "mu_floor=0.1" in outputs[4]  # the summary's condition
    # Hydra's saved overrides keep the URL, with *** for the password
    saved = [
        *work.glob("results/runs/*/.hydra/overrides.yaml"),
        *work.glob("results/multirun/*/*/.hydra/overrides.yaml"),
        *work.glob("results/multirun/*/multirun.yaml"),
    ]
    assert len(saved) == 3 and "***" in redact_url(url)  # the job, its resume, the multirun
    # (a multirun's job overrides escape ':' as '\\:', so look for the *** only)
    unscrubbed = [str(p) for p in saved if "@127.0.0.1" not in p.read_text().replace("\\", "")]
    assert unscrubbed == []
    unscrubbed = [str(p) for p in saved if ":***@" not in p.read_text().replace("\\", "")]
    assert unscrubbed == []
    # nowhere: terminal, Hydra's saved configs and comexp.log, the sweeps table
    assert not [o for o in outputs if PASSWORD in o]
    assert _grep_tree(work, PASSWORD) == []
    assert _grep_tree(tmp_path, PASSWORD) == []
    assert _grep_tree(ray_tmp, PASSWORD) == []  # Ray's session files and logs
    with ResultsDB(url, readonly=True) as db:
        (sweep,) = db.sweeps()
    assert PASSWORD not in repr(sweep) and "***" in sweep["config"]
    assert "***" in sweep["command_line"]


def test_two_concurrent_jobs_store_every_episode_once(pg: PgServer, tmp_path: Path) -> None:
    url = pg.create_database("race")
    grid = [
        "grid.objects=[square_7,l_shape]",
        "grid.coms_per_object=4",
        "grid.izz_scales=[1]",
        "pusher.mu=[1.0]",
        "floor.mu=[0.1,1.0]",
        "execution.batch_size=1",
        "workers=1",
    ]
    results: dict[str, subprocess.CompletedProcess[str]] = {}

    def job(name: str) -> None:
        d = tmp_path / name
        d.mkdir()
        results[name] = comexp(
            d, *grid, f"db={url}", *SCRIPTED, "+backend.options.build_sleep_s=0.05"
        )

    threads = [threading.Thread(target=job, args=(n,)) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    for r in results.values():
        assert r.returncode == 0, r.stderr
    with ResultsDB(url, readonly=True) as db:
        rows = db.episodes(columns=["episode_key", "object", "com_index"])
        keys = [r["episode_key"] for r in rows]
        assert len(keys) == len(set(keys)) == 2 * 4 * 2
        sweeps = db.sweeps()
        assert sum(s["n_episodes"] for s in sweeps) == 16
        with db.engine.connect() as conn:
            n_pushes = conn.exec_driver_sql("SELECT COUNT(*) FROM pushes").scalar()
            dup = conn.exec_driver_sql(
                "SELECT COUNT(*) FROM (SELECT episode_id, k FROM pushes "
                "GROUP BY episode_id, k HAVING COUNT(*) > 1) d"
            ).scalar()
    assert dup == 0 and n_pushes >= 0


def test_comexp_db_opens_postgresql_read_only(pg: PgServer) -> None:
    from sqlalchemy import text
    from sqlalchemy.exc import SQLAlchemyError

    url = pg.create_database("readonly")
    ResultsDB(url).close()  # create the schema
    with ResultsDB(url, readonly=True) as db:
        with (
            pytest.raises(SQLAlchemyError, match="read-only transaction"),
            db.engine.begin() as conn,
        ):
            conn.execute(text("DELETE FROM comexp_meta"))
        assert db.where == redact_url(url) and PASSWORD not in db.where
    r = _dbcli("--db", url, "episodes", "--status", "failed", "--format", "csv")
    assert r.returncode == 0 and r.stdout.startswith("id,sweep_id,")
    assert r.stdout.count("\n") == 1 and "no episodes stored" in r.stderr
    bad = pg.url("readonly").replace(PASSWORD, "wrong-password")
    r = _dbcli("--db", bad, "summary")
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "password authentication failed" in r.stderr and "wrong-password" not in r.stderr


def test_missing_driver_is_one_line(tmp_path: Path) -> None:
    """Without psycopg installed: one line naming the extra to install, no traceback."""
    code = (
        "import sys; sys.modules['psycopg'] = None; sys.modules['psycopg2'] = None\n"
        "from comexp.cli.query import main\n"
        "sys.exit(main(['--db', 'postgresql://u:pw@127.0.0.1:1/x', 'summary']))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "pip install 'comexp[postgres]'" in r.stderr


def test_concurrent_first_opens_create_the_schema_once(pg: PgServer) -> None:
    """Writers that open a fresh database at the same moment all succeed (PostgreSQL's
    catalog rejects concurrent CREATE TABLEs of the same name without the schema lock)."""
    url = pg.create_database("first_open")
    barrier = threading.Barrier(6)
    errors: list[BaseException] = []

    def open_once() -> None:
        barrier.wait()
        try:
            ResultsDB(url).close()
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_once) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == []
    with ResultsDB(url, readonly=True) as db, db.engine.connect() as conn:
        rows = conn.exec_driver_sql("SELECT value FROM comexp_meta").scalars().all()
        assert rows == [str(SCHEMA_VERSION)]
