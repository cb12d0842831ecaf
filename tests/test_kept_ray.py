"""The kept Ray (`comexp-ray start|status|stop`, comexp/workers/kept.py): a record is trusted
only when it is ours and alive, jobs find it and leave their workers warm in it, results are
the same as on a Ray of the job's own, and `comexp-ray stop` ends every process of it."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_cli import _env, comexp

from comexp.workers import kept

JOB = ("backend=planar", "grid.objects=[l_shape]", "grid.coms_per_object=1", "pusher.mu=[1.0]")


@pytest.fixture
def ray_dir(monkeypatch) -> Iterator[Path]:
    """A kept-Ray folder of the test's own: short, Ray's unix sockets live below it."""
    d = Path(tempfile.mkdtemp(prefix="cxr-", dir="/tmp"))
    monkeypatch.setenv(kept.DIR_ENV, str(d))
    yield d
    kept.stop()
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def stand_in() -> Iterator[subprocess.Popen]:
    """A process whose command line names a Ray temp dir, as `ray start --temp-dir=...` does."""
    p = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(120)", "--temp-dir=/tmp/cxr-stand-in"],
        start_new_session=True,
    )
    deadline = time.monotonic() + 10  # until it has exec'd (before, /proc shows pytest's line)
    while "--temp-dir=/tmp/cxr-stand-in" not in kept._cmdline(p.pid).split():
        assert time.monotonic() < deadline, "the stand-in did not start"
        time.sleep(0.01)
    yield p
    p.kill()
    p.wait()


def _record(proc: subprocess.Popen, **changes) -> kept.KeptRay:
    """A record as `start` writes it, of the stand-in `proc`."""
    base = kept.KeptRay(
        address="127.0.0.1:1", pid=proc.pid, temp_dir="/tmp/cxr-stand-in", token="t" * 64,
        cpus=2, comexp=kept._version(), python=sys.executable, started="2026-01-01T00:00:00",
    )  # fmt: skip
    return dataclasses.replace(base, **changes)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# --- the record ------------------------------------------------------------------------------


def test_no_record_means_no_kept_ray(ray_dir: Path) -> None:
    assert kept.load() == (None, None)
    assert not kept.available()


def test_a_live_record_of_ours_is_trusted(ray_dir: Path, stand_in) -> None:
    kept._write(_record(stand_in))
    assert (kept.record_path().stat().st_mode & 0o777) == 0o600
    ray, why = kept.load()
    assert why is None and ray == _record(stand_in)
    assert kept.stop() == ray  # ends its process
    assert stand_in.wait(timeout=10) is not None and not kept.record_path().exists()


def test_a_stale_record_is_reported_and_removed(ray_dir: Path, stand_in) -> None:
    kept._write(_record(stand_in, pid=_dead_pid()))
    ray, why = kept.load()
    assert ray is None and "is gone" in why
    assert not kept.record_path().exists()


@pytest.mark.parametrize(
    ("changes", "needle"),
    [
        ({"temp_dir": "/nowhere/kept-x"}, "is not its `ray start` any more"),
        ({"python": "/other/python"}, "started by another comexp"),
        ({"comexp": "0.0.0"}, "started by another comexp"),
    ],
)
def test_a_foreign_record_is_not_trusted(
    ray_dir: Path, stand_in, changes: dict, needle: str
) -> None:
    kept._write(_record(stand_in, **changes))
    ray, why = kept.load()
    assert ray is None and needle in why
    assert kept.record_path().exists()  # its process lives: not ours to remove
    if "temp_dir" in changes:
        kept.stop()  # forgets the record, and leaves a process it does not own alone
        assert stand_in.poll() is None and not kept.record_path().exists()


def test_a_record_others_can_read_is_ignored(ray_dir: Path, stand_in) -> None:
    kept._write(_record(stand_in))
    kept.record_path().chmod(0o644)
    ray, why = kept.load()
    assert ray is None and "not this user's alone" in why


def test_an_unreadable_record_is_ignored(ray_dir: Path, stand_in) -> None:
    kept._write(_record(stand_in))
    kept.record_path().write_text("{not json")
    ray, why = kept.load()
    assert ray is None and "unreadable" in why


def test_the_token_is_exported_unless_the_user_set_ray_auth(
    ray_dir: Path, stand_in, monkeypatch
) -> None:
    kept._write(_record(stand_in))
    for k in kept.AUTH_KEYS:  # set first, so that the teardown removes what export_auth sets
        monkeypatch.setenv(k, "")
        monkeypatch.delenv(k)
    kept.export_auth()
    assert os.environ["RAY_AUTH_MODE"] == "token" and os.environ["RAY_AUTH_TOKEN"] == "t" * 64
    monkeypatch.setenv("RAY_AUTH_TOKEN", "mine")
    kept._write(_record(stand_in, token="u" * 64))
    kept.export_auth()
    assert os.environ["RAY_AUTH_TOKEN"] == "mine"


def test_the_code_stamp_follows_a_plugin_backends_module(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "my_engine_mod.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = kept.code_stamp("my_engine_mod.Engine")
    assert kept.code_stamp("my_engine_mod.Engine") == before
    (tmp_path / "my_engine_mod.py").write_text("X = 22\n")  # a new size
    assert kept.code_stamp("my_engine_mod.Engine") != before
    assert kept.code_stamp("") == kept.code_stamp("")


def _comexp_ray(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "comexp.cli.kept_ray", *args],
        capture_output=True, text=True, timeout=120, env=_env(),
    )  # fmt: skip


def test_status_and_stop_without_a_kept_ray(ray_dir: Path) -> None:
    r = _comexp_ray("status")
    assert r.returncode == 0 and "no kept Ray" in r.stdout
    r = _comexp_ray("stop")
    assert r.returncode == 0 and "no kept Ray was running" in r.stdout
    r = _comexp_ray("start", "--cpus", "0")
    assert r.returncode == 2 and r.stderr.strip() == "comexp-ray: error: --cpus must be >= 1, got 0"


def test_status_says_why_a_record_is_not_used(ray_dir: Path, stand_in) -> None:
    kept._write(_record(stand_in, pid=_dead_pid()))
    r = _comexp_ray("status")
    assert r.returncode == 1 and "is gone" in r.stdout


# --- a kept Ray and the jobs that use it ---------------------------------------------------


def _job(cwd: Path, *args: str) -> str:
    """The small job's log (Hydra logs to stdout) after it ran well."""
    r = comexp(cwd, *JOB, *args)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout + r.stderr


