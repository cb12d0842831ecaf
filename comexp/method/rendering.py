"""Rendering: the exact ray-cast depth image of an extruded polygon on the floor (no engine).

The camera of `backend=planar`, of the engines' `camera.renderer=raycast` and of the tests:
`render_prism_depth` (compiled kernels) and `render_prism_depth_numpy`, the numpy reference it
must equal pixel for pixel.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from numba import njit

from comexp.method.frames import CameraModel, DepthImage, Pose2D


def _prism_window(camera: CameraModel, outline: np.ndarray, height_m: float, pose: Pose2D):
    """The pixel window (u0, u1, v0, v1) that can see the prism (its object-frame `outline`
    at `pose`), or None: between the outline's projections at the floor and at the top
    face, one pixel of margin."""
    x0, y0, z0 = camera.position_m
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)  # as `Pose2D.to_world`
    umin, umax, vmin, vmax = _projected_extremes(
        np.ascontiguousarray(outline, dtype=float), float(pose.x_m), float(pose.y_m), c, s,
        float(x0), float(y0), camera.cx_px, camera.cy_px, camera.fx_px, camera.fy_px,
        z0 - 0.0, z0 - float(height_m),
    )  # fmt: skip
    u0 = max(math.floor(umin) - 1, 0)
    u1 = min(math.ceil(umax) + 1, camera.width_px - 1)
    v0 = max(math.floor(vmin) - 1, 0)
    v1 = min(math.ceil(vmax) + 1, camera.height_px - 1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, u1, v0, v1


@njit(cache=True)
def _projected_extremes(outline, px, py, c, s, x0, y0, cx, cy, fx, fy, depth_a, depth_b):
    """The extremes of the posed outline's pixel coordinates at two depths: each point's
    `Pose2D.to_world` then `CameraModel.world_to_pixel` arithmetic, in scalars (a few us of
    numpy calls a frame)."""
    umin = vmin = np.inf
    umax = vmax = -np.inf
    for depth in (depth_a, depth_b):
        for i in range(outline.shape[0]):
            wx = px + c * outline[i, 0] - s * outline[i, 1]
            wy = py + s * outline[i, 0] + c * outline[i, 1]
            u = cx + (wx - x0) * fx / depth
            v = cy - (wy - y0) * fy / depth
            umin, umax = min(umin, u), max(umax, u)
            vmin, vmax = min(vmin, v), max(vmax, v)
    return umin, umax, vmin, vmax


# A pixel whose top-face point lies this close to the outline is left to shapely's exact
# point-in-polygon (boundary = outside), so that the kernel's pixels are those of the
# numpy reference; farther away the kernel's crossing test cannot err (rounding ~1e-18 m).
PRISM_NEAR_EDGE_M = 1e-9


@njit(cache=True)
def _ray_depth(tx, ty, bx, by, on_top, outline, hz, height):
    """Depth of one pixel's ray, from its point tx, ty on the top-face plane to bx, by on
    the floor (object frame): the top face, the first side wall it enters, or the floor.
    The reference's arithmetic, operation for operation."""
    if on_top:
        return hz - height
    r0, r1 = bx - tx, by - ty
    n = outline.shape[0]
    tmin = np.inf
    for k in range(n):
        a0, a1 = outline[k, 0], outline[k, 1]
        kn = k + 1 if k + 1 < n else 0
        e0, e1 = outline[kn, 0] - a0, outline[kn, 1] - a1
        denom = r0 * e1 - r1 * e0
        if denom == 0.0:
            continue
        ap0, ap1 = a0 - tx, a1 - ty
        t = (ap0 * e1 - ap1 * e0) / denom
        sk = (ap0 * r1 - ap1 * r0) / denom
        if t >= 0.0 and t <= 1.0 and sk >= 0.0 and sk <= 1.0 and t < tmin:
            tmin = t
    if tmin < np.inf:
        return hz - height * (1.0 - tmin)
    return hz


