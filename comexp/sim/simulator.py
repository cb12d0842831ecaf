"""The engine interface: what a backend implements so that the push protocol can drive it.

A backend builds a scene from engine-independent dataclasses (`comexp.sim.scene`), renders the
top-down depth image, places and drives the pusher, advances its physics and reads the
object's true state. That is all: the push itself (start clear, drive along the normal,
settle, retract, classify failures, take tracking frames) is the protocol's, written once in
`comexp.sim.protocol` on these primitives, so that a cross-engine comparison compares physics,
not protocols (as dm_control keeps its Physics apart from its Task). What an engine may do
besides, to make the protocol cheaper, are the protocol's optional capabilities
(`comexp.sim.protocol.SkipsStillSteps`, `JumpsStillSteps`, `RunsChunks`); without them the
protocol takes its plain path.

The true object state is for evaluation, tests and failure detection only; the estimator
never reads it unless `rotation_source=oracle` is asked for.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from comexp.method.frames import CameraModel, DepthImage, Pose2D
from comexp.method.rendering import render_prism_depth, render_prism_window_depth
from comexp.sim.scene import ObjectState, PushStatus, SceneSpec, SimSettings

# Pusher parking spot (world, m): beyond the floor edge and outside the camera's view at the
# pusher's top, unreachable by an object still in view.
PARK_XY_M = (0.0, 0.5)


class Simulator(ABC):
    """One engine instance, driven by the push protocol (`comexp.sim.protocol.push`).

    `build` may be called many times (scene reuse is the backend's job). An engine implements
    the abstract primitives; the others have working defaults it may override.
    """

    name: str = ""
    # steps advanced between two of the protocol's failure / rest checks: 10 ms for every
    # built-in backend; part of the protocol's settings
    check_every_steps: int = 10

    def __init__(self, settings: SimSettings | None = None) -> None:
        self.settings = settings or SimSettings()
        # when a list, every step's ObjectState is appended to it (physics tests: lift, tilt)
        self.trace: list[ObjectState] | None = None
        self._scene: SceneSpec | None = None
        self._views_of_scene: tuple[SceneSpec, CameraModel, np.ndarray] | None = None

    # --- what an engine implements --------------------------------------------------------
    @abstractmethod
    def build(self, scene: SceneSpec) -> None:
        """(Re)create floor, object at `scene.initial_pose` resting on the floor, the pusher
        parked out of the camera's view, and the camera; keep `scene` as `self._scene`."""

    @abstractmethod
    def render_depth(self) -> DepthImage:
        """Top-down metric depth image of the current scene (pusher parked, out of view)."""

    @abstractmethod
    def object_state(self) -> ObjectState:
        """True state of the object frame: evaluation and tests only."""

    @abstractmethod
    def place_pusher(self, xy: np.ndarray | Sequence[float]) -> None:
        """Put the pusher at rest at a world point (only called where it is clear of the
        object: the start of a push, the parking spot)."""

    @abstractmethod
    def pusher_xy(self) -> np.ndarray:
        """The pusher axis' actual world position."""

    @abstractmethod
    def advance(self, targets: np.ndarray) -> tuple[bool, float]:
        """Run len(targets) steps; the pusher reaches targets[i] (world, m) at the end of
        step i, moving straight between them. Returns (pusher touched the object during these
        steps, max tilt in deg over them). Appends every step's state to `trace` if set (planar:
        every step of its model, which takes one for several where the motion is slow)."""

    @abstractmethod
    def set_object_velocity(
        self, linear_m_s: tuple[float, float, float], angular_rad_s: tuple[float, float, float]
    ) -> None:
        """Overwrite the object's velocity (world frame; linear = the object frame origin's):
        physics validation only, never the estimator."""

    # --- defaults an engine may override --------------------------------------------------
    def render_tracking_depth(self) -> DepthImage:
        """The depth image of a tracking frame taken during a push. An engine may render only
        the window of the image the object can cover (`comexp.sim.view.object_window_px`),
        returned with the camera model of that window (`CameraModel.crop`), so that its pixels
        map to the same world points as the full image's."""
        return self.render_depth()

    def engine_failure(self) -> PushStatus | None:
        """An engine's own sign of trouble (e.g. solver warnings), checked after every
        chunk; None when healthy."""
        return None

    def park_xy(self) -> tuple[float, float]:
        return PARK_XY_M

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release engine resources."""

    # --- what the protocol reads of the built scene ---------------------------------------
    @property
    def scene(self) -> SceneSpec:
        """The scene last built; RuntimeError before the first `build`."""
        if self._scene is None:
            raise RuntimeError("build() a scene first")
        return self._scene

    def scene_views(self) -> tuple[CameraModel, np.ndarray]:
        """The built scene's camera model and outline array, made once per scene: every
        push and every tracking frame asks for them (callers must not write the outline)."""
        scene = self.scene
        views = self._views_of_scene
        if views is None or views[0] is not scene:
            outline = np.asarray(scene.obj.outline_m, dtype=float)
            views = self._views_of_scene = (scene, scene.camera.model(), outline)
        return views[1], views[2]

    def camera_model(self) -> CameraModel:
        return self.scene_views()[0]

    def outline_m(self) -> np.ndarray:
        return self.scene_views()[1]

    def pusher_radius_m(self) -> float:
        return self.scene.pusher.radius_m

    def true_pose(self) -> Pose2D:
        return self.object_state().pose

    def step(self, duration_s: float) -> None:
        """Advance the simulation by `duration_s` (rounded to whole steps), pusher held still:
        physics validation only."""
        self.scene  # noqa: B018 - built first, or RuntimeError
        n = max(0, round(duration_s / self.settings.timestep_s))
        if n:
            self.advance(np.repeat(self.pusher_xy()[None, :], n, axis=0))

    # --- the exact ray-cast camera, for engines that offer `camera.renderer=raycast` -------
    def raycast_depth(self) -> DepthImage:
        """The exact ray-cast depth image of the prism at the true pose: an engine's
        alternative to its own renderer, the same pixels as planar's."""
        scene = self.scene
        return render_prism_depth(
            self.camera_model(), self.outline_m(), scene.obj.height_m, self.object_state().pose
        )

    def raycast_tracking_depth(self) -> DepthImage:
        """`raycast_depth`'s pixels of the window the prism can cover only, with that
        window's camera model (`render_prism_window_depth`): a tracking frame's image."""
        scene = self.scene
        return render_prism_window_depth(
            self.camera_model(), self.outline_m(), scene.obj.height_m, self.object_state().pose
        )

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class SimulatorSpec:
    """Which simulator a worker builds: the backend's name (as the database stores it), its
    class (`target`, `module.Class`: the `_target_` of its `backend` config group option)
    and its constructor options (e.g. `floor_friction`, `renderer`). Plain data: it travels
    to the workers, which import the class (`make`)."""

    name: str
    target: str
    options: Mapping[str, str] = field(default_factory=dict)

    def simulator_class(self) -> type[Simulator]:
        """The class `target` names, imported; ValueError (one line naming the backend) when
        it cannot be imported or is not a `Simulator`."""
        cls = self._import()
        if not (isinstance(cls, type) and issubclass(cls, Simulator)):
            raise ValueError(f"backend {self.name!r}: {self.target} is not a Simulator subclass")
        return cls

    def make(self, settings: SimSettings | None = None) -> Simulator:
        """A new simulator of this backend (the class called with `settings` and the
        options)."""
        return self._import()(settings, **self.options)

    def _import(self) -> type:
        module_name, _, cls_name = self.target.rpartition(".")
        if not module_name:
            raise ValueError(
                f"backend {self.name!r}: _target_ must be module.Class, got {self.target!r}"
            )
        try:
            return getattr(importlib.import_module(module_name), cls_name)
        except (ImportError, AttributeError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise ValueError(f"backend {self.name!r}: cannot import {self.target}: {msg}") from None
