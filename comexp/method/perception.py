"""Re-exports the perception in one place: `comexp.method.observation`, `.tracking`, `.rendering`.

Perception from the top-down depth image alone is three jobs, one module each: what one image
tells (`comexp.method.observation`: mask, footprint, contour and normals, the initial CoM
region and contacts, a tracking frame's boundary), the pose that links images
(`comexp.method.tracking`: `PoseTracker`), and the exact ray-cast image of a prism
(`comexp.method.rendering`: `render_prism_depth`, planar's camera). This module keeps the
names users, notebooks and bench scripts import from `comexp.method.perception` (and
`comexp.perception`) working: they are the very objects of those modules.
"""

from comexp.method.observation import (
    ARC_RMS_PX,
    ARC_SLOPE_DEG,
    MIN_HEIGHT_M,
    NORMAL_HALF_WINDOW_PX,
    STRAIGHT_RMS_PX,
    Observation,
    Perception,
    PerceptionError,
    TrackingView,
    floor_depth_m,
    hull_region,
    mask_pusher,
    object_mask,
    observe,
    observe_boundary,
    perceive_first,
    sample_contacts,
)
from comexp.method.rendering import (
    PRISM_NEAR_EDGE_M,
    render_prism_depth,
    render_prism_depth_numpy,
)
from comexp.method.tracking import QUANTISED_FIT_PX, PoseFit, PoseTracker

__all__ = [
    "ARC_RMS_PX",
    "ARC_SLOPE_DEG",
    "MIN_HEIGHT_M",
    "NORMAL_HALF_WINDOW_PX",
    "Observation",
    "PRISM_NEAR_EDGE_M",
    "Perception",
    "PerceptionError",
    "PoseFit",
    "PoseTracker",
    "QUANTISED_FIT_PX",
    "STRAIGHT_RMS_PX",
    "TrackingView",
    "floor_depth_m",
    "hull_region",
    "mask_pusher",
    "object_mask",
    "observe",
    "observe_boundary",
    "perceive_first",
    "render_prism_depth",
    "render_prism_depth_numpy",
    "sample_contacts",
]
