"""The backends by name: which exist, their options, how one is made, what fixes its physics.

`make_simulator(name, ...)` imports a backend's module only when it is asked for (the engines
are heavy); `physics_identity(name, ...)` names what determines its results, part of every
episode's identity. The interface every backend implements is `comexp.experiment.interface`'s.
A researcher's own backend plugs in by name as `module:Class` (`backend.name`, e.g. from a user
config directory's `backend/NAME.yaml`): a `Simulator` subclass whose module defines
`PHYSICS_VERSION` and `PHYSICS_SETTINGS` (and `ENGINE_DISTRIBUTION` if an engine computes it),
as the built-in backends' modules do.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from comexp.method.scene import SimSettings

if TYPE_CHECKING:
    from comexp.experiment.interface import Simulator

BACKENDS: dict[str, str] = {
    "planar": "comexp.backends.planar_sim:PlanarSimulator",
    "pybullet": "comexp.backends.pybullet_sim:PybulletSimulator",
    "mujoco": "comexp.backends.mujoco_sim:MujocoSimulator",
}
# The 3-D engines: they take `floor_friction` and a renderer; planar and plug-ins take neither.
ENGINES = ("pybullet", "mujoco")
# How an engine gets the floor's friction: "model" applies the shared footprint model
# (backends/floor_friction.py) as a force each step, the engine's own object-floor friction off;
# "native" is the engine's own contact friction (kept to show the difference).
FLOOR_FRICTION_CHOICES = ("model", "native")
# How an engine makes its depth images (`camera.renderer`): "raycast" is the exact ray cast of
# the prism at the engine's pose (`comexp.method.rendering.render_prism_depth`, planar's
# camera; no pusher in the image, which the tracker masks anyway); "engine" is the engine's own
# renderer (pybullet's tiny renderer, MuJoCo's GL on Mesa).
RENDERER_CHOICES = ("raycast", "engine")


def physics_identity(
    name: str, settings: SimSettings | None = None, options: dict | None = None
) -> str:
    """What determines an episode's physics on backend `name`, as one short string: the
    backend's model revision (`PHYSICS_VERSION` in its module, bumped by any change that
    changes results), the engine's version, and a hash of the backend's settings and of the
    push protocol's. It is part of every episode's identity (`EpisodeSpec.physics`), so a
    database is never resumed across physics versions and no report pools two of them."""
    import hashlib
    from importlib import metadata

    from comexp.backends.physics_settings import BUILTIN_PHYSICS

    if name in BUILTIN_PHYSICS:  # read without importing the engine (the driver's memory)
        version, engine, physics_settings = BUILTIN_PHYSICS[name]
    else:
        module, _ = resolve_backend(name)
        version, physics_settings = module.PHYSICS_VERSION, module.PHYSICS_SETTINGS
        engine = getattr(module, "ENGINE_DISTRIBUTION", None)
    engine_v = metadata.version(engine) if engine else "none"
    # the engine's own renderer is what every row had before `camera.renderer` existed: it is
    # left out, so that those rows keep their identity
    opts = {k: v for k, v in (options or {}).items() if (k, v) != ("renderer", "engine")}
    text = repr((physics_settings, settings or SimSettings(), sorted(opts.items())))
    digest = hashlib.sha256(text.encode()).hexdigest()[:10]
    return f"{name}/{version}/{engine or 'numpy'}-{engine_v}/{digest}"


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def make_simulator(name: str, settings: SimSettings | None = None, **options) -> Simulator:
    """Create a backend by name (`planar`, `pybullet`, `mujoco`, or a plug-in `module:Class`);
    engines are imported lazily.
    `options` are the backend's own (e.g. `floor_friction` for the engines)."""
    _, cls = resolve_backend(name)
    return cls(settings, **options)


def resolve_backend(name: str) -> tuple[Any, type]:
    """The module and the `Simulator` class of backend `name`: a built-in by name, else the
    plug-in `module:Class`, imported. ValueError (one line, naming the backend) when it is
    unknown, cannot be imported, is not a `Simulator` or its module lacks the physics
    identity's names."""
    from comexp.experiment.interface import Simulator

    target = BACKENDS.get(name, name)
    module_name, sep, cls_name = target.partition(":")
    if not sep:
        raise ValueError(
            f"unknown backend {name!r}; choose one of {backend_names()} or a plug-in module:Class"
        )
    try:
        module = importlib.import_module(module_name)
        cls = getattr(module, cls_name)
    except (ImportError, AttributeError, ValueError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"backend {name!r}: cannot import the plug-in: {msg}") from None
    if not (isinstance(cls, type) and issubclass(cls, Simulator)):
        raise ValueError(f"backend {name!r}: not a Simulator subclass")
    missing = [a for a in ("PHYSICS_VERSION", "PHYSICS_SETTINGS") if not hasattr(module, a)]
    if missing:
        raise ValueError(
            f"backend {name!r}: its module must define {', '.join(missing)} (the physics identity)"
        )
    return module, cls
