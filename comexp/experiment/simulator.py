"""Re-exports the simulator's names in one place: interface, registry, view and contact geometry.

The simulator side of the experiment is four jobs, one module each: the interface every
backend implements and its one push protocol (`comexp.experiment.interface`), the backends by
name and their physics identity (`comexp.experiment.registry`), what the camera sees of the
object (`comexp.experiment.view`), and where pusher and object meet
(`comexp.experiment.contact`). This module keeps the names users, notebooks and bench scripts
import from `comexp.experiment.simulator` (and `comexp.simulator`) working: they are the very
objects of those modules.
"""

from comexp.experiment.contact import (
    contact_push,
    point_polygon_distance,
    pusher_clearance_m,
    pusher_contact_height_m,
)
from comexp.experiment.interface import (
    PARK_XY_M,
    Frame,
    PushOutcome,
    PushStatus,
    Simulator,
    at_rest,
    classify_state,
)
from comexp.experiment.registry import (
    BACKENDS,
    FLOOR_FRICTION_CHOICES,
    RENDERER_CHOICES,
    backend_names,
    make_simulator,
    physics_identity,
)
from comexp.experiment.view import (
    crop_camera,
    object_window_px,
    outline_radius_m,
    surely_in_view,
)

__all__ = [
    "BACKENDS",
    "FLOOR_FRICTION_CHOICES",
    "Frame",
    "PARK_XY_M",
    "PushOutcome",
    "PushStatus",
    "RENDERER_CHOICES",
    "Simulator",
    "at_rest",
    "backend_names",
    "classify_state",
    "contact_push",
    "crop_camera",
    "make_simulator",
    "object_window_px",
    "outline_radius_m",
    "physics_identity",
    "point_polygon_distance",
    "pusher_clearance_m",
    "pusher_contact_height_m",
    "surely_in_view",
]
