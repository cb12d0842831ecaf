"""The Makefile's two commands, dry-run (`make -n`, nothing installed): `make run` installs what
a job needs (no extras, no PostgreSQL server; EGL only for backend=mujoco), `make test` installs
every extra and the PostgreSQL server its tests start. Both create their venv when missing."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make not installed")


def _dry_run(target: str, venv: Path, *extra: str) -> str:
    res = subprocess.run(
        ["make", "-n", "--no-print-directory", target, f"VENV={venv}", *extra],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return res.stdout


def test_make_run_installs_only_what_the_job_needs(tmp_path: Path) -> None:
    venv = tmp_path / "venv"  # missing: the venv is created
    out = _dry_run("run", venv)
    assert f"python3 -m venv {venv}" in out
    assert "pip install -q -c requirements.lock -e .\n" in out and "-e '.[" not in out
    assert "postgresql" not in out and "libegl" not in out
    assert out.rstrip().endswith(f"{venv}/bin/comexp")
    mujoco = _dry_run("run", venv, "ARGS=backend=mujoco grid.coms_per_object=1")
    assert "libegl1" in mujoco and "postgresql" not in mujoco
    assert mujoco.rstrip().endswith(f"{venv}/bin/comexp backend=mujoco grid.coms_per_object=1")


def test_make_test_installs_every_extra_and_the_postgres_server(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    out = _dry_run("test", venv)
    assert f"python3 -m venv {venv}" in out
    assert "-e '.[" in out and "test" in out.split("-e '.[", 1)[1].split("]", 1)[0]
    assert "apt-get install -y -qq postgresql" in out and "libegl1" in out
    assert f"{venv}/bin/python -m pytest" in out


def test_a_full_install_satisfies_make_run(tmp_path: Path) -> None:
    """After `make test` (or `make install`) `make run` installs nothing more."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    for stamp in (".installed", ".installed-run"):
        (venv / stamp).touch()
    out = _dry_run("run", venv)
    assert "pip install" not in out and out.strip() == f"{venv}/bin/comexp"
