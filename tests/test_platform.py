"""Linux-only parts are stated (comexp/experiment/platform.py) and fail, elsewhere, in one
clear line; the episode time limit falls back to its watchdog where there is no SIGALRM."""

from __future__ import annotations

import signal
import sys

import pytest

from comexp.experiment.platform import LINUX_ONLY_BACKENDS, check_backend, has_sigalrm


@pytest.mark.parametrize("platform", ["darwin", "win32", "freebsd14"])
def test_mujoco_is_refused_off_linux_in_one_line(platform: str) -> None:
    with pytest.raises(ValueError) as err:
        check_backend("mujoco", platform)
    msg = str(err.value)
    assert msg.startswith("backend=mujoco runs on Linux only (headless EGL rendering")
    assert f"this is {platform}: use backend=planar or backend=pybullet" in msg
    assert "\n" not in msg


@pytest.mark.parametrize("backend", ["planar", "pybullet", "mujoco"])
def test_every_backend_runs_on_linux(backend: str) -> None:
    check_backend(backend, "linux")
    if backend not in LINUX_ONLY_BACKENDS:
        check_backend(backend, "darwin")
        check_backend(backend, "win32")
    check_backend(backend)  # this machine (the suite runs on Linux)


def test_without_sigalrm_the_time_limit_keeps_its_watchdog(monkeypatch, capfd) -> None:
    from test_faults import FACTORY, _specs

    from comexp.workers.actor import EpisodeWorker

    assert has_sigalrm() == (sys.platform != "win32")
    monkeypatch.delattr(signal, "SIGALRM")
    assert not has_sigalrm()
    w = EpisodeWorker("fake", runner="test_faults:hanging_run", simulator_factory=FACTORY,
                      episode_timeout_s=5.0)  # fmt: skip
    assert "no SIGALRM on" in capfd.readouterr().err
    assert w.run_one(_specs("box")[0]).status == "ok"  # no signal.SIGALRM needed to run
    w.close()
