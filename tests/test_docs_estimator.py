"""docs/your_estimator.md as written: its module and its YAML, written where the page says, and
its command line run through `comexp`'s console script with PYTHONPATH set as the page sets it,
on a tiny planar grid. Every episode is stored `ok`, made by the plug-in (its method in the
episode's estimator settings, its labels in `pushes.decision`)."""

from __future__ import annotations

import json
import os
import re
import shlex
import sqlite3
import subprocess
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "your_estimator.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", PAGE.read_text(), flags=re.S)


def _page() -> tuple[str, str, list[str]]:
    """The page's module, its YAML and its command line (as words)."""
    (module,) = [b for b in _blocks("python") if "class MyEstimator" in b]
    (config,) = [b for b in _blocks("yaml") if "method:" in b]
    (line,) = [ln for b in _blocks("sh") for ln in b.splitlines() if "comexp --config-dir" in ln]
    return module, config, shlex.split(line.split("#", 1)[0])


def _comexp() -> list[str]:
    script = Path(sys.executable).with_name("comexp")
    return [str(script)] if script.exists() else [sys.executable, "-m", "comexp.cli.run"]


def test_the_page_names_its_files_and_its_command() -> None:
    module, config, words = _page()
    text = PAGE.read_text()
    assert "`my_estimators.py`" in text and "`conf/estimator/mine.yaml`" in text
    assert "method: my_estimators:MyEstimator" in config
    assert words[0] == "PYTHONPATH=$PWD" and words[1] == "comexp"
    assert "--config-dir" in words and "estimator=mine" in words
    assert "backend=planar" in words


def test_the_plugin_of_the_page_runs_as_written(tmp_path: Path) -> None:
    module, config, words = _page()
    (tmp_path / "my_estimators.py").write_text(module)
    (tmp_path / "conf" / "estimator").mkdir(parents=True)
    (tmp_path / "conf" / "estimator" / "mine.yaml").write_text(config)
    env_words = [w for w in words if re.match(r"^[A-Z_]+=", w)]
    args = words[len(env_words) + 1 :]  # after `comexp`
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("HYDRA_FULL_ERROR", "RAY_ADDRESS", "PYTHONPATH")
        and not k.startswith("RAY_AUTH")
    }
    env["RAY_USAGE_STATS_ENABLED"] = "0"
    for w in env_words:  # PYTHONPATH=$PWD, as the page sets it, in the page's directory
        key, _, value = w.partition("=")
        env[key] = value.replace("$PWD", str(tmp_path))
    r = subprocess.run(
        [*_comexp(), *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "method=my_estimators:MyEstimator" in r.stdout
    db = tmp_path / next(a for a in args if a.startswith("db=")).removeprefix("db=")
    with sqlite3.connect(db) as c:
        episodes = c.execute("select status, failure, estimator, n_pushes from episodes").fetchall()
        decisions = {d for (d,) in c.execute("select decision from pushes")}
    assert len(episodes) == 8  # 1 object x 1 CoM x 2 Izz x 2 floor x 2 pusher frictions
    for status, failure, estimator, n_pushes in episodes:
        assert (status, failure) == ("ok", None)
        assert json.loads(estimator)["method"] == "my_estimators:MyEstimator"
        assert n_pushes >= 1
    assert decisions and decisions <= {"ccw", "cw", "small"}
