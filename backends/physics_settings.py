"""What fixes a backend's results: its model revision, the engine that computes it and every
setting that shapes it (the built-in backends' importable without any engine), and the one
identity made of them (`physics_identity`).

The driver names an episode's physics (`physics_identity`, part of every episode's key) from
here, so expanding a grid or resuming a job loads no MuJoCo or pybullet (docs/performance.md,
"Memory"). Each built-in backend's module re-exports its own entry as `PHYSICS_VERSION`,
`ENGINE_DISTRIBUTION` and `PHYSICS_SETTINGS`, the names a plug-in backend's module defines;
`tests/test_physics_identity.py` checks the two agree.

**Bump a backend's version here when a change to its module changes results.** The settings
enter the identity through their `repr`, which names the class, not this module.
"""

from __future__ import annotations

import hashlib
import importlib
from dataclasses import dataclass, fields
from importlib import metadata
from typing import Any, NamedTuple

from comexp.sim.scene import SimSettings

# How an engine gets the floor's friction (`backend.floor_friction`): "model" applies the shared
# footprint model (backends/floor_friction.py) as a force each step, the engine's own
# object-floor friction off; "native" is the engine's own contact friction (kept to show the
# difference). planar is the model itself.
FLOOR_FRICTION_CHOICES = ("model", "native")
# How an engine makes its depth images (`camera.renderer`): "raycast" is the exact ray cast of
# the prism at the engine's pose (`comexp.method.rendering.render_prism_depth`, planar's
# camera; no pusher in the image, which the tracker masks anyway); "engine" is the engine's own
# renderer (pybullet's tiny renderer, MuJoCo's GL on Mesa).
RENDERER_CHOICES = ("raycast", "engine")


class BackendPhysics(NamedTuple):
    version: str  # the model's revision: bump when a change changes results
    engine_distribution: str  # the package that computes it: its version is part of the physics
    settings: Any  # every setting that shapes the physics (hashed by repr)


@dataclass(frozen=True)
class FrictionSettings:
    """Numerical settings of the footprint friction (their convergence is tested)."""

    samples: int = 400  # target number of footprint area samples (grid cells)
    smoothing_m_s: float = 1e-7  # |u| is smoothed below this slip inside the Newton solve only
    newton_tol: float = 1e-13  # Newton decrement (J) at which a step's solve has converged
    max_newton: int = 60
    rest_snap_m_s: float = 1e-6  # a solved velocity this small, and no better than 0, is 0


@dataclass(frozen=True)
class SlowSteps:
    """Where the motion is slow and smooth the model takes one step for several of the
    protocol's: while the pusher moves no faster than `speed_m_s` and the object's fastest
    point (flat on the floor) no faster either, up to `steps` protocol steps are one step of
    their summed length (the protocol's chunk of checks, `Simulator.check_every_steps`, is
    two). Quasi-static pushing is such motion, the turning object's far end included; an
    impact or a fast slide is not. `steps=1` turns it off. The step is implicit in the
    friction and the pusher's contact together, so a 5 ms step moving 0.6 mm stays within
    the model's own accuracy: its cost is in docs/physics.md's convergence table."""

    speed_m_s: float = 0.12
    steps: int = 5


@dataclass(frozen=True)
class StillJumps:
    """The engines' still steps (`Simulator.steps_still`): while the object is at rest by the
    settle rule and the pusher stays farther from its outline than each step is long plus
    `margin_m`, the engine is not stepped: time passes, the object's state is kept, the
    pusher moves on. An engine's resting object never stops exactly; stepped, it creeps at
    the contacts' numerical scale (`bench/episode_profile.py --still-jumps`). 1 mm is beyond
    any contact a step could make (a 40 cm/s pusher moves 0.4 mm a step), and the protocol
    steps the last chunk before the pusher arrives. Only a flat object: tilted more than
    `max_tilt_deg` it may be falling back from a lift while its floor point is still (MuJoCo,
    a 3 cm hexagon after a 40 cm/s push on mu 1: 0.75 deg); resting, the engines' objects
    tilt up to 0.011 deg (pybullet) and 0.0007 deg (MuJoCo) where a jump starts."""

    margin_m: float = 1e-3
    max_tilt_deg: float = 0.1


STILL_JUMPS = StillJumps()


