"""The package reads as the architecture: one room per concern, the module names the README
documents importable as the very modules in their room (no copies), the entry points and the
config tree where pyproject says."""

from __future__ import annotations

import importlib
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import comexp

ROOT = Path(__file__).resolve().parents[1]
ROOMS = {
    "method": {"estimator", "geometry", "perception", "scene"},
    "experiment": {"config", "episode", "grid", "objects", "simulator"},
    "cli": {"run", "query"},
}


def test_top_level_holds_only_the_package_and_its_rooms():
    top = {p.name for p in (ROOT / "comexp").iterdir() if not p.name.startswith((".", "__pyc"))}
    assert top == {"__init__.py", "method", "experiment", "results", "cli"}
    for room, modules in ROOMS.items():
        files = {p.stem for p in (ROOT / "comexp" / room).glob("*.py")} - {"__init__"}
        assert modules <= files, room


@pytest.mark.parametrize("alias, real", sorted(comexp._ALIASES.items()))
def test_documented_names_are_the_modules_in_their_rooms(alias, real):
    assert importlib.import_module(alias) is importlib.import_module(real)
    assert importlib.import_module(real).__spec__.name == real  # not renamed by the alias


def test_documented_names_in_a_fresh_interpreter():
    code = (
        "import comexp.estimator, comexp.perception\n"
        "from comexp.reports import group_episodes\n"
        "from comexp.estimator import ObservedPush, estimate_com\n"
        "import comexp\n"
        "assert callable(comexp.load_results) and callable(comexp.replay)\n"
        "assert group_episodes.__module__ == 'comexp.results.reports'\n"
        "import comexp.method.estimator as m\n"
        "assert comexp.estimator is m\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_import_comexp_stays_light():
    code = "import sys, comexp; print(sorted(m for m in sys.modules if m.startswith('comexp')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['comexp']"


def test_unknown_attribute_is_an_attribute_error():
    with pytest.raises(AttributeError):
        _ = comexp.no_such_module


@pytest.mark.parametrize(
    "name, target", [("comexp", "comexp.cli.run"), ("comexp-db", "comexp.cli.query")]
)
def test_console_scripts_point_into_the_cli_room(name, target):
    (ep,) = [e for e in entry_points(group="console_scripts") if e.name == name]
    assert ep.value == f"{target}:main"
    assert callable(ep.load())


def test_every_module_of_the_package_is_tracked_by_git():
    """A room's name must not fall under an ignore rule (`results/` once hid comexp/results/'s
    new modules from `git add`: the tree worked, a checkout would not have)."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    dirs = ("comexp", "backends", "workers")
    res = subprocess.run(
        ["git", "ls-files", "--others", "--ignored", "--exclude-standard", *dirs],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    )
    hidden = [f for f in res.stdout.split() if f.endswith(".py")]
    assert hidden == [], f"ignored by .gitignore: {hidden}"