def _worker_pids(log: str) -> list[str]:
    return re.findall(r"worker \d ready: pid (\d+)", log)


def _episodes(db: Path) -> list[tuple]:
    with sqlite3.connect(db) as c:
        return c.execute(
            "select episode_key, est_com_x_cm, est_com_y_cm, error_cm, n_pushes, failure "
            "from episodes order by episode_key"
        ).fetchall()


def test_jobs_use_the_kept_ray_and_its_warm_workers(ray_dir: Path, tmp_path: Path) -> None:
    r = _comexp_ray("start")
    assert r.returncode == 0, r.stderr
    assert "keeps running" in r.stdout and "comexp-ray stop" in r.stdout
    ray, why = kept.load()
    assert why is None and ray is not None
    assert _comexp_ray("status").stdout.startswith(f"a kept Ray runs at {ray.address}")
    again = _comexp_ray("start")
    assert again.returncode == 2 and "runs already" in again.stderr

    first = _job(tmp_path, "db=kept1.db")
    assert "using the kept Ray" in first
    pids = _worker_pids(first)
    assert len(pids) == 2 and all(kept._alive(int(p)) for p in pids)  # left warm
    second = _job(tmp_path, "db=kept2.db")
    assert _worker_pids(second) == pids  # the same workers, warm
    assert "kernels ready" not in second  # nothing to load: the workers hold them

    own = _job(tmp_path, "ray.address=local", "db=own.db")
    assert "using the kept Ray" not in own
    assert not set(_worker_pids(own)) & set(pids)
    stored = _episodes(tmp_path / "own.db")
    assert len(stored) == 4
    assert _episodes(tmp_path / "kept1.db") == stored == _episodes(tmp_path / "kept2.db")

    r = _comexp_ray("stop")
    assert r.returncode == 0 and f"pid {ray.pid}" in r.stdout
    deadline = time.monotonic() + 10
    while any(kept._alive(int(p)) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(kept._alive(int(p)) for p in [ray.pid, *map(int, pids)])
    assert not kept.record_path().exists()
    assert _comexp_ray("status").stdout.startswith("no kept Ray")
