"""The tests' backend, plugged in as a researcher's own is (tests/conf/backend/scripted.yaml):
the planar model, whose episodes run through the real episode loop, with faults and delays
scripted by object name for the command-line, fault and cluster tests.

Its options (the backend config's `options`, e.g. `+backend.options.build_sleep_s=0.4`):
`faults` turns `FAULTS` on: what an object's episodes do, a physics failure the protocol
reports (the state or the engine says so once the first push starts), a hang (build sleeps
until the time limit interrupts it) or a worker that dies (build ends the process);
`build_sleep_s` slows every build down (a job long enough to interrupt or to strike at).
"""

from __future__ import annotations

import dataclasses
import os
import time

from comexp.backends.planar_sim import PlanarSimulator
from comexp.sim.scene import ObjectState, PushStatus, SceneSpec

PHYSICS_VERSION = "scripted-1"
PHYSICS_SETTINGS = {"model": "planar, faults scripted by object"}

FAULTS: dict[str, str] = {
    "t_shape": "tipped",
    "u_shape": "left_view",
    "cross_12": "not_settled",
    "z_shape": "sim_unstable",
    "arrow": "hang",  # -> timeout
    "l_shape": "die",  # -> worker_died
}


class ScriptedPlanar(PlanarSimulator):
    name = "scripted"

    def __init__(self, settings=None, faults: bool = False, build_sleep_s: float = 0.0) -> None:
        super().__init__(settings)
        self.faults = faults
        self.build_sleep_s = float(build_sleep_s)

    def build(self, scene: SceneSpec) -> None:
        self._fault = FAULTS.get(scene.obj.name) if self.faults else None
        self._pushing = False
        if self.build_sleep_s:
            time.sleep(self.build_sleep_s)
        if self._fault == "hang":
            time.sleep(3600)
        if self._fault == "die":
            os._exit(1)
        super().build(scene)

    def place_pusher(self, xy) -> None:
        super().place_pusher(xy)
        self._pushing = True  # the first push has started

    def object_state(self) -> ObjectState:
        state = super().object_state()
        if not self._pushing:
            return state
        if self._fault == "tipped":
            return dataclasses.replace(state, roll_rad=0.6)
        if self._fault == "left_view":
            return dataclasses.replace(state, position_m=(5.0, 5.0, state.position_m[2]))
        if self._fault == "not_settled":
            return dataclasses.replace(state, linear_velocity_m_s=(1.0, 0.0, 0.0))
        return state

    def steps_still(self, targets) -> int:
        return 0 if self._fault else super().steps_still(targets)  # a scripted state: no skips

    def engine_failure(self) -> PushStatus | None:
        return PushStatus.SIM_UNSTABLE if self._pushing and self._fault == "sim_unstable" else None
