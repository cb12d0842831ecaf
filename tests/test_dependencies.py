"""Dependencies: what comexp/, backends/ and workers/ import is declared in pyproject.toml, and
what pyproject.toml declares is imported (an AST scan of every import, top-level or deferred).
"""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("comexp", "backends", "workers")
# distribution name (canonical) -> the top-level module it installs, where the two differ
IMPORT_NAMES = {
    "opencv-python-headless": "cv2",
    "pyyaml": "yaml",
    "hydra-core": "hydra",
    "psycopg": "psycopg",
}
# declared but reached without an import statement of ours: the PostgreSQL driver, which
# SQLAlchemy loads for postgresql:// URLs (the `postgres` extra), and SciPy, whose LAPACK
# Numba's np.linalg calls at run time (np.linalg.solve in backends/floor_friction.py's kernels:
# without SciPy they abort the process, "Specified LAPACK function could not be found")
NOT_IMPORTED = {"psycopg", "scipy"}
# extras for development only (the test suite, the linter)
DEV_EXTRAS = {"test"}


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _dist(requirement: str) -> str:
    return _canonical(re.split(r"[\s;<>=!~\[(]", requirement.strip(), maxsplit=1)[0])


def _declared() -> tuple[set[str], set[str]]:
    """(required distributions, optional ones outside the dev extras), canonical names."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    required = {_dist(r) for r in project["dependencies"]}
    optional = {
        _dist(r)
        for extra, reqs in project.get("optional-dependencies", {}).items()
        if extra not in DEV_EXTRAS
        for r in reqs
    }
    return required, optional


def _imported() -> dict[str, set[str]]:
    """Top-level third-party module -> the files that import it."""
    out: dict[str, set[str]] = {}
    for folder in SOURCES:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    mods = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    mods = [node.module]
                else:
                    continue
                for mod in mods:
                    top = mod.partition(".")[0]
                    if top == "comexp" or top in sys.stdlib_module_names:
                        continue
                    out.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return out


def _module(dist: str) -> str:
    return IMPORT_NAMES.get(dist, dist.replace("-", "_"))


def test_what_is_imported_is_declared() -> None:
    required, optional = _declared()
    modules = {_module(d) for d in required | optional}
    undeclared = {m: sorted(f) for m, f in _imported().items() if m not in modules}
    assert not undeclared, f"imported, not declared in pyproject.toml: {undeclared}"


def test_what_is_declared_is_imported() -> None:
    required, optional = _declared()
    imported = set(_imported())
    unused = sorted(
        d for d in required | optional if d not in NOT_IMPORTED and _module(d) not in imported
    )
    assert not unused, f"declared in pyproject.toml, imported nowhere: {unused}"


def test_scipy_is_what_numba_linalg_needs() -> None:
    """The reason SciPy is declared though nothing imports it: a Numba kernel that calls
    np.linalg.solve (as floor_friction's do) runs."""
    import numba
    import numpy as np

    @numba.njit(cache=False)
    def solve(a, b):
        return np.linalg.solve(a, b)

    assert np.allclose(solve(np.eye(2) * 2.0, np.ones(2)), [0.5, 0.5])


def test_the_scan_sees_the_imports() -> None:
    imported = _imported()
    assert {"numpy", "hydra", "ray", "sqlalchemy", "yaml", "cv2", "mujoco", "pybullet"} <= set(
        imported
    )
