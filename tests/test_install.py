"""What `make install` gives: a venv that holds exactly requirements.lock (no more, no less, same
versions), and a package that builds without warnings and, installed from its wheel, finds its
own config tree (`pkg://comexp.conf`) from any directory.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import site
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "requirements.lock"


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _lock_exclude() -> set[str]:
    """The Makefile's LOCK_EXCLUDE: names `make lock` leaves out, so the check skips them."""
    m = re.search(r"^LOCK_EXCLUDE\s*:=(.*)$", (ROOT / "Makefile").read_text(), re.MULTILINE)
    assert m, "no LOCK_EXCLUDE in the Makefile"
    return {_canonical(n) for n in m.group(1).split()}


def _locked() -> dict[str, str]:
    out: dict[str, str] = {}
    for raw in LOCK.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        assert sep and version.strip(), f"requirements.lock: {raw!r} is not NAME==VERSION"
        assert _canonical(name) not in out, f"requirements.lock: {name} listed twice"
        out[_canonical(name)] = version.strip()
    return out


def _not_the_project_venv() -> str | None:
    """Why the venv check does not apply here, or None when it does."""
    if not LOCK.is_file():
        return "requirements.lock not found: not running from a source checkout"
    prefix = Path(sys.prefix).resolve()
    if prefix != (ROOT / ".venv").resolve() and not (prefix / ".installed").is_file():
        return f"not running from a virtualenv made by `make install` (sys.prefix={sys.prefix})"
    return None


@pytest.mark.skipif(not LOCK.is_file(), reason="requirements.lock not found")
def test_lock_is_names_and_exact_versions_of_packages_only() -> None:
    locked = _locked()
    assert len(locked) > 10
    excluded = _lock_exclude()
    assert {"comexp", "pip"} <= excluded
    assert not excluded & set(locked), "make lock leaves these out; the lock lists them"
    for name, version in locked.items():
        Version(version)  # raises on anything but a plain version (no URLs, no ranges)
        assert name == _canonical(name)


def test_venv_holds_exactly_the_locked_packages() -> None:
    """A drift either way fails: a package the lock does not list (a dependency added to
    pyproject.toml without `make lock`, or installed by hand), a locked one missing, or another
    version than the locked one."""
    reason = _not_the_project_venv()
    if reason:
        pytest.skip(reason)
    excluded = _lock_exclude()
    locked = _locked()
    installed: dict[str, set[str]] = {}
    # The venv's site-packages only: sys.path can hold more once a test imported ray, which
    # puts its vendored psutil and colorama (ray/thirdparty_files) on it.
    for dist in metadata.distributions(path=site.getsitepackages()):
        name = dist.metadata["Name"]
        if name and _canonical(name) not in excluded:
            installed.setdefault(_canonical(name), set()).add(dist.version)
    problems = [
        f"{n} {sorted(v)} installed, not in the lock"
        for n, v in installed.items()
        if n not in locked
    ]
    problems += [f"{n}=={v} locked, not installed" for n, v in locked.items() if n not in installed]
    for n in sorted(set(locked) & set(installed)):
        if {Version(v) for v in installed[n]} != {Version(locked[n])}:
            problems.append(f"{n}: installed {sorted(installed[n])}, locked {locked[n]}")
    assert not problems, (
        "the venv and requirements.lock differ (dependencies changed: run `make lock`; "
        "a stale or hand-extended venv: `make clean install`):\n  " + "\n  ".join(problems)
    )


# --- the package built as users get it ------------------------------------------------------


def _source_copy(dest: Path) -> None:
    """What the build reads (as the Dockerfile COPYs it), outside the checkout: the build
    then leaves nothing in the worktree and proves the list complete."""
    import tomllib

    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    for name in ("pyproject.toml", pyproject["project"]["readme"]):
        shutil.copy2(ROOT / name, dest / name)
    for folder in pyproject["tool"]["setuptools"]["package-dir"].values():
        shutil.copytree(ROOT / folder, dest / folder, ignore=shutil.ignore_patterns("__pycache__"))


def _warning_lines(output: str) -> list[str]:
    """setuptools' warnings reach pip's output (license format, data folders taken for
    packages, ...); pip's own notices about this machine's index locations are not ours."""
    return [
        ln
        for ln in output.splitlines()
        if re.search(r"warn", ln, re.IGNORECASE) and not ln.startswith("WARNING: Location ")
    ]


def test_editable_install_as_the_makefile_runs_it_prints_no_warnings(tmp_path: Path) -> None:
    """`make install`'s editable build, with the Makefile's PYTHONWARNINGS filter for
    setuptools' "Editable installation" notice; the installed finder maps the package-dir
    layout (comexp.backends -> backends/, ...)."""
    m = re.search(r"^NO_EDITABLE_NOTICE\s*:=(.*)$", (ROOT / "Makefile").read_text(), re.M)
    assert m, "no NO_EDITABLE_NOTICE in the Makefile"
    env = dict(os.environ)
    for word in shlex.split(m.group(1)):
        key, _, value = word.partition("=")
        env[key] = value
    src = tmp_path / "src"
    src.mkdir()
    _source_copy(src)
    site = tmp_path / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "-e", str(src)]
        + ["--target", str(site)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    assert not _warning_lines(r.stdout + r.stderr), r.stdout + r.stderr
    # -S: without the venv's own site-packages, whose editable finder maps this checkout
    probe = (
        "import site, sys; site.addsitedir(sys.argv[1]); "
        "import comexp.backends, comexp.conf; print(comexp.backends.__file__)"
    )
    r = subprocess.run(
        [sys.executable, "-S", "-c", probe, str(site)], capture_output=True, text=True, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(src / "backends" / "__init__.py")


def test_wheel_builds_without_warnings_and_finds_its_configs_installed(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    _source_copy(src)
    wheels = tmp_path / "wheels"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", str(src), "-w", str(wheels)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    warnings = _warning_lines(r.stdout + r.stderr)
    assert not warnings, "\n".join(warnings)
    (wheel,) = wheels.glob("comexp-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {
        f"comexp/conf/{p.relative_to(ROOT / 'conf')}" for p in (ROOT / "conf").rglob("*.yaml")
    }
    assert shipped and shipped <= names, sorted(shipped - names)
    tops = {n.split("/", 1)[0] for n in names}
    assert tops == {"comexp", wheel.name.split("-py3")[0] + ".dist-info"}, tops  # no squatting
    meta = zipfile.ZipFile(wheel).read(f"{wheel.name.split('-py3')[0]}.dist-info/METADATA")
    assert b"License-Expression: MIT" in meta

    site = tmp_path / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), wheel],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    run = tmp_path / "run"
    run.mkdir()
    probe = (
        "import sys, comexp; from comexp.cli.run import main;"
        " print('FROM', comexp.__file__); main()"
    )
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    for args, needle in [(["--help"], "l_shape"), (["--cfg", "job", "floor=aniso"], "- yx")]:
        r = subprocess.run(
            [sys.executable, "-c", probe, *args],
            cwd=run,
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        assert r.returncode == 0, r.stderr
        assert f"FROM {site}/comexp/__init__.py" in r.stdout  # the wheel's copy, not the checkout
        assert needle in r.stdout, r.stdout
    assert list(run.iterdir()) == []
