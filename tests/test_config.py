"""The config schema, its validation and object lookup, in-process (Hydra's compose API).

The command-line side (one error line, exit code, nothing written) is in test_cli.py.
"""

from __future__ import annotations

import ast
import dataclasses
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException

from comexp.experiment import config as config_module
from comexp.experiment.config import (
    ConfigError,
    prepare_job,
    to_experiment,
)
from comexp.experiment.job import probe_resources
from comexp.method.estimator import EstimatorSettings
from comexp.workers import session

TRIANGLE = """\
name: my_tri
outline_cm: [[0, 0], [9, 0], [0, 6]]
height_cm: 2.0
"""


def _compose(*overrides: str):
    with initialize_config_module("comexp.conf", version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


def test_defaults_follow_the_public_contract() -> None:
    exp = to_experiment(_compose())
    assert exp.backend.name == "pybullet"
    assert (exp.floor.name, exp.floor.mu, exp.floor.orientations) == ("iso", [0.1, 1.0], None)
    assert exp.speed == 40.0 and exp.pusher.mu == [0.1, 1.0]
    assert exp.grid.objects is None and exp.grid.coms_per_object == 10
    assert exp.grid.izz_scales == [1.0, 10.0]
    assert exp.workers is None and exp.ray.address is None
    assert exp.db == "results/comexp.db" and exp.seed == 0
    est = exp.estimator
    assert (list(est.w), est.theta_T, est.C_bw, est.n_push, est.rotation_source) == (
        [1.0, 0.5],
        1.0,
        10.0,
        5,
        "vision",
    )


def test_aniso_group_runs_both_orientations_by_default() -> None:
    exp = to_experiment(_compose("floor=aniso"))
    assert (exp.floor.name, exp.floor.mu, exp.floor.orientations) == (
        "aniso",
        [0.1, 1.0],
        ["xy", "yx"],
    )


def test_every_estimator_setting_is_configurable() -> None:
    job = prepare_job(_compose())
    assert job.estimator == EstimatorSettings()  # defaults agree field by field
    job = prepare_job(
        _compose(
            "estimator.theta_T=2.5", "estimator.C_bw=4", "estimator.w=[1,0]", "estimator.n_push=3"
        )
    )
    assert (job.estimator.theta_T_deg, job.estimator.C_bw_px) == (2.5, 4.0)
    assert job.estimator.w == (1.0, 0.0) and job.estimator.n_push == 3
    cfg = _compose()
    names = set(cfg.estimator)
    assert len(names) == len(dataclasses.fields(EstimatorSettings))


def test_estimator_method_is_a_knob() -> None:
    assert prepare_job(_compose()).estimator.method == "paper"
    job = prepare_job(
        _compose(
            "estimator.method=magnitude", "estimator.mag_noise=0.5", "estimator.mag_rel_noise=0"
        )
    )
    assert (job.estimator.method, job.estimator.mag_noise_deg) == ("magnitude", 0.5)
    assert job.estimator.mag_rel_noise == 0.0


def test_wrong_types_are_rejected_while_composing() -> None:
    for bad in ("speed=abc", "grid.coms_per_object=1.5", "nope=1"):
        with pytest.raises(ConfigCompositionException):
            _compose(bad)


@pytest.mark.parametrize("bad", ["two", "0", "-1", "1.5"])
def test_workers_is_a_count_or_auto(bad: str) -> None:
    """`workers` takes a count, `auto` or null (so it is typed loosely): validation refuses the
    rest in one line."""
    with pytest.raises(ConfigError, match="workers must be a count >= 1 or auto"):
        prepare_job(_compose(f"workers={bad}"))
    assert prepare_job(_compose("workers=auto")).cfg.workers == "auto"
    assert prepare_job(_compose("workers=3")).cfg.workers == 3


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        (["speed=-4"], "speed"),
        (["speed=0"], "speed"),
        (["floor.mu=[-1]"], "floor.mu"),
        (["floor.mu=[]"], "floor.mu"),
        (["pusher.mu=[-0.5]"], "pusher.mu"),
        (["pusher.mu=[1,1]"], "pusher.mu"),
        (["grid.coms_per_object=0"], "grid.coms_per_object"),
        (["grid.izz_scales=[0]"], "grid.izz_scales"),
        (["grid.objects=[no_such_object]"], "no_such_object"),
        (["grid.objects=[]"], "grid.objects"),
        (["episode.push_length_cm=0"], "episode.push_length_cm"),
        (["episode.recenter_beyond_cm=-1"], "episode.recenter_beyond_cm"),
        (["estimator.theta_T=-1"], "estimator.theta_T"),
        (["estimator.C_bw=-1"], "estimator.C_bw"),
        # the config once accepted 0 and the estimator refused it: one rule now, one message
        (["estimator.C_bw=0"], "estimator.C_bw must be finite and > 0, got 0.0"),
        (["estimator.theta_T=nan"], "estimator.theta_T must be finite"),
        (["estimator.n_push=0"], "estimator.n_push"),
        (["estimator.w=[1]"], "estimator.w"),
        (["estimator.rotation_source=magic"], "estimator.rotation_source"),
        (["estimator.method=bayes"], "estimator.method"),
        (["estimator.mag_noise=0"], "estimator.mag_noise"),
        (["estimator.mag_rel_noise=-1"], "estimator.mag_rel_noise"),
        (["floor=aniso", "floor.mu=[1]"], "floor.mu"),
        (["floor=aniso", "floor.orientations=[zz]"], "floor.orientations"),
        (["floor.orientations=[xy]"], "floor.orientations"),
        (["workers=0"], "workers"),
        (["seed=-1"], "seed"),
    ],
)
def test_bad_values_are_rejected_with_one_line(overrides: list[str], needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        prepare_job(_compose(*overrides))
    msg = str(info.value)
    assert needle in msg and "\n" not in msg


def test_objects_come_from_every_config_source(tmp_path: Path) -> None:
    (tmp_path / "object").mkdir()
    (tmp_path / "object" / "my_tri.yaml").write_text(TRIANGLE)
    sp = f"hydra.searchpath=[file://{tmp_path}]"
    job = prepare_job(_compose(sp, "grid.objects=[my_tri,l_shape]"))
    assert list(job.objects) == ["my_tri", "l_shape"]
    tri = job.objects["my_tri"]
    assert abs(sum(x for x, _ in tri.outline_cm)) < 1e-9  # re-centred on its centroid
    everything = prepare_job(_compose(sp)).objects
    assert "my_tri" in everything and "l_shape" in everything
    assert len(everything) == len(prepare_job(_compose()).objects) + 1


def test_broken_user_objects_are_one_line_errors(tmp_path: Path) -> None:
    (tmp_path / "object").mkdir()
    (tmp_path / "object" / "renamed.yaml").write_text(TRIANGLE)
    (tmp_path / "object" / "flat.yaml").write_text("outline_cm: [[0, 0], [1, 0], [2, 0]]\n")
    sp = f"hydra.searchpath=[file://{tmp_path}]"
    for name in ("renamed", "flat"):
        with pytest.raises(ConfigError, match=name) as info:
            prepare_job(_compose(sp, f"grid.objects=[{name}]"))
        assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("text", "where", "problem"),
    [
        ("outline_cm: [[0, 0], [9, 0]\nheight_cm: 2\n", "line 2, column 1", "expected ','"),
        (TRIANGLE + "height_cm: 3\n", "line 4, column 1", "found duplicate key height_cm"),
        ("outline_cm: [[0, 0],\t[9, 0], [0, 6]]\n", "line 1, column 21", "found character '\\t'"),
    ],
)
def test_malformed_object_yaml_names_file_and_position(
    tmp_path: Path, text: str, where: str, problem: str
) -> None:
    (tmp_path / "object").mkdir()
    (tmp_path / "object" / "bad.yaml").write_text(text)
    sp = f"hydra.searchpath=[file://{tmp_path}]"
    with pytest.raises(ConfigError) as info:
        prepare_job(_compose(sp, "grid.objects=[bad]"))
    msg = str(info.value)
    assert msg.startswith(f"object 'bad': malformed YAML in {tmp_path}/object/bad.yaml, {where}: ")
    assert problem in msg and "\n" not in msg