@dataclass(frozen=True)
class MujocoContactSettings:
    """Solver and contact parameters; the defaults are the validated ones.

    `solref`/`solimp` apply to every contact pair (the pusher pair takes `pusher_solref`).
    `multiccd` asks the convex collider for several contact points per mesh pair (MuJoCo >= 3.3
    understands the flag; MuJoCo 4 has it on by default). `pusher_mass_kg` must dwarf the
    object's 0.2 kg: the pusher coasts through a chunk of steps at its commanded velocity, and
    the object's reaction must not slow it (1e6 kg: < 1e-7 m/s per chunk).
    """

    solref: tuple[float, float] = (0.004, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.95, 0.99, 0.0005, 0.5, 2.0)
    solreffriction: tuple[float, float] = (0.01, 1.0)  # (0, 0): friction rows use solref
    impratio: float = 1.0
    noslip_iterations: int = 0
    integrator: str = "implicitfast"
    iterations: int = 50
    tolerance: float = 1e-10
    multiccd: bool = True
    use_box_geoms: bool = True  # rectangles as primitive boxes (exact box-box collider)
    support_spacing_m: float = 0.01  # > 0: floor contact through small spheres (see header)
    # floor_friction=model: the supports carry the weight only (condim 1; the footprint model
    # supplies the friction), so a coarser core does (docs/physics_mujoco.md)
    support_spacing_model_m: float = 0.02
    support_min_points_model: int = 4
    support_min_points: int = 8  # the grid spacing is halved until the core has this many
    support_radius_m: float = 0.001
    rim_lift_m: float = 0.0005  # rim supports sit this high: they touch only when tilted
    build_settle_s: float = 0.1
    substeps: int = 1  # physics steps per SimSettings.timestep_s (pusher command rate)
    pusher_mass_kg: float = 1.0e6
    pusher_geom: str = "capsule"  # "cylinder": MuJoCo's general convex collider (see header)
    # the pusher pair over-damped (damping ratio 2): a plastic impact, as in the model; at
    # critical damping the object left the pusher at impact and the push turned 49.2 or
    # 53.2 deg by float rounding (planar 51.2; the same push at 8 yaws, mu 0.1, 40 cm/s)
    pusher_solref: tuple[float, float] | None = (0.005, 2.0)  # None: `solref`
    cone: str = "elliptic"
    # depth renderers kept (one per object geometry, ~80 MB each): the grid runs each object's
    # episodes together, so a small cache loses nothing (docs/performance.md)
    max_renderers: int = 2

    def __repr__(self) -> str:
        """The dataclass's repr with the retired settings in their places, at the only values
        they ever took in a stored study: the physics identity hashes this text, so that the
        episodes stored before they were retired keep their keys (git keeps the code that
        read them: the support layouts "grid" and "rings", a floor margin, a pusher sleeve, a
        rim grid and a frictionless rim, each measured and not chosen)."""
        parts = []
        for f in fields(self):
            parts.append(f"{f.name}={getattr(self, f.name)!r}")
            parts += [f"{k}={v!r}" for k, v in _RETIRED_AFTER.get(f.name, ())]
        return f"{type(self).__name__}({', '.join(parts)})"


# retired MuJoCo contact settings, after the field they followed, at their only values
_RETIRED_AFTER: dict[str, tuple[tuple[str, Any], ...]] = {
    "support_min_points": (("support_layout", "symmetric"),),
    "rim_lift_m": (("rim_frictionless", False), ("rim_grid", False)),
    "cone": (("floor_margin_m", 0.0), ("ring_min_points", 16), ("pusher_sleeve_kg", 0.0)),
}


DEFAULT_CONTACT = MujocoContactSettings()

# pybullet's pusher (backends/pybullet_sim.py). Its mass (kg): 500x the object's, so contact
# impulses change its velocity by < 0.2 % of the object's change within a step; its velocity is
# re-imposed before every step.
PYBULLET_PUSHER_MASS_KG = 100.0
# The pusher's inertia about its axle per kg (m^2): ~0, so that rolling absorbs any vertical slip
# at its contact within the step's solve (a valid tensor: a thin rod's).
PYBULLET_PUSHER_AXLE_INERTIA_M2 = 1e-10
PYBULLET_SOLVER_ITERATIONS = 50


