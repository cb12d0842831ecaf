"""A job's config sources, read as Hydra reads them: where a config group's files are found
(the package's `conf/`, `--config-dir`, `hydra.searchpath` entries: Hydra's
`hydra.runtime.config_sources`), and the mapping in one file, with YAML errors in one line.

The objects (`object/NAME.yaml`) and the backends (`backend/NAME.yaml`) are looked up here by
name, outside Hydra's composition: a job's grid names many objects, and a stored episode names
its backend.
"""

from __future__ import annotations

import importlib.resources
import os
from collections.abc import Mapping, Sequence
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf

# The package's own config tree alone: the built-in objects and backends (conf/).
PACKAGE_SOURCES: tuple[Mapping[str, str], ...] = (
    {"provider": "main", "schema": "pkg", "path": "comexp.conf"},
)


def source_root(source: Mapping[str, Any]) -> Traversable | None:
    """The folder behind one Hydra config source; None for the ConfigStore (`structured://`,
    which holds the schema only) and for a package that is not installed."""
    schema, path = str(source["schema"]), str(source["path"])
    if schema == "file":
        return Path(os.path.realpath(path))  # as Hydra's file source names its files
    if schema == "pkg":
        module, _, sub = path.partition("/")
        try:
            root = importlib.resources.files(module)
        except ModuleNotFoundError:
            return None
        return root.joinpath(sub) if sub else root
    return None


def group_files(group: str, sources: Sequence[Mapping[str, Any]]) -> dict[str, Traversable]:
    """name -> file for every option of config group `group` the sources hold; the first source
    with a name wins."""
    out: dict[str, Traversable] = {}
    for source in sources:
        root = source_root(source)
        folder = root.joinpath(group) if root is not None else None
        if folder is None or not folder.is_dir():
            continue
        for f in sorted(folder.iterdir(), key=lambda f: f.name):
            if f.is_file() and f.name.endswith(".yaml"):
                out.setdefault(f.name.removesuffix(".yaml"), f)
    return out


def yaml_error_line(e: yaml.YAMLError) -> str:
    """`malformed YAML in FILE, line L, column C: problem (context at line, column)`: PyYAML's
    multi-line message in one line, positions 1-based as editors count them."""
    if not isinstance(e, yaml.MarkedYAMLError) or e.problem_mark is None:
        text = [t.strip() for t in str(e).splitlines() if t.strip()]
        return f"malformed YAML: {' '.join(text[:2]) or type(e).__name__}"
    mark = e.problem_mark
    out = f"malformed YAML in {mark.name}, line {mark.line + 1}, column {mark.column + 1}: "
    out += e.problem or "syntax error"
    ctx = e.context_mark
    if e.context and ctx is not None:
        where = f"line {ctx.line + 1}, column {ctx.column + 1}"
        out += f" ({e.context} at {where})" if ctx.name == mark.name else f" ({e.context})"
    return out


def read_mapping(what: str, file: Traversable) -> dict[str, Any]:
    """The mapping in one config file, read as Hydra reads config files (OmegaConf's YAML,
    interpolations resolved, a `defaults` list ignored); ValueError (one line starting with
    `what`) otherwise."""
    try:
        with file.open(encoding="utf-8") as f:
            node = OmegaConf.load(f)
    except yaml.YAMLError as e:
        raise ValueError(f"{what}: {yaml_error_line(e)}") from None
    if OmegaConf.is_dict(node) and "defaults" in node:
        node = OmegaConf.masked_copy(node, [k for k in node if k != "defaults"])
    data = OmegaConf.to_container(node, resolve=True)
    if not isinstance(data, dict):
        raise ValueError(f"{what}: config must be a mapping")
    return data
