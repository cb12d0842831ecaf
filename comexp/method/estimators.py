"""Every estimator by its method name (`estimator.method`): the built-in ones, a researcher's
own plug-in class, the protocol they share, and the factory an episode uses (`make_estimator`).

A plug-in plugs in from config without editing the package: `estimator.method=my_pkg.module:
MyEstimator` (or `my_pkg.module.MyEstimator`; in a user config directory, `estimator/NAME.yaml`
holding `method: my_pkg.module:MyEstimator`, chosen with `estimator=NAME`) names a class that
implements the `Estimator` protocol and takes `ComEstimator`'s constructor arguments. Its module
must be importable where episodes run (installed, or on PYTHONPATH, which a local Ray's workers
inherit; on a cluster, on every node): docs/your_estimator.md.
"""

from __future__ import annotations

import importlib
from typing import Any, Protocol, runtime_checkable

import numpy as np

from comexp.method.estimator import METHODS, ComEstimator, EstimatorSettings, is_plugin
from comexp.method.fit_estimator import FitEstimator
from comexp.method.motion_estimator import KnownNuisances, MotionEstimator

# the built-in methods' classes: paper and magnitude are Algorithms 1 and 2 (magnitude also fits
# how much each push turns), motion reads the tracked path of each push, fit also reads the
# slow pushes' paths with a quasi-static forward model
BUILT_IN: dict[str, type] = {
    "paper": ComEstimator,
    "magnitude": ComEstimator,
    "motion": MotionEstimator,
    "fit": FitEstimator,
}
assert set(BUILT_IN) == set(METHODS)


@runtime_checkable
class Estimator(Protocol):
    """What an episode needs of an estimator (`ComEstimator` is the built-in one). A plug-in
    class is constructed as `Cls(region_m, contacts_m, normals, pixel_m, settings, outline_m=...,
    pusher_radius_m=...)` (`make_estimator`); the frames and units are `ComEstimator`'s."""

    def next_push(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(contact, inward push direction) of the next push, or None to stop."""
        ...

    def observe(
        self,
        contact_m: np.ndarray,
        direction: np.ndarray,
        rotation_deg: float,
        line_direction: np.ndarray | None = None,
    ) -> str:
        """Take the measured rotation of that push; returns a short decision label."""
        ...

    @property
    def estimate_m(self) -> np.ndarray:
        """The current CoM estimate (2,), metres."""
        ...

    @property
    def region_px(self) -> int:
        """The size of the current CoM region (points), recorded per push."""
        ...

    # optional: `region_m`, the region's points (its frame, m), whose hull each push stores
    # (`comexp-db show` draws it); an estimator without it stores no region


_PROTOCOL = ("next_push", "observe", "estimate_m", "region_px")


def resolve_estimator(method: str) -> type:
    """The estimator class `method` names: a built-in's (`BUILT_IN`), else the plug-in
    `module:Class` / `module.Class`, imported; ValueError (one line, starting with `method`)
    when it is neither, cannot be imported or lacks the `Estimator` protocol."""
    if method in BUILT_IN:
        return BUILT_IN[method]
    if not is_plugin(method):
        raise ValueError(
            f"method must be one of {METHODS} or a plug-in 'module:Class', got {method!r}"
        )
    module, sep, name = method.partition(":")
    if not sep:
        module, _, name = method.rpartition(".")
    try:
        cls: Any = importlib.import_module(module)
        for part in name.split("."):
            cls = getattr(cls, part)
    except (ImportError, AttributeError, ValueError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"method {method!r}: cannot import the plug-in: {msg}") from None
    missing = [m for m in _PROTOCOL if not hasattr(cls, m)]
    if not isinstance(cls, type) or missing:
        raise ValueError(
            f"method {method!r}: not an estimator class (missing: {', '.join(missing) or '-'})"
        )
    return cls


def make_estimator(
    region_m: np.ndarray,
    contacts_m: np.ndarray,
    normals: np.ndarray,
    pixel_m: float,
    settings: EstimatorSettings | None = None,
    outline_m: np.ndarray | None = None,
    pusher_radius_m: float | None = None,
    nuisances: KnownNuisances | None = None,
) -> Estimator:
    """The estimator `settings.method` chooses (built-in `ComEstimator` or a plug-in class),
    constructed with `ComEstimator`'s arguments; `nuisances` (`settings.nuisance_source=oracle`,
    which only motion and fit accept) tells it the scene's floor, pusher friction and Izz."""
    settings = settings or EstimatorSettings()
    cls = resolve_estimator(settings.method)
    told = {} if nuisances is None else {"nuisances": nuisances}
    if told and cls not in (MotionEstimator, FitEstimator):
        raise ValueError(f"method {settings.method!r} cannot be told the nuisances")
    return cls(
        region_m,
        contacts_m,
        normals,
        pixel_m,
        settings,
        outline_m=outline_m,
        pusher_radius_m=pusher_radius_m,
        **told,
    )