@njit(cache=True)
def _boundary_distance(tx, ty, outline):
    """Distance from the point (tx, ty) to the outline's boundary (object frame)."""
    n = outline.shape[0]
    best = np.inf
    for i in range(n):
        ax, ay = outline[i, 0], outline[i, 1]
        j = i + 1 if i + 1 < n else 0
        ex, ey = outline[j, 0] - ax, outline[j, 1] - ay
        t = min(1.0, max(0.0, ((tx - ax) * ex + (ty - ay) * ey) / (ex * ex + ey * ey)))
        dx, dy = ax + t * ex - tx, ay + t * ey - ty
        best = min(best, dx * dx + dy * dy)
    return math.sqrt(best)


@njit(cache=True)
def _near_or_inside(tx, ty, outline, near_m):
    """Whether (tx, ty) lies within `near_m` of an edge (then undecided), else whether it is
    inside: even-odd crossings of the ray to +x; an edge's ends as stored, so that a ray
    through a vertex counts once (half-open in y)."""
    n = outline.shape[0]
    near2 = near_m * near_m
    inside = False
    for i in range(n):
        ax, ay = outline[i, 0], outline[i, 1]
        j = i + 1 if i + 1 < n else 0
        qx, qy = outline[j, 0], outline[j, 1]
        ex, ey = qx - ax, qy - ay
        cr = ex * (ty - ay) - ey * (tx - ax)
        if (
            cr * cr <= near2 * (ex * ex + ey * ey)
            and min(ax, qx) - near_m <= tx <= max(ax, qx) + near_m
            and min(ay, qy) - near_m <= ty <= max(ay, qy) + near_m
        ):
            return True, False
        if (ay > ty) != (qy > ty) and tx < ax + (ty - ay) * ex / ey:
            inside = not inside
    return False, inside


# `_prism_kernel` fills the pixels after one it ray-cast without casting them while their
# top-face points stay farther from the outline than this (m) beyond what the pixels' steps
# and rays can cover: far above the arithmetic's rounding (~1e-17 m) and the near band
PRISM_SKIP_GUARD_M = 1e-8


@njit(cache=True)
def _prism_kernel(outline, hz, height, cam, pose, win, out, near_m):
    """Ray-cast the window `win` = (u0, u1, v0, v1) of `out` (rows v, columns u).

    cam = (x0, y0, cx, cy, fx, fy), pose = (x, y, cos yaw, sin yaw). Returns the pixels
    whose top-face point is within `near_m` of the outline, left undecided (k, 6): v, u and
    the ray's top and floor points, for the caller to settle with an exact point-in-polygon.

    Along a row, a pixel's top-face point moves by one pixel's width on the top face: after
    a pixel ray-cast at distance d from the outline, the next pixels whose points stay
    within d (less `PRISM_SKIP_GUARD_M`) are on the top face as it is, or, outside it, floor
    as long as their rays (no longer than the row's longest) cannot reach a side wall either:
    they take the depth the ray cast would give them, without it. A pixel beyond the near
    band is decided by its crossings alone, and an outside one whose ray cannot reach the
    outline is floor without its wall test.
    """
    x0, y0, cx, cy, fx, fy = cam
    px, py, c, s = pose
    u0, u1, v0, v1 = win
    dtop = hz - height
    amb = np.empty((16, 6))
    k = 0
    step = dtop / fx  # a pixel's width on the top face
    guard = PRISM_SKIP_GUARD_M + 4.0 * near_m
    for v in range(v0, v1 + 1):
        fv = float(v)
        wyt = y0 - (fv - cy) * dtop / fy
        wyb = y0 - (fv - cy) * hz / fy
        # the longest ray of the row from its top-face point to the floor (m)
        ry = (fv - cy) * height / fy
        rx = max(abs(float(u0) - cx), abs(float(u1) - cx)) * height / fx
        ray = math.sqrt(rx * rx + ry * ry)
        skip, fill = 0, hz
        for u in range(u0, u1 + 1):
            if skip > 0:
                out[v, u] = fill
                skip -= 1
                continue
            fu = float(u)
            dx = x0 + (fu - cx) * dtop / fx - px
            dy = wyt - py
            tx, ty = c * dx + s * dy, -s * dx + c * dy
            dx = x0 + (fu - cx) * hz / fx - px
            dy = wyb - py
            bx, by = c * dx + s * dy, -s * dx + c * dy
            dist = _boundary_distance(tx, ty, outline)
            if dist > guard:  # beyond the near band: no edge test can find it near
                inside = _near_or_inside(tx, ty, outline, 0.0)[1]
                clear = dist - guard - (0.0 if inside else ray)
                if inside or clear > 0.0:  # the top face, or a ray that reaches no wall
                    out[v, u] = dtop if inside else hz
                else:
                    out[v, u] = _ray_depth(tx, ty, bx, by, False, outline, hz, height)
                if clear > step:
                    skip, fill = int(clear / step), dtop if inside else hz
                continue
            near, inside = _near_or_inside(tx, ty, outline, near_m)
            if near:
                if k == amb.shape[0]:
                    grown = np.empty((2 * k, 6))
                    grown[:k] = amb
                    amb = grown
                amb[k, 0], amb[k, 1], amb[k, 2] = v, u, tx
                amb[k, 3], amb[k, 4], amb[k, 5] = ty, bx, by
                k += 1
                continue
            out[v, u] = _ray_depth(tx, ty, bx, by, inside, outline, hz, height)
    return amb[:k]


