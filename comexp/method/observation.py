"""Observation: what one top-down depth image tells about the object, in metres on the floor.

The object mask, the footprint points, the contour with inward normals, the initial CoM region
(pixels inside the convex hull) and the contact candidates of the first image
(`perceive_first`); the cheap boundary of a tracking frame taken during a push
(`observe_boundary`, after `mask_pusher`). The pose that links images is `comexp.method.tracking`'s.

Why metric back-projection: the camera is perspective, so the object's top face appears
magnified and its side walls are visible away from the image centre. Back-projecting every mask
pixel with its own depth (`CameraModel.pixel_to_world`) puts top-face pixels exactly above the
footprint and side-wall pixels exactly on the outline, so all geometry below is in metres on
the floor plane and independent of where the object sits in the image.

Frames: world z up; image column u ~ +x, row v ~ -y (rows grow downward); yaw CCW positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import shapely
from numba import njit

from comexp.method.frames import CameraModel, DepthImage, Pose2D
from comexp.method.geometry import centroid as polygon_centroid
from comexp.method.geometry import signed_area

MIN_HEIGHT_M = 0.004  # anything this far above the floor plane is object
NORMAL_HALF_WINDOW_PX = 4  # contour pixels on each side used to fit a local tangent line
# A contour point is a reliable contact (not near a corner) when a line fits its neighbours
# (edge) or a parabola fits them symmetrically (arc). Tuned on ray-cast images of boxes,
# polygons, discs and ellipses: normal error <= ~5 deg where accepted (docs/method.md).
STRAIGHT_RMS_PX = 0.35
ARC_RMS_PX = 0.25
ARC_SLOPE_DEG = 3.0


class PerceptionError(RuntimeError):
    """The image does not show a usable object (empty mask, object cut by the image border).

    `failure` is the episode failure reason it maps to.
    """

    def __init__(self, message: str, failure: str = "perception") -> None:
        super().__init__(message)
        self.failure = failure


@dataclass(frozen=True)
class Observation:
    """What one depth image tells about the object, in world metres on the floor plane.

    `contour_m` is the object's outer boundary (back-projected boundary pixels), ordered
    counter-clockwise in the y-up world frame, with `normals` the inward unit normals from a
    local line fit and `straight` true where that fit is reliable (not at a corner).
    """

    mask: np.ndarray  # (H, W) bool
    points_m: np.ndarray  # (n, 2) back-projected mask pixels
    contour_m: np.ndarray  # (m, 2) CCW
    normals: np.ndarray  # (m, 2) inward unit normals
    straight: np.ndarray  # (m,) bool
    pixel_m: float  # size of one pixel at the object's top face

    @property
    def hull_m(self) -> np.ndarray:
        """Convex hull of the footprint points, counter-clockwise (k, 2)."""
        hull = cv2.convexHull(self.points_m.astype(np.float32), clockwise=False)[:, 0, :]
        hull = hull.astype(float)
        # OpenCV's orientation flag refers to its own axes; enforce CCW in the y-up frame.
        if signed_area(hull) < 0:
            hull = hull[::-1]
        return hull


def floor_depth_m(camera: CameraModel) -> float:
    """Depth of the floor plane z = 0 (the camera looks straight down)."""
    return float(camera.position_m[2])


def object_mask(img: DepthImage, min_height_m: float = MIN_HEIGHT_M) -> np.ndarray:
    """Pixels clearly above the floor; only the largest connected blob is kept (the object)."""
    depth = img.depth_m
    mask = np.zeros(depth.shape, dtype=bool)
    below = depth.dtype.type(floor_depth_m(img.camera) - min_height_m)  # the image's precision
    v0, v1, u0, u1 = _above_floor_box(depth, below)
    if v1 == 0:  # nothing above the floor
        return mask
    # only the box around what is above the floor is labelled (a few % of a full image): its
    # blobs, their raster order and so the first of the largest are the full image's
    above = np.empty((v1 - v0, u1 - u0), dtype=np.uint8)
    _above_floor(depth, u0, v0, below, above)
    # Labels plus a bincount for the areas: cv2.connectedComponentsWithStats computes
    # bounding boxes and centroids we do not need and costs ~8x more (docs/performance.md).
    n, labels = cv2.connectedComponents(above, connectivity=8)
    areas = np.bincount(labels.ravel(), minlength=n)
    biggest = 1 + int(np.argmax(areas[1:]))
    mask[v0:v1, u0:u1] = labels == biggest
    return mask


@njit(cache=True)
def _above_floor_box(depth, below):
    """Rows v0:v1 and columns u0:u1 of the box around the pixels whose depth is finite and
    less than `below` (`_above_floor`'s test); v1 = 0 when there are none. One pass over the
    image, each row first tested whole without branches (vectorised: most rows are floor)."""
    h, w = depth.shape
    v0, v1, u0, u1 = h, 0, w, 0
    for v in range(h):
        row = depth[v]
        hits = 0
        for u in range(w):
            d = row[u]
            hits += (d < below) & (d > -np.inf)  # finite and below (NaN: neither)
        if hits == 0:
            continue
        if v < v0:
            v0 = v
        v1 = v + 1
        for u in range(w):
            d = row[u]
            if d < below and d > -np.inf:
                u0 = min(u0, u)
                u1 = max(u1, u + 1)
    return v0, v1, u0, u1


@njit(cache=True)
def _local_fit_kernel(pts, half, smooth, tangent, line_rms, parab_rms, slope_deg):
    """`_local_fit` point by point, into the output arrays. Returns False when a parabola's
    normal equations are singular (repeated points): no fit."""
    m = pts.shape[0]
    w = 2 * half + 1
    xs = np.empty(w)  # the window in the point's (t, n) frame
    ys = np.empty(w)
    for i in range(m):
        px, py = pts[i, 0], pts[i, 1]
        mx = my = 0.0
        for j in range(-half, half + 1):
            k = (i + j) % m
            mx += pts[k, 0]
            my += pts[k, 1]
        mx /= w
        my /= w
        sxx = syy = sxy = 0.0
        for j in range(-half, half + 1):
            k = (i + j) % m
            ex, ey = pts[k, 0] - mx, pts[k, 1] - my
            sxx += ex * ex
            syy += ey * ey
            sxy += ex * ey
        sxx /= w
        syy /= w
        sxy /= w
        ang = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # major eigenvector of the scatter
        tx, ty = math.cos(ang), math.sin(ang)
        tr, det = sxx + syy, sxx * syy - sxy * sxy
        line_rms[i] = math.sqrt(max(0.5 * tr - math.sqrt(max(0.25 * tr * tr - det, 0.0)), 0.0))
        a, b = (i + half) % m, (i - half) % m
        if tx * (pts[a, 0] - pts[b, 0]) + ty * (pts[a, 1] - pts[b, 1]) < 0.0:
            tx, ty = -tx, -ty
        nx, ny = -ty, tx
        # the parabola y = c0 + c1 x + c2 x^2 in the (t, n) frame at the point: normal
        # equations in u = x / L (L the window's rms x: well conditioned), Cramer's rule
        ss = 0.0
        for j in range(w):
            k = (i + j - half) % m
            dx, dy = pts[k, 0] - px, pts[k, 1] - py
            xs[j] = dx * tx + dy * ty
            ys[j] = dx * nx + dy * ny
            ss += xs[j] * xs[j]
        scale = math.sqrt(ss / w)
        if not scale > 0.0:
            return False
        s0 = s1 = s2 = s3 = s4 = r0 = r1 = r2 = 0.0
        for j in range(w):
            u = xs[j] / scale
            uu = u * u
            s0 += 1.0
            s1 += u
            s2 += uu
            s3 += uu * u
            s4 += uu * uu
            r0 += ys[j]
            r1 += u * ys[j]
            r2 += uu * ys[j]
        c00, c01, c02 = s2 * s4 - s3 * s3, s2 * s3 - s1 * s4, s1 * s3 - s2 * s2
        det3 = s0 * c00 + s1 * c01 + s2 * c02
        if not abs(det3) > 1e-12 * s0 * s2 * s4:
            return False
        c11, c12, c22 = s0 * s4 - s2 * s2, s1 * s2 - s0 * s3, s0 * s2 - s1 * s1
        c0 = (c00 * r0 + c01 * r1 + c02 * r2) / det3
        c1 = (c01 * r0 + c11 * r1 + c12 * r2) / det3 / scale
        c2 = (c02 * r0 + c12 * r1 + c22 * r2) / det3 / (scale * scale)
        res = 0.0
        for j in range(w):
            x = xs[j]
            e = c0 + c1 * x + c2 * x * x - ys[j]
            res += e * e
        parab_rms[i] = math.sqrt(res / w)
        gx, gy = tx + c1 * nx, ty + c1 * ny
        g = math.sqrt(gx * gx + gy * gy)
        tangent[i, 0], tangent[i, 1] = gx / g, gy / g
        smooth[i, 0], smooth[i, 1] = px + c0 * nx, py + c0 * ny
        slope_deg[i] = math.degrees(abs(math.atan(c1)))
    return True


def _local_fit(pts: np.ndarray, half: int) -> dict[str, np.ndarray]:
    """Local shape of a closed polyline around every point (compiled: `_local_fit_kernel`).

    A line is fitted to the 2*half+1 neighbours (its direction orients the local frame), then a
    parabola y = a + b x + c x^2 in that frame (x along the line, origin at the point). The
    parabola gives a denoised position (p + a n) and tangent (slope b) that are unbiased on
    curves too; its residual, and the line's, tell corners from edges and arcs.
    """
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    m = len(pts)
    out = {
        "smooth": np.empty((m, 2)),
        "tangent": np.empty((m, 2)),
        "line_rms": np.empty(m),
        "parab_rms": np.empty(m),
        "slope_deg": np.empty(m),
    }
    ok = _local_fit_kernel(
        pts, int(half), out["smooth"], out["tangent"], out["line_rms"], out["parab_rms"],
        out["slope_deg"],
    )  # fmt: skip
    if not ok:
        raise PerceptionError("the object's contour has repeated points", "perception")
    return out


def observe(img: DepthImage, min_height_m: float = MIN_HEIGHT_M) -> Observation:
    """Mask, footprint points, contour and inward normals of the object in one depth image."""
    cam = img.camera
    mask = object_mask(img, min_height_m)
    if not mask.any():
        raise PerceptionError("no object above the floor in the depth image", "left_view")
    h, w = mask.shape
    if mask[0, :].any() or mask[-1, :].any() or mask[:, 0].any() or mask[:, -1].any():
        raise PerceptionError("the object touches the image border", "left_view")
    # same row-major order as np.nonzero(mask), ~9x cheaper on a 224 x 224 mask
    v, u = np.divmod(np.flatnonzero(mask), w)
    depth = img.depth_m[v, u]
    points = cam.pixel_to_world(u, v, depth)[:, :2]
    top_depth = float(np.min(depth))
    pixel_m = cam.pixel_size_m(top_depth)

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=len)[:, 0, :]  # (m, 2) as (u, v)
    cu, cv_ = c[:, 0], c[:, 1]
    contour = cam.pixel_to_world(cu, cv_, img.depth_m[cv_, cu])[:, :2]
    if signed_area(contour) < 0:
        contour = contour[::-1].copy()
    half = NORMAL_HALF_WINDOW_PX if len(contour) > 4 * NORMAL_HALF_WINDOW_PX else 1
    fit = _local_fit(contour, half)
    tangent = fit["tangent"]
    normals = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # left of CCW = inward
    line_px = fit["line_rms"] / pixel_m
    parab_px = fit["parab_rms"] / pixel_m
    # edges: a line fits; arcs: a parabola fits and is centred on the point (symmetric window)
    straight = (line_px < STRAIGHT_RMS_PX) | (
        (parab_px < ARC_RMS_PX) & (fit["slope_deg"] < ARC_SLOPE_DEG)
    )
    return Observation(
        mask=mask,
        points_m=points,
        contour_m=fit["smooth"],
        normals=normals,
        straight=straight,
        pixel_m=pixel_m,
    )


def mask_pusher(
    img: DepthImage, pusher_xy_m: tuple[float, float], radius_m: float, margin_m: float = 1e-3
) -> DepthImage:
    """The image with the pusher removed (its pixels set to the floor's depth).

    A pixel is the pusher's when its back-projected point (with its own depth) lies within
    `radius_m + margin_m` of the pusher's axis: the pusher is a round body about a vertical
    axis, so every point of it does, while a point of the object is at least `radius_m` from
    the axis (it touches, does not penetrate), so at most a sliver of the object at the
    contact goes with it. Only a small window around the pusher's projection is looked at.
    """
    cam = img.camera
    depth = img.depth_m
    hz = floor_depth_m(cam)
    r = radius_m + margin_m
    x, y = pusher_xy_m
    # the pusher's projection at the floor and up to the camera's near end of the object
    # (`CameraModel.world_to_pixel` of the square's corners, in scalars: the same arithmetic)
    x0, y0, z0 = cam.position_m
    us, vs = [], []
    for depth_c in (z0 - 0.0, z0 - 0.5 * hz):
        for wx, wy in ((x - r, y - r), (x + r, y + r)):
            us.append(cam.cx_px + (wx - x0) * cam.fx_px / depth_c)
            vs.append(cam.cy_px - (wy - y0) * cam.fy_px / depth_c)
    u0 = max(math.floor(min(us)) - 1, 0)
    u1 = min(math.ceil(max(us)) + 1, cam.width_px - 1)
    v0 = max(math.floor(min(vs)) - 1, 0)
    v1 = min(math.ceil(max(vs)) + 1, cam.height_px - 1)
    if u1 < u0 or v1 < v0:
        return img
    out = depth.copy()
    # only what is above the floor can be it (compared in the image's own precision)
    below = depth.dtype.type(hz - MIN_HEIGHT_M)
    view = np.array([x0, y0, cam.cx_px, cam.cy_px, cam.fx_px, cam.fy_px, x, y, r, hz])
    if _mask_pusher_kernel(out, u0, v0, u1, v1, below, view) == 0:
        return img
    return DepthImage(out, cam)


@njit(cache=True)
def _mask_pusher_kernel(out, u0, v0, u1, v1, below, view):
    """`mask_pusher`'s pixels, set to the floor's depth in `out` (the image's copy) within
    the window [u0, u1] x [v0, v1]; returns how many. `view`: camera position x, y, its
    principal point and focal lengths (px), the pusher's axis x, y, its radius with the
    margin, the floor's depth. Each pixel's back-projection is `CameraModel.pixel_to_world`'s
    arithmetic, in the same order (the numpy form's bits: tests/test_frame_kernels.py)."""
    x0, y0, cx, cy, fx, fy, x, y, r, hz = view
    n = 0
    for v in range(v0, v1 + 1):
        for u in range(u0, u1 + 1):
            d = out[v, u]
            if not d < below:
                continue
            px = x0 + (float(u) - cx) * d / fx
            py = y0 - (float(v) - cy) * d / fy
            if np.hypot(px - x, py - y) < r:
                out[v, u] = hz
                n += 1
    return n


@dataclass(frozen=True)
class TrackingView:
    """What a tracking frame needs: the object's boundary in world metres and the area
    centroid of the polygon it bounds (`observe_boundary`)."""

    contour_m: np.ndarray  # (m, 2)
    centroid_m: np.ndarray  # (2,)


def observe_boundary(
    img: DepthImage,
    near_xy_m: tuple[float, float] | None = None,
    reach_m: float = 0.15,
    min_height_m: float = MIN_HEIGHT_M,
    max_points: int = 64,
) -> TrackingView:
    """The object's outer boundary in one frame, cheaply: only a window of `reach_m` around
    `near_xy_m` (the last known position) is thresholded, no connected components (the
    largest external contour is the object once the pusher is masked), no normal fits, and
    at most `max_points` boundary points (evenly strided). A tracking frame only has to
    place the pose in the right symmetric basin; the image at rest is measured in full."""
    cam = img.camera
    depth = img.depth_m
    h, w = depth.shape
    u0, v0, u1, v1 = 0, 0, w - 1, h - 1
    x0, y0, z0 = cam.position_m
    if near_xy_m is not None:
        # `CameraModel.world_to_pixel` of the window's corners at the floor, in scalars
        x, y = near_xy_m
        fl = z0 - 0.0
        ua = cam.cx_px + ((x - reach_m) - x0) * cam.fx_px / fl
        ub = cam.cx_px + ((x + reach_m) - x0) * cam.fx_px / fl
        va = cam.cy_px - ((y + reach_m) - y0) * cam.fy_px / fl
        vb = cam.cy_px - ((y - reach_m) - y0) * cam.fy_px / fl
        u0, u1 = max(int(ua), 0), min(int(math.ceil(ub)), w - 1)
        v0, v1 = max(int(va), 0), min(int(math.ceil(vb)), h - 1)
    above = np.empty((max(v1 - v0 + 1, 0), max(u1 - u0 + 1, 0)), dtype=np.uint8)
    below = depth.dtype.type(floor_depth_m(cam) - min_height_m)  # the image's precision
    _above_floor(depth, u0, v0, below, above)
    contours, _ = cv2.findContours(above, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise PerceptionError("no object above the floor in the tracking frame", "left_view")
    c = max(contours, key=len)
    step = math.ceil(len(c) / max_points) if len(c) > max_points else 1
    contour = np.empty(((len(c) + step - 1) // step, 2))
    view = np.array([x0, y0, cam.cx_px, cam.cy_px, cam.fx_px, cam.fy_px])
    _boundary_to_world(c, step, depth, u0, v0, view, contour)
    centre = polygon_centroid(contour) if len(contour) >= 3 else contour.mean(axis=0)
    return TrackingView(contour, centre)


@njit(cache=True)
def _above_floor(depth, u0, v0, below, above):
    """`above` (uint8, the window's shape, at u0, v0): 1 where the depth is finite and less
    than `below`, else 0."""
    for i in range(above.shape[0]):
        for j in range(above.shape[1]):
            d = depth[v0 + i, u0 + j]
            above[i, j] = 1 if np.isfinite(d) and d < below else 0


@njit(cache=True)
def _boundary_to_world(c, step, depth, u0, v0, view, out):
    """Every `step`-th point of an OpenCV contour `c` ((n, 1, 2) window pixels u, v) on the
    floor plane, each at its own depth: `CameraModel.pixel_to_world`'s x and y, in the same
    arithmetic (tests/test_frame_kernels.py). `view`: camera position x, y, principal point
    and focal lengths (px)."""
    x0, y0, cx, cy, fx, fy = view
    for k in range(out.shape[0]):
        u = c[k * step, 0, 0] + u0
        v = c[k * step, 0, 1] + v0
        d = depth[v, u]
        out[k, 0] = x0 + (float(u) - cx) * d / fx
        out[k, 1] = y0 - (float(v) - cy) * d / fy


def hull_region(hull_m: np.ndarray, spacing_m: float) -> np.ndarray:
    """Regular grid points (spacing = one pixel, grid anchored at the frame origin) inside a
    polygon: the paper's "pixels inside the convex hull", as metric points on the floor.

    A metric grid rather than the raw mask pixels keeps the region uniform (perspective
    magnifies the top face and side walls crowd onto the outline), so its centroid is unbiased.
    """
    lo = np.floor(hull_m.min(axis=0) / spacing_m).astype(int)
    hi = np.ceil(hull_m.max(axis=0) / spacing_m).astype(int)
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1) * spacing_m
    inside = shapely.contains_xy(shapely.Polygon(hull_m), pts[:, 0], pts[:, 1])
    return pts[inside]


def sample_contacts(
    contour_m: np.ndarray, normals: np.ndarray, straight: np.ndarray, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Contact candidates every `spacing_m` of arc length along the contour, skipping corners
    (where the normal, hence the push direction, is ill-defined)."""
    seg = np.linalg.norm(np.diff(contour_m, axis=0, append=contour_m[:1]), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    bins = np.floor(s / spacing_m).astype(int)
    first = np.ones(len(bins), dtype=bool)
    first[1:] = bins[1:] != bins[:-1]
    keep = first & straight
    return contour_m[keep].copy(), normals[keep].copy()


@dataclass(frozen=True)
class Perception:
    """The first image's perception, expressed in the estimator's own object frame.

    The estimator frame is the world frame at the first image, shifted to the footprint hull's
    centroid: `frame_pose` is its pose in the world at that image (yaw 0 by construction).
    """

    frame_pose: Pose2D
    region_m: np.ndarray  # initial CoM region (grid points inside the hull), estimator frame
    outline_m: np.ndarray  # contour, estimator frame, CCW
    outline_normals: np.ndarray
    contacts_m: np.ndarray  # sampled contact points, estimator frame
    contact_normals: np.ndarray  # inward unit normals = push directions
    pixel_m: float


def perceive_first(
    img: DepthImage, contact_spacing_px: float = 2.0, min_height_m: float = MIN_HEIGHT_M
) -> tuple[Perception, Observation]:
    """Initial CoM region and contact candidates from the first image (Algorithm 1's input)."""
    obs = observe(img, min_height_m)
    hull = obs.hull_m
    origin = polygon_centroid(hull)
    frame = Pose2D(float(origin[0]), float(origin[1]), 0.0)
    hull_local = hull - origin
    region = hull_region(hull_local, obs.pixel_m)
    outline = obs.contour_m - origin
    contacts, cnormals = sample_contacts(
        outline, obs.normals, obs.straight, contact_spacing_px * obs.pixel_m
    )
    perc = Perception(
        frame_pose=frame,
        region_m=region,
        outline_m=outline,
        outline_normals=obs.normals.copy(),
        contacts_m=contacts,
        contact_normals=cnormals,
        pixel_m=obs.pixel_m,
    )
    return perc, obs
