"""The package reads as the architecture: one room per concern, the short module names the
README documents as thin re-export modules (the very objects of their room, no copies, no import
hook), the entry points and the config tree where pyproject says."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import comexp

ROOT = Path(__file__).resolve().parents[1]
ROOMS = {
    "method": {
        "estimator",
        "geometry",
        "observation",
        "perception",
        "rendering",
        "scene",
        "tracking",
    },
    "experiment": {
        "config",
        "contact",
        "episode",
        "grid",
        "interface",
        "objects",
        "registry",
        "simulator",
        "task",
        "view",
    },
    "cli": {"run", "query"},
}


def test_top_level_holds_only_the_package_and_its_rooms():
    top = {p.name for p in (ROOT / "comexp").iterdir() if not p.name.startswith((".", "__pyc"))}
    shorts = {f"{m.rpartition('.')[2]}.py" for m in SHORT}
    assert top == {"__init__.py", "method", "experiment", "results", "cli"} | shorts
    for room, modules in ROOMS.items():
        files = {p.stem for p in (ROOT / "comexp" / room).glob("*.py")} - {"__init__"}
        assert modules <= files, room


# the short names the README and docs use -> the module in its room they re-export
SHORT = {
    "comexp.estimator": "comexp.method.estimator",
    "comexp.perception": "comexp.method.perception",
    "comexp.scene": "comexp.method.scene",
    "comexp.objects": "comexp.experiment.objects",
    "comexp.simulator": "comexp.experiment.simulator",
    "comexp.reports": "comexp.results.reports",
}
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FILE_NAMES = {"comexp.log"}  # Hydra's job log, written `comexp.log` in the docs: not a name


def test_the_short_names_are_the_re_export_modules():
    assert {f"comexp.{n}" for n in comexp.SHORT_MODULES} == set(SHORT)
    shorts = {p.stem for p in (ROOT / "comexp").glob("*.py")} - {"__init__"}
    assert {f"comexp.{n}" for n in shorts} == set(SHORT)


@pytest.mark.parametrize("short, real", sorted(SHORT.items()))
def test_a_short_name_re_exports_the_very_objects_of_its_room(short, real):
    mod, room = importlib.import_module(short), importlib.import_module(real)
    assert mod.__all__, short
    for name in mod.__all__:
        assert getattr(mod, name) is getattr(room, name), f"{short}.{name}"
    assert getattr(comexp, short.rpartition(".")[2]) is mod
    assert room.__spec__.name == real  # the real module keeps its own name
    first = (mod.__doc__ or "").splitlines()[0]
    assert f"`{real}`" in first, f"{short}: the docstring names the module it re-exports"


# modules that were split by job, and the names their old paths keep re-exporting (users'
# code, notebooks and bench scripts import them there): old module -> {name: real module}
SPLIT = {
    "comexp.method.perception": {
        "observe": "comexp.method.observation",
        "perceive_first": "comexp.method.observation",
        "mask_pusher": "comexp.method.observation",
        "observe_boundary": "comexp.method.observation",
        "PerceptionError": "comexp.method.observation",
        "PoseTracker": "comexp.method.tracking",
        "PoseFit": "comexp.method.tracking",
        "render_prism_depth": "comexp.method.rendering",
        "render_prism_depth_numpy": "comexp.method.rendering",
    },
    "comexp.experiment.simulator": {
        "Simulator": "comexp.experiment.interface",
        "PushOutcome": "comexp.experiment.interface",
        "PushStatus": "comexp.experiment.interface",
        "Frame": "comexp.experiment.interface",
        "at_rest": "comexp.experiment.interface",
        "classify_state": "comexp.experiment.interface",
        "make_simulator": "comexp.experiment.registry",
        "physics_identity": "comexp.experiment.registry",
        "backend_names": "comexp.experiment.registry",
        "BACKENDS": "comexp.experiment.registry",
        "object_window_px": "comexp.experiment.view",
        "crop_camera": "comexp.experiment.view",
        "surely_in_view": "comexp.experiment.view",
        "contact_push": "comexp.experiment.contact",
        "pusher_contact_height_m": "comexp.experiment.contact",
        "point_polygon_distance": "comexp.experiment.contact",
    },
    "comexp.experiment.episode": {
        "EpisodeSpec": "comexp.experiment.task",
        "EpisodeResult": "comexp.experiment.task",
        "PushRecord": "comexp.experiment.task",
        "build_scene": "comexp.experiment.task",
        "initial_yaw_rad": "comexp.experiment.task",
    },
}


@pytest.mark.parametrize("old", sorted(SPLIT))
def test_a_split_module_keeps_its_old_names(old):
    mod = importlib.import_module(old)
    for name, real in SPLIT[old].items():
        assert getattr(mod, name) is getattr(importlib.import_module(real), name), name
        assert name in mod.__all__, f"{old}.__all__ lacks {name}"


def test_every_module_names_its_one_job_first():
    """A module's first docstring line names its job (what a reader sees first)."""
    bad = []
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            if path.name != "__init__.py" and not doc.strip():
                bad.append(str(path.relative_to(ROOT)))
    assert not bad, f"modules without a docstring: {bad}"


