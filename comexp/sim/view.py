"""What the camera sees of the object: sure-in-view tests, the image window it can cover.

Geometry of the top-down camera and the object's outline, shared by the push protocol
(`comexp.experiment.interface`: the object leaving the view is a failure) and the engines
(tracking frames render only the window the object can cover).
"""

from __future__ import annotations

import math

import numpy as np

from comexp.method.frames import CameraModel
from comexp.sim.scene import ObjectState


def outline_radius_m(outline_m: np.ndarray) -> float:
    """The largest distance of an outline corner from the object frame's origin."""
    o = np.asarray(outline_m, dtype=float)
    return float(np.sqrt(np.max(o[:, 0] * o[:, 0] + o[:, 1] * o[:, 1])))


def surely_in_view(x_m: float, y_m: float, radius_m: float, camera: CameraModel) -> bool:
    """True when a disc of `radius_m` about the floor point (x, y) projects well inside the
    image, so every outline corner within it does: the protocol checks the view every few
    steps, and this test (a few float operations) spares the exact per-corner projection
    (numpy on a handful of points, ~100x its cost) on nearly every check. False decides
    nothing: the exact test runs. Its margin (1e-6 px, 1e-9 relative on the radius) is far
    above the rounding of either computation, so the verdict is always the exact test's."""
    x0, y0, z0 = camera.position_m
    r = radius_m * (1.0 + 1e-9) + 1e-12
    kx, ky = camera.fx_px / z0, camera.fy_px / z0
    margin = 1e-6
    return (
        camera.cx_px + (x_m - r - x0) * kx >= margin
        and camera.cx_px + (x_m + r - x0) * kx <= camera.width_px - 1 - margin
        and camera.cy_px - (y_m + r - y0) * ky >= margin
        and camera.cy_px - (y_m - r - y0) * ky <= camera.height_px - 1 - margin
    )


def surely_in_view_box(
    radius_m: float, camera: CameraModel, inset_m: float = 1e-4
) -> tuple[float, float, float, float]:
    """(x_lo, x_hi, y_lo, y_hi): the floor box where the object frame's origin keeps
    `surely_in_view(x, y, radius_m, camera)` true, `inset_m` inside the box its four
    inequalities bound (the inset is far above their rounding). A backend that runs several
    of the protocol's chunks in one call (`Simulator.advance_chunks`) stops where the origin
    leaves it, for the protocol's exact check."""
    x0, y0, z0 = camera.position_m
    r = radius_m * (1.0 + 1e-9) + 1e-12
    kx, ky = camera.fx_px / z0, camera.fy_px / z0
    margin = 1e-6
    return (
        x0 + r + (margin - camera.cx_px) / kx + inset_m,
        x0 - r + (camera.width_px - 1 - margin - camera.cx_px) / kx - inset_m,
        y0 + r + (camera.cy_px - (camera.height_px - 1 - margin)) / ky + inset_m,
        y0 - r + (camera.cy_px - margin) / ky - inset_m,
    )


def object_window_px(
    camera: CameraModel,
    outline_m: np.ndarray,
    height_m: float,
    state: ObjectState,
    margin_px: int = 2,
) -> tuple[int, int, int, int] | None:
    """The window (u0, v0, width, height) of the image that holds every pixel the object can
    cover, `margin_px` wider each side, clipped to the image; None when it is off the image.

    Why it is enough: the object is a union of convex prisms, so its image lies inside the
    convex hull of the projections of its 2 n corners (bottom and top outline), placed by the
    full 3-D state (tilted or lifted objects included). Tracking frames need only this window
    (`Simulator.render_tracking_depth`): the pusher is masked away anyway.
    """
    outline = np.asarray(outline_m, dtype=float)
    n = len(outline)
    local = np.zeros((2 * n, 3))
    local[:, :2] = np.concatenate([outline, outline])
    local[n:, 2] = height_m
    cr, sr = math.cos(state.roll_rad), math.sin(state.roll_rad)
    cp, sp = math.cos(state.pitch_rad), math.sin(state.pitch_rad)
    cy, sy = math.cos(state.yaw_rad), math.sin(state.yaw_rad)
    rot = np.array(  # ZYX: R = Rz(yaw) Ry(pitch) Rx(roll), the engines' convention
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    world = local @ rot.T + np.asarray(state.position_m, dtype=float)
    uv = camera.world_to_pixel(world[:, 0], world[:, 1], world[:, 2])
    u0 = max(int(np.floor(uv[:, 0].min())) - margin_px, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + margin_px, camera.width_px - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - margin_px, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + margin_px, camera.height_px - 1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, v0, u1 - u0 + 1, v1 - v0 + 1


def crop_camera(
    camera: CameraModel, u0: int, v0: int, width_px: int, height_px: int
) -> CameraModel:
    """`CameraModel.crop`: the camera model of a window of `camera`'s image."""
    return camera.crop(u0, v0, width_px, height_px)
