"""The package reads as it runs: one name per thing (no module only re-exports another), rooms
by concern with the driver/worker line drawn (the episode side imports no Hydra and no driver
module), an import graph drawn from the code's own imports with no circle and no import running
back up, imports at the top of modules, few long functions, the entry points and the config
tree where pyproject says."""

from __future__ import annotations

import ast
import importlib
import re
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import comexp

ROOT = Path(__file__).resolve().parents[1]
# the rooms, top floor first: a module imports only from its own room or a room below it
FLOORS = [
    ("cli", "api"),
    ("experiment",),
    ("workers", "real"),
    ("results",),
    ("episode",),
    ("backends",),
    ("sim",),
    ("method",),
]
# the episode side: what a Ray worker imports to run an episode
EPISODE_SIDE = ("episode", "backends", "sim", "method")
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FILE_NAMES = {"comexp.log"}  # Hydra's job log, written `comexp.log` in the docs: not a name
PACKAGE_DIRS = ("comexp", "backends", "workers")


def _modules() -> dict[str, Path]:
    """Every module of the package by its import name (backends/ and workers/ live in the
    comexp namespace, as pyproject maps them)."""
    out = {}
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if parts[0] != "comexp":
                parts = ["comexp", *parts]
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _room(module: str) -> str:
    """A module's room: the folder below `comexp` (`comexp.api` is a room of its own)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _floor(room: str) -> int:
    for i, rooms in enumerate(FLOORS):
        if room in rooms:
            return i
    raise AssertionError(f"room {room!r} is on no floor of the house: add it to FLOORS")


def _imports(path: Path, *, top_level_only: bool) -> list[tuple[str, int, bool]]:
    """(imported comexp module, line, at the module's top level) of one file."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        at_top = id(node) in top
        if top_level_only and not at_top:
            continue
        if isinstance(node, ast.ImportFrom) and node.level:
            base = _package_of(path)
            mod = ".".join(base.split(".")[: len(base.split(".")) - node.level + 1])
            mod = f"{mod}.{node.module}" if node.module else mod
            names = [f"{mod}.{a.name}" for a in node.names]
            out += [(n if n in MODULES else mod, node.lineno, at_top) for n in names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("comexp"):
            names = [f"{node.module}.{a.name}" for a in node.names]
            out += [(n if n in MODULES else node.module, node.lineno, at_top) for n in names]
        elif isinstance(node, ast.Import):
            out += [
                (a.name, node.lineno, at_top) for a in node.names if a.name.startswith("comexp")
            ]
    return out


def _package_of(path: Path) -> str:
    name = next(m for m, p in MODULES.items() if p == path)
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _graph() -> dict[str, set[str]]:
    """module -> the comexp modules it imports (at its top level)."""
    graph = {}
    for mod, path in MODULES.items():
        graph[mod] = {m for m, _, _ in _imports(path, top_level_only=True) if m in MODULES}
    return graph


def test_every_room_is_on_a_floor():
    rooms = {_room(m) for m in MODULES} - {""}
    for room in rooms:
        _floor(room)


def test_no_module_only_re_exports_another():
    """One name per thing: every module defines something of its own."""
    bad = []
    for mod, path in MODULES.items():
        if path.name == "__init__.py":
            continue
        body = [
            n
            for n in ast.parse(path.read_text()).body
            if not isinstance(n, ast.Import | ast.ImportFrom | ast.Expr)
            and not (
                isinstance(n, ast.Assign)
                and [t.id for t in n.targets if isinstance(t, ast.Name)] == ["__all__"]
            )
        ]
        if not body:
            bad.append(mod)
    assert not bad, f"modules that only re-export others: {bad}"


def test_a_package_init_defines_no_names_of_its_submodules():
    """A room's `__init__` says what the room is; it re-exports nothing (the package's own
    `comexp/__init__` gives the notebook API by name, imported on first use)."""
    for mod, path in MODULES.items():
        if path.name != "__init__.py" or mod == "comexp":
            continue
        tree = ast.parse(path.read_text())
        assert all(isinstance(n, ast.Expr) for n in tree.body), f"{mod}: a docstring only"


def test_no_import_circle():
    graph = _graph()
    seen: dict[str, int] = {}  # 1: on the path, 2: done
    stack: list[str] = []

    def visit(m: str) -> None:
        seen[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if seen.get(n) == 1:
                raise AssertionError(" -> ".join(stack[stack.index(n) :] + [n]))
            if n not in seen:
                visit(n)
        stack.pop()
        seen[m] = 2

    for m in sorted(graph):
        if m not in seen:
            visit(m)


def test_no_import_runs_back_up():
    """A module imports from its own room or a room below: the house reads top down."""
    bad = []
    for mod, deps in _graph().items():
        for dep in deps:
            a, b = _room(mod), _room(dep)
            if a and b and a != b and _floor(b) < _floor(a):
                bad.append(f"{mod} -> {dep}")
    assert not bad, "imports running back up: " + ", ".join(sorted(bad))


def test_imports_are_at_the_top_of_modules():
    """A walk from the job to the episode loop is never lost at a function-local import; a
    deferred import says why (a measured start-up cost) on its line or the line above."""
    bad = []
    for _mod, path in MODULES.items():
        lines = path.read_text().splitlines()
        for dep, line, at_top in _imports(path, top_level_only=False):
            if at_top:
                continue
            said = " ".join(lines[max(0, line - 2) : line])
            if "start-up" not in said and "first use" not in said:
                bad.append(f"{path.relative_to(ROOT)}:{line} {dep}")
    assert not bad, "function-local imports of comexp: " + ", ".join(bad)


def test_the_episode_side_imports_no_hydra_and_no_driver_module():
    """What a Ray worker imports to run an episode: `comexp.episode.loop`, the backends, and
    everything they import, in a fresh interpreter."""
    code = (
        "import sys\n"
        "import comexp.episode.loop, comexp.backends.planar_sim, comexp.backends.pybullet_sim\n"
        "import comexp.workers.actor\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'omegaconf', 'pandas',"
        " 'sqlalchemy', 'matplotlib') or m.startswith(('comexp.experiment', 'comexp.results',"
        " 'comexp.cli', 'comexp.api')))\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_no_patching_of_third_party_internals():
    """The package sets nothing on other packages' modules or private names: no
    `module.attr = ...` on an imported third-party module, no `ray._private`/`ray._raylet`, no
    replaced logging record factory."""
    bad = []
    for path in MODULES.values():
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            elif isinstance(node, ast.Attribute):
                names = [ast.unparse(node)]
            for name in names:
                if name.startswith(("ray._private", "ray._raylet")) or "RecordFactory" in name:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {name}")
    assert not bad, bad


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
        "import sys, comexp, comexp.method.estimator, comexp.results.reports\n"
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
    names something that exists."""
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


def test_the_notebook_api_and_the_robot_library_in_a_fresh_interpreter():
    code = (
        "import comexp\n"
        "assert callable(comexp.load_results) and callable(comexp.replay)\n"
        "assert callable(comexp.run)\n"
        "from comexp.method.estimator import ObservedPush, estimate_com, estimate_com_world\n"
        "from comexp.results.reports import group_episodes\n"
        "assert group_episodes.__module__ == 'comexp.results.reports'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_import_comexp_stays_light():
    """`import comexp` loads the kept Ray's record reader (its token must be in the
    environment before anything imports Ray) and nothing else of the package, nor Ray, NumPy
    or Hydra: the notebook API is imported on first use."""
    code = (
        "import sys, comexp; print(sorted(m for m in sys.modules if m.startswith('comexp')));"
        "print(sorted(m for m in ('ray', 'numpy', 'hydra', 'sqlalchemy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    mine, heavy = out.stdout.strip().splitlines()
    assert mine == "['comexp', 'comexp.workers', 'comexp.workers.kept']"
    assert heavy == "[]"


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