def test_no_import_hook():
    """Plain imports: nothing of comexp's in the import system (IDEs, type checkers and
    readers follow every name)."""
    code = (
        "import sys, comexp, comexp.estimator, comexp.reports\n"
        "hooks = [f for f in sys.meta_path if type(f).__module__.startswith('comexp')]\n"
        "assert not hooks, hooks\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def _resolve(dotted: str) -> object:
    """The object a dotted name names: its longest importable module prefix, then attributes."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:n]))
        except ModuleNotFoundError:
            continue
        for attr in parts[n:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


def test_names_the_docs_use_resolve():
    """Every dotted `comexp.` name and `from comexp... import <names>` of the README and docs/
    names something that exists (the short names among them)."""
    names = set()
    for doc in DOCS:
        text = doc.read_text()
        for m in re.finditer(r"`(comexp(?:\.[A-Za-z_]\w*)+)", text):
            if m.group(1) not in FILE_NAMES:
                names.add((doc.name, m.group(1)))
        for m in re.finditer(r"from (comexp(?:\.\w+)*) import ([\w, ]+)", text):
            names |= {(doc.name, f"{m.group(1)}.{n.strip()}") for n in m.group(2).split(",")}
    bad = []
    for where, dotted in sorted(names):
        try:
            _resolve(dotted)
        except (ImportError, AttributeError) as e:
            bad.append(f"{where}: {dotted} ({e})")
    assert not bad, "\n".join(bad)
    shorts = {d.split(".")[1] for _, d in names} & set(comexp.SHORT_MODULES)
    assert shorts == set(comexp.SHORT_MODULES), "the docs use every short name"


def test_documented_names_in_a_fresh_interpreter():
    code = (
        "import comexp.estimator, comexp.perception\n"
        "from comexp.reports import group_episodes\n"
        "from comexp.estimator import ObservedPush, estimate_com\n"
        "import comexp\n"
        "assert callable(comexp.load_results) and callable(comexp.replay)\n"
        "assert group_episodes.__module__ == 'comexp.results.reports'\n"
        "import comexp.method.estimator as m\n"
        "assert comexp.estimator.estimate_com is m.estimate_com\n"
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


# At most this many functions over LONG_LINES lines in the package (comexp/, backends/, workers/):
# a long function does several jobs that want names of their own. A compiled kernel (Numba's
# njit) may stay long where splitting it costs speed; it says so in its docstring.
LONG_LINES = 80
MAX_LONG_FUNCTIONS = 3
PACKAGE_DIRS = ("comexp", "backends", "workers")


def _long_functions() -> dict[str, ast.FunctionDef | ast.AsyncFunctionDef]:
    """`path:line name` -> node, for every function or method over LONG_LINES lines (from
    `def` to its last line, decorators not counted)."""
    out = {}
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if (
                    isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
                    and node.end_lineno - node.lineno + 1 > LONG_LINES
                ):
                    out[f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"] = node
    return out


def _compiled(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """Decorated with Numba's njit (or jit), bare or called."""
    for d in node.decorator_list:
        f = d.func if isinstance(d, ast.Call) else d
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        if name in ("njit", "jit"):
            return True
    return False


def test_few_long_functions():
    long = _long_functions()
    assert len(long) <= MAX_LONG_FUNCTIONS, (
        f"{len(long)} functions over {LONG_LINES} lines (at most {MAX_LONG_FUNCTIONS}): "
        + ", ".join(sorted(long))
    )


def test_a_long_compiled_kernel_says_why():
    for where, node in _long_functions().items():
        if _compiled(node):
            doc = ast.get_docstring(node) or ""
            assert "Long on purpose" in doc, f"{where}: say why the kernel is not split"
