"""Linux-only parts are stated (conf/backend/mujoco.yaml's `linux_only`) and refused, elsewhere,
in one clear line; the episode time limit falls back to its watchdog where there is no SIGALRM."""

from __future__ import annotations

import signal
import sys

import pytest
from hydra import compose, initialize_config_module

from comexp.experiment import config as config_module
from comexp.experiment.config import ConfigError, load_backend, prepare_job
from comexp.workers.actor import has_sigalrm


def _job(backend: str):
    with initialize_config_module("comexp.conf", version_base="1.3"):
        cfg = compose("config", [f"backend={backend}", "grid.objects=[l_shape]"], True)
    return prepare_job(cfg)


@pytest.mark.parametrize("platform", ["darwin", "win32", "freebsd14"])
def test_mujoco_is_refused_off_linux_in_one_line(platform: str, monkeypatch) -> None:
    monkeypatch.setattr(config_module.sys, "platform", platform)
    with pytest.raises(ConfigError) as err:
        _job("mujoco")
    msg = str(err.value)
    assert msg.startswith("backend=mujoco runs on Linux only (headless EGL rendering")
    assert f"this is {platform}: use backend=planar or backend=pybullet" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("backend", ["planar", "pybullet", "mujoco"])
def test_every_backend_runs_on_linux(backend: str, monkeypatch) -> None:
    _job(backend)  # this machine (the suite runs on Linux)
    if load_backend(backend).linux_only is None:
        for platform in ("darwin", "win32"):
            monkeypatch.setattr(config_module.sys, "platform", platform)
            _job(backend)


def test_without_sigalrm_the_time_limit_keeps_its_watchdog(monkeypatch, capfd) -> None:
    from test_faults import FAKE, _specs, hanging_run

    from comexp.workers.actor import EpisodeWorker

    assert has_sigalrm() == (sys.platform != "win32")
    monkeypatch.delattr(signal, "SIGALRM")
    assert not has_sigalrm()
    w = EpisodeWorker(FAKE, runner=hanging_run, episode_timeout_s=5.0)
    assert "no SIGALRM on" in capfd.readouterr().err
    assert w.run_one(_specs("box")[0]).status == "ok"  # no signal.SIGALRM needed to run
    w.close()