def test_shipped_experiment_reproduces_the_papers_aniso_setting() -> None:
    exp = to_experiment(_compose("+experiment=paper_aniso", "speed=4"))
    assert (exp.floor.name, exp.floor.mu, exp.floor.orientations) == (
        "aniso",
        [0.1, 1.0],
        ["xy", "yx"],
    )
    assert exp.pusher.mu == [0.5] and exp.speed == 4.0


# --- ray.address --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("address", "expected"),
    [("ray-head:6379", ("ray-head", 6379)), ("[::1]:6379", ("::1", 6379))],
)
def test_ray_address_parses(address: str, expected: tuple[str, int]) -> None:
    assert session.parse_ray_address(address) == expected


@pytest.mark.parametrize(
    "address", ["ray-head", "ray-head:", ":6379", "ray-head:0", "ray-head:99999", "ray://h:1"]
)
def test_bad_ray_addresses_are_config_errors(address: str) -> None:
    with pytest.raises(ValueError):
        session.check_ray_address(address)
    job = prepare_job(_compose(f"ray.address='{address}'"))  # validation probes nothing
    with pytest.raises(ConfigError, match=r"^ray\.address: "):
        probe_resources(job.cfg)


def test_a_database_location_that_cannot_be_is_a_config_error() -> None:
    job = prepare_job(_compose("db=/proc/no/such.db"))
    with pytest.raises(ConfigError, match=r"^db: ") as info:
        probe_resources(job.cfg)
    assert "\n" not in str(info.value)


