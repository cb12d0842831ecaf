"""The files under docker/, checked without a Docker engine (this machine has only the client):
the compose file is a head, two workers and a sweep with the database on a volume; the image
installs the way the Makefile does and copies everything that install needs; the cluster
launcher config runs the same image with start commands consistent with the compose file.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
DOCKER = ROOT / "docker"


def _load(name: str) -> dict[str, Any]:
    data = yaml.safe_load((DOCKER / name).read_text())
    assert isinstance(data, dict), name
    return data


def _words(command: Any) -> list[str]:
    """A compose/launcher command (list or string) as shell words."""
    text = command if isinstance(command, str) else " ".join(map(str, command))
    return shlex.split(text)


def _dockerfile() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) in order, continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in (DOCKER / "Dockerfile").read_text().splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        op, _, args = buf.partition(" ")
        out.append((op.upper(), args.strip()))
        buf = ""
    return out


def _copied() -> list[tuple[int, str]]:
    """(instruction index, source path) of every COPY from the build context."""
    out = []
    for i, (op, args) in enumerate(_dockerfile()):
        if op != "COPY":
            continue
        words = [w for w in shlex.split(args) if not w.startswith("--")]
        out += [(i, src.rstrip("/")) for src in words[:-1]]
    return out


def _run_index(needle: str) -> int:
    hits = [i for i, (op, args) in enumerate(_dockerfile()) if op == "RUN" and needle in args]
    assert len(hits) == 1, f"expected one RUN with {needle!r}, found {len(hits)}"
    return hits[0]


def _make_prerequisites(target: str) -> list[str]:
    """Prerequisites of a Makefile rule (`$(STAMP)` style names as written)."""
    text = (ROOT / "Makefile").read_text()
    m = re.search(rf"^{re.escape(target)}\s*:(?!=)(.*)$", text, re.MULTILINE)
    assert m, f"no rule {target!r} in the Makefile"
    return m.group(1).split()


# --- compose -----------------------------------------------------------------------------------


def test_compose_has_a_head_two_workers_and_a_sweep_on_a_volume() -> None:
    c = _load("compose.yaml")
    services = c["services"]
    workers = [n for n in services if n.startswith("ray-worker")]
    assert "ray-head" in services and "sweep" in services and len(workers) == 2
    for name, svc in services.items():
        assert svc.get("image") == "comexp:latest", name  # one image everywhere
        build = svc.get("build")
        if build:
            assert (DOCKER / build["context"] / build["dockerfile"]).resolve() == (
                DOCKER / "Dockerfile"
            ), name
    head = _words(services["ray-head"]["command"])
    assert head[:3] == ["ray", "start", "--head"] and "--port=6379" in head and "--block" in head
    assert "--num-cpus=0" in head  # the head schedules; episodes run on the workers
    cpus = 0
    for w in workers:
        words = _words(services[w]["command"])
        assert words[:2] == ["ray", "start"] and "--address=ray-head:6379" in words
        assert "--block" in words  # else the container exits and takes the node with it
        assert services[w]["depends_on"]["ray-head"]["condition"] == "service_healthy"
        cpus += int(next(x for x in words if x.startswith("--num-cpus=")).split("=")[1])
    sweep = services["sweep"]
    text = " ".join(_words(sweep["entrypoint"]) + _words(sweep["command"]))
    assert "comexp ray.address=ray-head:6379" in text
    # comexp joins as a zero-CPU node of its own (workers/session.py JoinNode): the container
    # starts no Ray node itself, but needs the shared memory of that node's object store
    assert "ray start" not in text
    assert sweep.get("shm_size"), "the sweep's join node keeps its object store in /dev/shm"
    for name, svc in services.items():
        assert svc.get("init") is True, f"{name}: PID 1 must reap Ray's orphaned daemons"
    assert f"workers={cpus}" in text and f"/{cpus:.1f} CPU" in text  # waits for all CPUs
    db = re.search(r"\bdb=(\S+)", text)
    assert db, text
    mounts = {m.split(":")[1]: m.split(":")[0] for m in sweep["volumes"]}
    assert any(db.group(1).startswith(target + "/") for target in mounts), (db, mounts)
    volume = mounts[next(t for t in mounts if db.group(1).startswith(t + "/"))]
    assert volume in (c.get("volumes") or {}), "the database volume must be a named volume"
    assert sweep.get("working_dir") in mounts  # Hydra's run folders (reports) too
    assert set(sweep["depends_on"]) == {"ray-head", *workers}


# --- the image -----------------------------------------------------------------------------------


def test_dockerfile_installs_with_the_makefile_and_copies_what_it_needs() -> None:
    steps = _dockerfile()
    assert steps[0][0] == "FROM" and "python:3.11" in steps[0][1]
    runs = [args for op, args in steps if op == "RUN"]
    # the project's own install is the Makefile's, not a second recipe that could drift
    assert not any(re.search(r"\bpip3?\b.*\binstall\b", r) for r in runs), runs
    system_deps, install = _run_index("make system-deps"), _run_index("make install")
    copied = _copied()
    copied_names = {src for _, src in copied}

    def copied_before(path: str, step: int) -> bool:
        return any(src == path and i < step for i, src in copied)

    # make's own inputs
    assert copied_before("Makefile", system_deps) and copied_before("Makefile", install)
    # everything the install rule depends on: `install: system-deps $(STAMP)` and the
    # stamp rule's prerequisites (pyproject.toml, requirements.lock)
    install_prereqs = _make_prerequisites("install")
    assert "system-deps" in install_prereqs
    stamp = next(p for p in install_prereqs if p != "system-deps")
    for f in _make_prerequisites(stamp):
        assert copied_before(f, install), f"{f} (a prerequisite of {stamp}) is not copied"
        assert (ROOT / f).is_file(), f
    # what pip needs to build the package: the readme and every package folder
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    readme = pyproject["project"].get("readme")
    if readme:
        assert copied_before(readme, install)
    for pkg, folder in pyproject["tool"]["setuptools"]["package-dir"].items():
        assert copied_before(folder, install), f"package {pkg} ({folder}/) is not copied"
        assert (ROOT / folder).is_dir()
    for src in copied_names:
        assert (ROOT / src).exists(), f"COPY {src}: no such file in the repository"
    # the installed commands are on PATH for every service
    env = " ".join(args for op, args in steps if op == "ENV")
    venv = re.search(r"make install VENV=(\S+)", runs[[*runs].index(steps[install][1])])
    assert venv and f"PATH={venv.group(1)}/bin:" in env
    assert "MUJOCO_GL=egl" in env  # headless rendering (the backend's default), explicit here


def test_build_context_ignore_file_keeps_what_the_image_copies() -> None:
    """BuildKit reads docker/Dockerfile.dockerignore for docker/Dockerfile: it must not
    exclude anything COPYed, and must keep the virtualenv out of the context."""
    lines = [
        ln.strip()
        for ln in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    assert lines[0] == "**"  # everything out, then the few things in
    allowed = {ln[1:].rstrip("/") for ln in lines if ln.startswith("!")}
    for _, src in _copied():
        assert src in allowed, f"{src} is COPYed but excluded from the build context"
    assert ".venv" not in allowed


# --- the cluster launcher ------------------------------------------------------------------------


def test_cluster_launcher_matches_the_compose_file() -> None:
    cl = _load("cluster.yaml")
    compose = _load("compose.yaml")["services"]
    assert cl["docker"]["image"] == compose["ray-head"]["image"]
    assert cl["min_workers"] == cl["max_workers"] == len(cl["provider"]["worker_ips"])
    # the image holds the installed project: nothing is installed at start-up
    for key in ("setup_commands", "head_setup_commands", "worker_setup_commands"):
        assert not cl.get(key), key
    head = _words(next(c for c in cl["head_start_ray_commands"] if "ray start" in c))
    compose_head = _words(compose["ray-head"]["command"])
    port = next(w for w in compose_head if w.startswith("--port="))
    assert "--head" in head and port in head
    for flag in ("--num-cpus=0", "--include-dashboard=false"):
        assert (flag in head) == (flag in compose_head), flag
    worker = _words(next(c for c in cl["worker_start_ray_commands"] if "ray start" in c))
    assert f"--address=$RAY_HEAD_IP:{port.split('=')[1]}" in worker
    volumes = " ".join(cl["docker"].get("run_options", []))
    assert ":/data" in volumes  # the database directory, as in the compose file


@pytest.mark.parametrize("name", ["compose.yaml", "cluster.yaml"])
def test_yaml_files_parse_without_tabs_or_duplicates(name: str) -> None:
    """pyyaml silently keeps the last of two equal keys; a duplicated service or command
    would be lost without a word."""

    class Strict(yaml.SafeLoader):
        pass

    def no_duplicates(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict:
        keys = [k.value for k, _ in node.value if k.tag != "tag:yaml.org,2002:merge"]
        dup = {k for k in keys if keys.count(k) > 1}
        assert not dup, f"{name}: duplicate keys {dup}"
        return loader.construct_mapping(node)

    Strict.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, no_duplicates)
    text = (DOCKER / name).read_text()
    assert "\t" not in text
    assert isinstance(yaml.load(text, Loader=Strict), dict)