def render_prism_depth(
    camera: CameraModel, outline_m: np.ndarray, height_m: float, pose: Pose2D
) -> DepthImage:
    """Exact ray-cast depth image of an extruded polygon on the floor (no engine needed).

    The camera of `backend=planar` and of tests: each pixel's ray is followed from the top-face
    plane down to the floor; it hits the top face, enters through a side wall, or reaches the
    floor. Only the pixels between the outline's projections at the floor and at the top face
    can hit the object (a point of a side wall projects between the two), so only that window
    is ray-cast (`_prism_kernel`, compiled); the rest is floor. The pixels are those of
    `render_prism_depth_numpy`: the same arithmetic, and shapely decides the pixels whose
    top-face point is within `PRISM_NEAR_EDGE_M` of the outline, as it does there.
    """
    outline = np.ascontiguousarray(outline_m, dtype=float)
    hz = float(camera.position_m[2])
    depth_img = np.full((camera.height_px, camera.width_px), hz)
    win = _prism_window(camera, outline, height_m, pose)
    if win is not None:
        _ray_cast_window(camera, outline, float(height_m), pose, win, depth_img)
    return DepthImage(depth_img, camera)


def render_prism_window_depth(
    camera: CameraModel,
    outline_m: np.ndarray,
    height_m: float,
    pose: Pose2D,
    margin_px: int = 2,
) -> DepthImage:
    """`render_prism_depth`'s pixels of the window that can see the prism, `margin_px` of
    floor wider each side (clipped to the image), with that window's camera model
    (`crop_camera`: its pixels back-project to the same world points): a tracking frame
    needs only the object, and the full image is ~25x more pixels to fill and threshold.
    The full image when no pixel can see it."""
    outline = np.ascontiguousarray(outline_m, dtype=float)
    win = _prism_window(camera, outline, height_m, pose)
    if win is None:
        return render_prism_depth(camera, outline, height_m, pose)
    wu0, wu1, wv0, wv1 = win
    u0, v0 = max(wu0 - margin_px, 0), max(wv0 - margin_px, 0)
    u1 = min(wu1 + margin_px, camera.width_px - 1)
    v1 = min(wv1 + margin_px, camera.height_px - 1)
    crop = camera.crop(u0, v0, u1 - u0 + 1, v1 - v0 + 1)
    depth_img = np.full((v1 - v0 + 1, u1 - u0 + 1), float(camera.position_m[2]))
    local = (wu0 - u0, wu1 - u0, wv0 - v0, wv1 - v0)
    _ray_cast_window(crop, outline, float(height_m), pose, local, depth_img)
    return DepthImage(depth_img, crop)