PLANAR = BackendPhysics(
    # 2: compiled steps; 3: the solver's start and line search (results moved within the
    # solver's tolerance); 4: the pitch about a support edge (a push reports tipped by the tilt
    # rule, as on the engines, not at the pitch's onset); 5: slow steps; 6: the footprint's
    # sample loops as SIMD loops (their sums reassociated: last-bit differences); 7: slow
    # steps up to 12 cm/s, was 5 (a quasi-static push turns its object's far end faster);
    # 8: the footprint friction's 3x3 solves in scalars and its line search's trials with their
    # gradients (last-bit differences); 9: a sustained push's solve on the contact plane
    # first, the free solve only when the plane's frictionless multiplier does not rule it out
    # (the same choices; last-bit differences)
    "planar-9",
    "numba",  # the kernels are compiled by it
    (FrictionSettings(), SlowSteps()),
)
PYBULLET = BackendPhysics(
    # 2: shared push protocol; 3: compiled friction; 4: roller pusher; 5: the footprint
    # friction's line search (results moved within the solver's tolerance); 6: the footprint's
    # sample loops as SIMD loops (last-bit differences); 7: still steps jumped (`StillJumps`);
    # 8: the protocol checks every 10 steps, as on MuJoCo and planar (was 5); 9: the footprint
    # friction's 3x3 solves in scalars and its line search's trials with their gradients
    # (last-bit differences)
    "pybullet-9",
    "pybullet",
    {
        "pusher_mass_kg": PYBULLET_PUSHER_MASS_KG,
        "pusher_axle_inertia_m2": PYBULLET_PUSHER_AXLE_INERTIA_M2,
        "solver_iterations": PYBULLET_SOLVER_ITERATIONS,
        "footprint": FrictionSettings(),
        "still_jumps": STILL_JUMPS,
    },
)
MUJOCO = BackendPhysics(
    # 2: the shared push protocol; 3: compiled footprint friction; 4: the step loop compiled
    # (its 3x3 products in scalars, not BLAS: last-bit differences); 5: the footprint
    # friction's line search (results moved within the solver's tolerance); 6: the footprint's
    # sample loops as SIMD loops (last-bit differences); 7: still steps jumped (`StillJumps`);
    # 8: the footprint friction's 3x3 solves in scalars and its line search's trials with their
    # gradients (last-bit differences); 9: under the model, floor supports 2 cm apart, halved
    # down to 4 core points (were 1 cm, 8 points)
    "mujoco-9",
    "mujoco",
    (DEFAULT_CONTACT, FrictionSettings(), STILL_JUMPS),
)
# the built-in backends' modules (their `_target_`s' modules in conf/backend/*.yaml)
BUILTIN_PHYSICS: dict[str, BackendPhysics] = {
    "comexp.backends.planar_sim": PLANAR,
    "comexp.backends.pybullet_sim": PYBULLET,
    "comexp.backends.mujoco_sim": MUJOCO,
}


def backend_physics(target: str) -> BackendPhysics:
    """The physics of the backend whose simulator class is `target` (`module.Class`): a
    built-in's from the table above, without importing its engine; a plug-in's from the
    names its module defines. ValueError (one line) when the module lacks them."""
    module_name = target.rpartition(".")[0]
    if module_name in BUILTIN_PHYSICS:
        return BUILTIN_PHYSICS[module_name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"cannot import {module_name!r}: {str(e).splitlines()[0]}") from None
    missing = [a for a in ("PHYSICS_VERSION", "PHYSICS_SETTINGS") if not hasattr(module, a)]
    if missing:
        raise ValueError(
            f"module {module_name!r} must define {', '.join(missing)} (the physics identity)"
        )
    engine = getattr(module, "ENGINE_DISTRIBUTION", None)
    return BackendPhysics(module.PHYSICS_VERSION, engine, module.PHYSICS_SETTINGS)


def physics_identity(
    name: str, target: str, settings: SimSettings | None = None, options: dict | None = None
) -> str:
    """What determines an episode's physics on backend `name` (simulator class `target`), as
    one short string: the backend's model revision (`PHYSICS_VERSION`, bumped by any change
    that changes results), the engine's version, and a hash of the backend's settings, its
    options and the push protocol's settings. It is part of every episode's identity
    (`EpisodeSpec.physics`), so a database is never resumed across physics versions and no
    report pools two of them."""
    version, engine, physics_settings = backend_physics(target)
    engine_v = metadata.version(engine) if engine else "none"
    # the engine's own renderer is what every row had before `camera.renderer` existed: it is
    # left out, so that those rows keep their identity
    opts = {k: v for k, v in (options or {}).items() if (k, v) != ("renderer", "engine")}
    text = repr((physics_settings, settings or SimSettings(), sorted(opts.items())))
    digest = hashlib.sha256(text.encode()).hexdigest()[:10]
    return f"{name}/{version}/{engine or 'numpy'}-{engine_v}/{digest}"