def test_validation_is_pure() -> None:
    """Validating a job imports neither the results store nor the workers (a wrong-way
    import), so it probes neither the database nor Ray: the command does, once."""
    code = (
        "import sys\n"
        "from hydra import compose, initialize_config_module\n"
        "from comexp.experiment.config import prepare_job\n"
        "with initialize_config_module('comexp.conf', version_base='1.3'):\n"
        "    cfg = compose('config', overrides=['db=/proc/x.db'], return_hydra_config=True)\n"
        "prepare_job(cfg)\n"
        "print(sorted(m for m in sys.modules if m.startswith(('comexp.', 'ray', 'sqlalchemy'))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    loaded = ast.literal_eval(out.stdout.strip().splitlines()[-1])
    assert loaded, "the check sees the modules"
    # the workers' settings are plain dataclasses the config composes (no Ray)
    workers = ("comexp.workers.pool", "comexp.workers.session", "comexp.workers.actor")
    wrong = [m for m in loaded if m.startswith(("comexp.results", *workers, "ray"))]
    assert wrong == [], wrong
    assert not [m for m in loaded if m.startswith("sqlalchemy")]


def test_an_unanswered_ray_address_fails_within_the_timeout(monkeypatch) -> None:
    """A head whose packets are dropped: the probe's own timeout, one line naming the
    address (`create_connection` raises TimeoutError after `timeout`)."""
    seen = {}

    def dropped(addr, timeout):
        seen.update(addr=addr, timeout=timeout)
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", dropped)
    with pytest.raises(ValueError, match=r"no answer from 10\.1\.2\.3:6379 within 5 s"):
        session.check_ray_address("10.1.2.3:6379")
    assert seen == {"addr": ("10.1.2.3", 6379), "timeout": session.RAY_CONNECT_TIMEOUT_S}


def test_null_and_auto_need_no_probe(monkeypatch) -> None:
    monkeypatch.setattr(socket, "create_connection", lambda *a, **k: pytest.fail("probed"))
    session.check_ray_address(None)
    session.check_ray_address("auto")


def test_every_estimator_setting_is_a_knob_with_the_settings_default() -> None:
    """The `estimator` node is made from `EstimatorSettings`: a knob per field, named as the
    paper names it where the field says so, its default the field's."""
    import dataclasses

    from comexp.experiment.config import EstimatorConfig
    from comexp.method.estimator import EstimatorSettings

    knobs = [f.name for f in dataclasses.fields(EstimatorConfig)]
    fields = dataclasses.fields(EstimatorSettings)
    assert knobs == [f.metadata.get("knob", f.name) for f in fields]
    assert {"theta_T", "C_bw", "w", "n_push", "method"} <= set(knobs)
    assert config_module.estimator_settings(EstimatorConfig()) == EstimatorSettings()


def test_the_user_facing_config_carries_no_test_hooks() -> None:
    """The tests' fakes come in as a user's own would (a backend in a config directory, a
    runner handed to the pool in Python), not through `execution.*`."""
    exp = to_experiment(_compose())
    assert not {"runner", "simulator_factory"} & set(vars(exp.execution))


# --- documented defaults are the config's ---------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _config_value(cfg, key: str):
    """A key's default: the group's choice for a config group, else the composed value."""
    from omegaconf import OmegaConf

    choices = cfg.hydra.runtime.choices
    if key in choices:
        return choices[key]
    node = OmegaConf.select(cfg, key, throw_on_missing=True)
    return OmegaConf.to_container(node) if OmegaConf.is_config(node) else node


def _flat_keys(node, prefix: str = "") -> list[str]:
    """Every leaf key of a config as `--cfg job` prints it (mappings opened, lists kept)."""
    out = []
    for k, v in node.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out += _flat_keys(v, f"{key}.")
        else:
            out.append(key)
    return out


def _knobs_block() -> str:
    """The generated `knobs` block of docs/operations.md."""
    text = (ROOT / "docs" / "operations.md").read_text()
    start, end = "<!-- generated: knobs -->\n", "<!-- end generated -->"
    assert start in text, "docs/operations.md has no generated knob table"
    return text.split(start, 1)[1].split(end, 1)[0]


def test_every_key_comexp_prints_is_documented_with_its_default() -> None:
    """Every key `comexp --cfg job` prints has its row in docs/operations.md's knob table, with
    its default and a meaning, and the table is the one the structured config makes now
    (`python bench/docs_tables.py knobs` after adding or changing a key)."""
    import json
    import subprocess
    import sys

    import yaml

    from comexp.experiment.config import config_keys

    script = Path(sys.executable).with_name("comexp")
    out = subprocess.run([str(script), "--cfg", "job"], capture_output=True, text=True, check=True)
    printed = _flat_keys(yaml.safe_load(out.stdout))
    rows = {}
    for line in _knobs_block().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        if len(cells) == 3 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = cells
    missing = [k for k in printed if k not in rows]
    assert not missing, f"keys `comexp --cfg job` prints that the docs do not describe: {missing}"
    cfg = _compose()
    for key in printed:
        _, default, meaning = rows[key]
        assert meaning, f"{key}: no meaning in the knob table"
        if default != "`(the option's)`":  # backend.*, floor.*: the chosen option's
            assert json.loads(default.strip("`")) == _config_value(cfg, key), key
    assert sorted(rows) == sorted(k.key for k in config_keys()), "rerun bench/docs_tables.py"


def test_defaults_quoted_in_the_docs_are_the_configs() -> None:
    """ "`key=value` (the default)" / "default `key=value`" anywhere in README and docs/."""
    import re

    import yaml

    cfg = _compose()
    wrong = []
    forms = (r"`([\w.]+)=([^`]+)` \(the default\)", r"default `([\w.]+)=([^`]+)`")
    for doc in DOC_FILES:
        for form in forms:
            for m in re.finditer(form, doc.read_text()):
                value = _config_value(cfg, m.group(1))
                if yaml.safe_load(m.group(2)) != value:
                    wrong.append(f"{doc.name}: {m.group(1)} documented {m.group(2)!r}, {value!r}")
    assert not wrong, "\n".join(wrong)


def test_defaults_are_written_once() -> None:
    """conf/config.yaml restates no value of the schema (it holds the group choices and
    Hydra's settings); the report labels and the grid take theirs from the config classes."""
    import yaml

    from comexp.episode.task import CameraSettings, EpisodeSettings
    from comexp.results.reports import PROTOCOL_DEFAULTS

    primary = yaml.safe_load((ROOT / "conf" / "config.yaml").read_text())
    assert set(primary) == {"defaults", "hydra"}, set(primary) - {"defaults", "hydra"}
    assert {
        "mass_kg": EpisodeSettings.mass_kg,
        "push_length_cm": EpisodeSettings.push_length_cm,
        "recenter_beyond_cm": EpisodeSettings.recenter_beyond_cm,
        "camera_fps": CameraSettings.fps,
    } == PROTOCOL_DEFAULTS