def _ray_cast_window(
    camera: CameraModel,
    outline: np.ndarray,
    h: float,
    pose: Pose2D,
    win: tuple[int, int, int, int],
    depth_img: np.ndarray,
) -> None:
    """Ray-cast the pixels of `win` into `depth_img` (`_prism_kernel`), shapely settling
    those within `PRISM_NEAR_EDGE_M` of the outline."""
    hz = float(camera.position_m[2])
    x0, y0, _ = camera.position_m
    cam = (float(x0), float(y0), camera.cx_px, camera.cy_px, camera.fx_px, camera.fy_px)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    pose_t = (float(pose.x_m), float(pose.y_m), c, s)
    amb = _prism_kernel(outline, hz, h, cam, pose_t, win, depth_img, PRISM_NEAR_EDGE_M)
    if len(amb):
        inside = shapely.contains_xy(shapely.Polygon(outline), amb[:, 2], amb[:, 3])
        for (v, u, tx, ty, bx, by), on_top in zip(amb, inside, strict=True):
            depth_img[int(v), int(u)] = _ray_depth(tx, ty, bx, by, on_top, outline, hz, h)


def render_prism_depth_numpy(
    camera: CameraModel, outline_m: np.ndarray, height_m: float, pose: Pose2D
) -> DepthImage:
    """`render_prism_depth` in numpy (shapely's point-in-polygon, a pixels x edges segment
    test): the reference its compiled kernel must equal pixel for pixel
    (tests/test_frame_kernels.py); ~2.7 ms per tracking frame against ~0.3 ms."""
    outline = np.asarray(outline_m, dtype=float)
    hz = camera.position_m[2]
    depth_img = np.full((camera.height_px, camera.width_px), hz)
    window = _prism_window(camera, outline, height_m, pose)
    if window is None:
        return DepthImage(depth_img, camera)
    u0, u1, v0, v1 = window
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    u, v = uu.ravel().astype(float), vv.ravel().astype(float)
    top = pose.to_object(camera.pixel_to_world(u, v, np.full(u.shape, hz - height_m))[:, :2])
    bot = pose.to_object(camera.pixel_to_world(u, v, np.full(u.shape, hz))[:, :2])
    depth = np.full(u.shape, hz)
    on_top = shapely.contains_xy(shapely.Polygon(outline), top[:, 0], top[:, 1])
    depth[on_top] = hz - height_m
    # side walls: first crossing of the segment top->bot with any edge
    rest = ~on_top
    p, r = top[rest], bot[rest] - top[rest]
    a = outline
    e = np.roll(outline, -1, axis=0) - outline
    denom = r[:, None, 0] * e[None, :, 1] - r[:, None, 1] * e[None, :, 0]
    ap = a[None, :, :] - p[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ap[..., 0] * e[None, :, 1] - ap[..., 1] * e[None, :, 0]) / denom
        s = (ap[..., 0] * r[:, None, 1] - ap[..., 1] * r[:, None, 0]) / denom
    hit = (denom != 0) & (t >= 0) & (t <= 1) & (s >= 0) & (s <= 1)
    t = np.where(hit, t, np.inf).min(axis=1)
    wall = np.isfinite(t)
    d_rest = np.full(p.shape[0], hz)
    d_rest[wall] = hz - height_m * (1.0 - t[wall])
    depth[rest] = d_rest
    depth_img[v0 : v1 + 1, u0 : u1 + 1] = depth.reshape(v1 - v0 + 1, u1 - u0 + 1)
    return DepthImage(depth_img, camera)
