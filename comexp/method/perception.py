"""Perception from the top-down depth image alone: object mask, footprint points in metres,
the initial CoM region (pixels inside the convex hull), contour points with inward normals,
and the object's planar pose relative to the first image.

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

from comexp.method.geometry import centroid as polygon_centroid
from comexp.method.geometry import signed_area
from comexp.method.scene import CameraModel, DepthImage, Pose2D
from comexp.method.scene import wrap_angle as _wrap  # the tracker's name for it

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
    above = np.isfinite(depth) & (depth < floor_depth_m(img.camera) - min_height_m)
    # Labels plus a bincount for the areas: cv2.connectedComponentsWithStats computes
    # bounding boxes and centroids we do not need and costs ~8x more (docs/performance.md).
    n, labels = cv2.connectedComponents(above.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(above)
    areas = np.bincount(labels.ravel(), minlength=n)
    biggest = 1 + int(np.argmax(areas[1:]))
    return labels == biggest


def _local_fit(pts: np.ndarray, half: int) -> dict[str, np.ndarray]:
    """Local shape of a closed polyline around every point, vectorised over all points.

    A line is fitted to the 2*half+1 neighbours (its direction orients the local frame), then a
    parabola y = a + b x + c x^2 in that frame (x along the line, origin at the point). The
    parabola gives a denoised position (p + a n) and tangent (slope b) that are unbiased on
    curves too; its residual, and the line's, tell corners from edges and arcs.
    """
    m = len(pts)
    idx = (np.arange(m)[:, None] + np.arange(-half, half + 1)[None, :]) % m
    win = pts[idx]  # (m, w, 2)
    d0 = win - win.mean(axis=1, keepdims=True)
    sxx = np.mean(d0[..., 0] ** 2, axis=1)
    syy = np.mean(d0[..., 1] ** 2, axis=1)
    sxy = np.mean(d0[..., 0] * d0[..., 1], axis=1)
    ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # major eigenvector of the scatter matrix
    t = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    line_rms = np.sqrt(np.maximum(0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0)), 0))
    chord = pts[(np.arange(m) + half) % m] - pts[(np.arange(m) - half) % m]
    t[np.sum(t * chord, axis=1) < 0] *= -1.0
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    d = win - pts[:, None, :]
    x = np.sum(d * t[:, None, :], axis=2)
    y = np.sum(d * n[:, None, :], axis=2)
    a_mat = np.stack([np.ones_like(x), x, x * x], axis=2)
    ata = np.einsum("mki,mkj->mij", a_mat, a_mat)
    aty = np.einsum("mki,mk->mi", a_mat, y)
    coef = np.linalg.solve(ata, aty[..., None])[..., 0]
    fit = np.einsum("mki,mi->mk", a_mat, coef)
    parab_rms = np.sqrt(np.mean((fit - y) ** 2, axis=1))
    slope = coef[:, 1]
    tangent = t + slope[:, None] * n
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return {
        "smooth": pts + coef[:, :1] * n,
        "tangent": tangent,
        "line_rms": line_rms,
        "parab_rms": parab_rms,
        "slope_deg": np.degrees(np.abs(np.arctan(slope))),
    }


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
    d = depth[v0 : v1 + 1, u0 : u1 + 1]
    vv, uu = np.nonzero(d < hz - MIN_HEIGHT_M)  # only what is above the floor can be it
    if len(vv) == 0:
        return img
    dv = d[vv, uu]
    # `CameraModel.pixel_to_world`'s x and y, without the stacking
    px = x0 + ((uu + u0).astype(float) - cam.cx_px) * dv / cam.fx_px
    py = y0 - ((vv + v0).astype(float) - cam.cy_px) * dv / cam.fy_px
    hit = np.hypot(px - x, py - y) < r
    if not hit.any():
        return img
    out = depth.copy()
    out[vv[hit] + v0, uu[hit] + u0] = hz
    return DepthImage(out, cam)


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
    win = depth[v0 : v1 + 1, u0 : u1 + 1]
    above = (np.isfinite(win) & (win < floor_depth_m(cam) - min_height_m)).view(np.uint8)
    contours, _ = cv2.findContours(above, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise PerceptionError("no object above the floor in the tracking frame", "left_view")
    c = max(contours, key=len)[:, 0, :]
    if len(c) > max_points:
        c = c[:: math.ceil(len(c) / max_points)]
    cu, cv_ = c[:, 0] + u0, c[:, 1] + v0
    dc = depth[cv_, cu]
    # `CameraModel.pixel_to_world`'s x and y, without the stacking
    contour = np.empty((len(c), 2))
    contour[:, 0] = x0 + (cu.astype(float) - cam.cx_px) * dc / cam.fx_px
    contour[:, 1] = y0 - (cv_.astype(float) - cam.cy_px) * dc / cam.fy_px
    centre = polygon_centroid(contour) if len(contour) >= 3 else contour.mean(axis=0)
    return TrackingView(contour, centre)


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


# A boundary traced on the pixel grid is off the true outline by a quantisation error of about
# 1/sqrt(12) = 0.29 px rms; fits up to this rms are all "as good as the image tells".
QUANTISED_FIT_PX = 0.5


def _rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _principal_angle(points: np.ndarray) -> tuple[float, float]:
    """Orientation of the main axis (rad, mod pi) and anisotropy (1 - l2/l1) of a point set."""
    d = points - points.mean(axis=0)
    sxx, syy, sxy = np.mean(d[:, 0] ** 2), np.mean(d[:, 1] ** 2), np.mean(d[:, 0] * d[:, 1])
    ang = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = math.sqrt(max(0.25 * tr * tr - det, 0.0))
    l1, l2 = 0.5 * tr + disc, 0.5 * tr - disc
    return ang, (1.0 - l2 / l1) if l1 > 0 else 0.0


@dataclass(frozen=True)
class PoseFit:
    pose: Pose2D  # pose of the estimator frame in the world at this image
    rms_px: float  # point-to-line residual of the contour registration
    iterations: int


class PoseTracker:
    """Pose of the object (its estimator frame) in each new image, by registering the image's
    contour onto the first image's contour (point-to-line ICP, seeded by the previous pose and
    by second-moment alignment).

    Registering against the first image, not the previous one, keeps errors from accumulating.
    Rotational symmetries of the outline are invisible to any vision method: among equally
    good fits the one closest to the previous pose is returned (smallest rotation per push).
    """

    def __init__(self, first: Perception, first_obs: Observation) -> None:
        self.ref = first.outline_m
        self.ref_normals = first.outline_normals
        # Nearest reference points by brute force (a few hundred x a few hundred): cheaper
        # than a k-d tree query at this size, and constant when the seed is far off.
        self._ref_sq = np.einsum("ij,ij->i", self.ref, self.ref)
        self.pixel_m = first.pixel_m
        self.frame0 = first.frame_pose
        self.ref_axis, self.ref_aniso = _principal_angle(first_obs.points_m)
        self.ref_center = first_obs.points_m.mean(axis=0) - np.array(
            [first.frame_pose.x_m, first.frame_pose.y_m]
        )
        self.ref_centroid = polygon_centroid(self.ref)
        self.last = first.frame_pose
        # tracking within a push (`begin_push`, `track`): (t_s, yaw_rad) of the push's start
        # and of its frames so far, for the constant-rate prediction of the next yaw
        self._history: list[tuple[float, float]] = []

    def _nearest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to, and index of, the nearest reference point for each row of x.

        The argmin uses |r|^2 - 2 x.r (|x|^2 is the same for every r); the distance is then
        recomputed from the coordinate differences, as a k-d tree computes it."""
        j = np.argmin(self._ref_sq[None, :] - 2.0 * (x @ self.ref.T), axis=1)
        diff = x - self.ref[j]
        return np.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]), j

    def _icp(
        self,
        q: np.ndarray,
        yaw0: float,
        t0: np.ndarray,
        max_iter: int = 40,
        tol_rad: float = 1e-7,
        tol_m: float = 1e-8,
    ) -> PoseFit:
        """Fit world->frame transform x = R(phi) q + s; returns the frame's pose in the world."""
        phi = -yaw0
        s = -_rot(phi) @ t0
        gate = 4.0 * self.pixel_m
        it = 0
        rms = math.inf
        for it in range(1, max_iter + 1):  # noqa: B007 - reported
            x = q @ _rot(phi).T + s
            dist, j = self._nearest(x)
            keep = dist < max(gate, 3.0 * _median(dist))
            jk = j[keep]
            n = self.ref_normals[jk]
            xk = x[keep]
            r = np.sum(n * (xk - self.ref[jk]), axis=1)
            jac = np.column_stack([n[:, 1] * xk[:, 0] - n[:, 0] * xk[:, 1], n[:, 0], n[:, 1]])
            delta, *_ = np.linalg.lstsq(jac, -r, rcond=None)
            # truncated residual over ALL points: dropped outliers count as a full gate each,
            # so a partial overlap cannot look like a good fit
            r_all = np.full(len(q), gate)
            r_all[keep] = np.minimum(np.abs(r), gate)
            rms = float(np.sqrt(np.mean(r_all * r_all))) / self.pixel_m
            phi += float(delta[0])
            s = _rot(float(delta[0])) @ s + delta[1:]
            if abs(delta[0]) < tol_rad and np.hypot(delta[1], delta[2]) < tol_m:
                break
        yaw = -phi
        t = -_rot(yaw) @ s
        return PoseFit(Pose2D(float(t[0]), float(t[1]), yaw), rms, it)

    def _icp_fast(
        self,
        q: np.ndarray,
        yaw0: float,
        t0: np.ndarray,
        max_iter: int,
        tol_rad: float,
        tol_m: float,
    ) -> PoseFit:
        """`_icp` in one compiled call (`_icp_kernel`): the same iterations, the least-squares
        step by its normal equations instead of an SVD (equal up to rounding). A tracking
        frame's ICP was ~0.5 ms of numpy calls on 64 points (docs/performance.md). Should
        the normal equations be singular, `_icp` itself runs (it returns lstsq's min-norm step).
        """
        phi = -yaw0
        s = -_rot(phi) @ t0
        q = np.ascontiguousarray(q, dtype=float)
        ok, phi, sx, sy, rms_m, it = _icp_kernel(
            q,
            self.ref,
            self._ref_sq,
            self.ref_normals,
            phi,
            float(s[0]),
            float(s[1]),
            4.0 * self.pixel_m,
            max_iter,
            tol_rad,
            tol_m,
        )
        if not ok:
            return self._icp(q, yaw0, t0, max_iter=max_iter, tol_rad=tol_rad, tol_m=tol_m)
        yaw = -phi
        t = -_rot(yaw) @ np.array([sx, sy])
        return PoseFit(Pose2D(float(t[0]), float(t[1]), yaw), rms_m / self.pixel_m, it)

    def fit(self, obs: Observation) -> PoseFit:
        q = obs.contour_m
        prev = self.last
        axis, aniso = _principal_angle(obs.points_m)
        cands = [prev.yaw_rad]
        if aniso > 0.05:  # the main axis is well defined: moment alignment, both ways round
            d = axis - self.ref_axis
            cands += [d, d + math.pi]
        center_w = obs.points_m.mean(axis=0)

        def start(yaw: float) -> np.ndarray:
            return center_w - _rot(yaw) @ self.ref_center

        fits = [self._icp(q, y, start(y)) for y in cands]
        best = min(f.rms_px for f in fits)
        if best > 1.0:  # poor fit from every seed: search the whole circle
            extra = [prev.yaw_rad + k * math.pi / 4 for k in range(1, 8)]
            fits += [self._icp(q, y, start(y)) for y in extra]
            best = min(f.rms_px for f in fits)
        # fits within a few degrees of each other are one basin: keep its best. Distinct
        # basins that fit equally well are symmetric copies: take the smallest rotation.
        # "Equally well" is up to what the image can tell: a copy may fit a few tenths of a
        # pixel better than the true pose (perspective shows other side walls where the object
        # now stands), so any fit within the quantisation noise counts as good.
        basins: list[PoseFit] = []
        for f in sorted(fits, key=lambda f: f.rms_px):
            if all(abs(_wrap(f.pose.yaw_rad - b.pose.yaw_rad)) > math.radians(5) for b in basins):
                basins.append(f)
        good = [f for f in basins if f.rms_px <= max(best + 0.1, QUANTISED_FIT_PX)]
        chosen = min(good, key=lambda f: abs(_wrap(f.pose.yaw_rad - prev.yaw_rad)))
        # unwrapped: the yaw continues from the previous one, so that a tracked rotation over
        # several frames may exceed half a turn
        p = chosen.pose
        yaw = prev.yaw_rad + _wrap(p.yaw_rad - prev.yaw_rad)
        chosen = PoseFit(Pose2D(p.x_m, p.y_m, yaw), chosen.rms_px, chosen.iterations)
        self.last = chosen.pose
        return chosen

    def begin_push(self) -> None:
        """A push starts from the current pose, at rest: the next frames are predicted from it."""
        self._history = [(0.0, self.last.yaw_rad)]

    def hold(self, t_s: float) -> None:
        """A frame at `t_s` into the push showed the object at rest (not rendered: it shows
        nothing new): the pose is the last one, and the next frame is predicted from rest.
        Without it the rate of the last two moving frames is extrapolated over the gap: an
        object that stops and is hit again (a high-friction floor) was then predicted to have
        turned on, up to a whole symmetry angle."""
        if not self._history:
            self._history = [(0.0, self.last.yaw_rad)]
        self._history.append((t_s, self.last.yaw_rad))

    def predicted_yaw(self, t_s: float) -> float:
        """The yaw at time `t_s` of the push, extrapolated at the rate of the last two frames
        (the push's start counts as one, at rest): the seed of the next frame's fit."""
        h = self._history
        if len(h) < 2:
            return self.last.yaw_rad
        (t0, y0), (t1, y1) = h[-2], h[-1]
        rate = (y1 - y0) / (t1 - t0) if t1 > t0 else 0.0
        return y1 + rate * (t_s - t1)

    def wants_frame(self, t_s: float, driving: bool, step_deg: float, gap_s: float) -> bool:
        """Whether the camera frame `t_s` into the push is worth tracking (skipped ones are
        not even rendered in simulation: `Simulator.push(frame_wanted=...)`).

        While the pusher drives, every frame: the fastest turns of the study (40-55 deg within
        a 75 ms push on a high-friction floor) happen in contact, where the rate changes
        abruptly. Once the pusher stops, the object slides under floor friction alone, and a
        frame is needed when the constant-rate prediction from the last two frames has it
        turned `step_deg` since the last one, or `gap_s` after it at the latest: friction
        can also speed a turn up (the load shifts as the object slides), and an angular
        acceleration alpha the prediction misses adds alpha gap^2 / 2 (docs/method.md
        measures the turn beyond the prediction with and without the cap). `step_deg` <= 0:
        every frame.
        """
        if driving or step_deg <= 0.0 or len(self._history) < 2:
            return True
        t1, y1 = self._history[-1]
        if t_s - t1 >= gap_s - 1e-9:
            return True
        return abs(self.predicted_yaw(t_s) - y1) >= math.radians(step_deg)

    def track(self, view: TrackingView, t_s: float, max_iter: int = 8) -> PoseFit:
        """Pose in a tracking frame taken `t_s` into the push (after `begin_push`).

        Registered against the first image, like `fit`, so errors do not accumulate from
        frame to frame; seeded by the predicted yaw, so that between two frames the object
        only has to turn by less than half its symmetry angle *more than predicted* for the
        right basin to be found. One seed and few iterations: the frame only carries the
        unwrapped yaw forward; the image at rest is then measured by `fit`, seeded here.
        """
        yaw0 = self.predicted_yaw(t_s)
        t0 = view.centroid_m - _rot(yaw0) @ self.ref_centroid
        # converged to 0.05 deg / 0.1 mm: a frame only carries the yaw to the right basin
        f = self._icp_fast(view.contour_m, yaw0, t0, max_iter=max_iter, tol_rad=1e-3, tol_m=1e-4)
        p = f.pose
        yaw = yaw0 + _wrap(p.yaw_rad - yaw0)
        f = PoseFit(Pose2D(p.x_m, p.y_m, yaw), f.rms_px, f.iterations)
        if not self._history:
            self._history = [(0.0, self.last.yaw_rad)]
        self._history.append((t_s, yaw))
        self.last = f.pose
        return f


@njit(cache=True)
def _icp_kernel(q, ref, ref_sq, ref_normals, phi, sx, sy, gate, max_iter, tol_rad, tol_m):
    """`PoseTracker._icp`'s iterations on world->frame x = R(phi) q + s, in scalars.

    Per iteration: nearest reference point of every x (argmin of |r|^2 - 2 x.r, the
    distance from the differences), the gate max(gate, 3 median), the point-to-line normal
    equations of the kept points, solved by Cholesky, and the update. Returns (ok, phi, sx,
    sy, truncated rms in metres, iterations); ok is False when the normal equations are
    not positive definite (then nothing is to be trusted and `_icp` runs instead).
    """
    m = q.shape[0]
    nr = ref.shape[0]
    x = np.empty((m, 2))
    dist = np.empty(m)
    jidx = np.empty(m, dtype=np.int64)
    it = 0
    rms = np.inf
    for it in range(1, max_iter + 1):  # noqa: B007 - reported
        c, s = math.cos(phi), math.sin(phi)
        for i in range(m):
            x0 = q[i, 0] * c - q[i, 1] * s + sx
            x1 = q[i, 0] * s + q[i, 1] * c + sy
            x[i, 0], x[i, 1] = x0, x1
            best, jb = np.inf, 0
            for j in range(nr):
                v = ref_sq[j] - 2.0 * (x0 * ref[j, 0] + x1 * ref[j, 1])
                if v < best:
                    best, jb = v, j
            jidx[i] = jb
            d0, d1 = x0 - ref[jb, 0], x1 - ref[jb, 1]
            dist[i] = math.sqrt(d0 * d0 + d1 * d1)
        srt = np.sort(dist)
        k = m // 2
        med = srt[k] if m % 2 else 0.5 * (srt[k - 1] + srt[k])
        lim = max(gate, 3.0 * med)
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        b0 = b1 = b2 = 0.0
        acc = 0.0
        for i in range(m):
            if not dist[i] < lim:
                acc += gate * gate
                continue
            jb = jidx[i]
            n0, n1 = ref_normals[jb, 0], ref_normals[jb, 1]
            x0, x1 = x[i, 0], x[i, 1]
            r = n0 * (x0 - ref[jb, 0]) + n1 * (x1 - ref[jb, 1])
            g0 = n1 * x0 - n0 * x1
            a00 += g0 * g0
            a01 += g0 * n0
            a02 += g0 * n1
            a11 += n0 * n0
            a12 += n0 * n1
            a22 += n1 * n1
            b0 -= g0 * r
            b1 -= n0 * r
            b2 -= n1 * r
            ra = min(abs(r), gate)
            acc += ra * ra
        rms = math.sqrt(acc / m)
        # Cholesky of the symmetric 3x3 normal matrix, then the two triangular solves
        if not a00 > 0.0:
            return False, phi, sx, sy, rms, it
        l00 = math.sqrt(a00)
        l10, l20 = a01 / l00, a02 / l00
        p11 = a11 - l10 * l10
        if not p11 > 0.0:
            return False, phi, sx, sy, rms, it
        l11 = math.sqrt(p11)
        l21 = (a12 - l20 * l10) / l11
        p22 = a22 - l20 * l20 - l21 * l21
        if not p22 > 0.0:
            return False, phi, sx, sy, rms, it
        l22 = math.sqrt(p22)
        y0 = b0 / l00
        y1 = (b1 - l10 * y0) / l11
        y2 = (b2 - l20 * y0 - l21 * y1) / l22
        e2 = y2 / l22
        e1 = (y1 - l21 * e2) / l11
        e0 = (y0 - l10 * e1 - l20 * e2) / l00
        phi += e0
        cd, sd = math.cos(e0), math.sin(e0)
        sx, sy = cd * sx - sd * sy + e1, sd * sx + cd * sy + e2
        if abs(e0) < tol_rad and math.hypot(e1, e2) < tol_m:
            break
    return True, phi, sx, sy, rms, it


def _median(d: np.ndarray) -> float:
    """np.median of a 1-d float array without NaNs, by partial sort (~5x less overhead)."""
    n = len(d)
    k = n // 2
    if n % 2:
        return float(np.partition(d, k)[k])
    p = np.partition(d, (k - 1, k))
    return float(0.5 * (p[k - 1] + p[k]))


def _prism_window(camera: CameraModel, world_outline: np.ndarray, height_m: float):
    """The pixel window (u0, u1, v0, v1) that can see the prism, or None: between the
    outline's projections at the floor and at the top face, one pixel of margin."""
    uv = np.concatenate(
        [
            camera.world_to_pixel(world_outline[:, 0], world_outline[:, 1], 0.0),
            camera.world_to_pixel(world_outline[:, 0], world_outline[:, 1], height_m),
        ]
    )
    u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 1, camera.width_px - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 1, camera.height_px - 1)
    if u1 < u0 or v1 < v0:
        return None
    return u0, u1, v0, v1


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
def _prism_kernel(outline, hz, height, cam, pose, win, out, near_m):
    """Ray-cast the window `win` = (u0, u1, v0, v1) of `out` (rows v, columns u).

    cam = (x0, y0, cx, cy, fx, fy), pose = (x, y, cos yaw, sin yaw). Returns the pixels
    whose top-face point is within `near_m` of the outline, left undecided (k, 6): v, u and
    the ray's top and floor points, for the caller to settle with an exact point-in-polygon.
    """
    x0, y0, cx, cy, fx, fy = cam
    px, py, c, s = pose
    u0, u1, v0, v1 = win
    n = outline.shape[0]
    dtop = hz - height
    near2 = near_m * near_m
    amb = np.empty((16, 6))
    k = 0
    for v in range(v0, v1 + 1):
        fv = float(v)
        wyt = y0 - (fv - cy) * dtop / fy
        wyb = y0 - (fv - cy) * hz / fy
        for u in range(u0, u1 + 1):
            fu = float(u)
            dx = x0 + (fu - cx) * dtop / fx - px
            dy = wyt - py
            tx, ty = c * dx + s * dy, -s * dx + c * dy
            dx = x0 + (fu - cx) * hz / fx - px
            dy = wyb - py
            bx, by = c * dx + s * dy, -s * dx + c * dy
            inside = False
            near = False
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
                    near = True
                    break
                # even-odd crossings of the ray to +x; an edge's ends as stored, so that a
                # ray through a vertex counts once (half-open in y)
                if (ay > ty) != (qy > ty) and tx < ax + (ty - ay) * ex / ey:
                    inside = not inside
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
    win = _prism_window(camera, pose.to_world(outline), height_m)
    if win is None:
        return DepthImage(depth_img, camera)
    x0, y0, _ = camera.position_m
    cam = (float(x0), float(y0), camera.cx_px, camera.cy_px, camera.fx_px, camera.fy_px)
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    pose_t = (float(pose.x_m), float(pose.y_m), c, s)
    h = float(height_m)
    amb = _prism_kernel(outline, hz, h, cam, pose_t, win, depth_img, PRISM_NEAR_EDGE_M)
    if len(amb):
        inside = shapely.contains_xy(shapely.Polygon(outline), amb[:, 2], amb[:, 3])
        for (v, u, tx, ty, bx, by), on_top in zip(amb, inside, strict=True):
            depth_img[int(v), int(u)] = _ray_depth(tx, ty, bx, by, on_top, outline, hz, h)
    return DepthImage(depth_img, camera)


def render_prism_depth_numpy(
    camera: CameraModel, outline_m: np.ndarray, height_m: float, pose: Pose2D
) -> DepthImage:
    """`render_prism_depth` in numpy (shapely's point-in-polygon, a pixels x edges segment
    test): the reference its compiled kernel must equal pixel for pixel
    (tests/test_frame_kernels.py); ~2.7 ms per tracking frame against ~0.3 ms."""
    outline = np.asarray(outline_m, dtype=float)
    hz = camera.position_m[2]
    depth_img = np.full((camera.height_px, camera.width_px), hz)
    window = _prism_window(camera, pose.to_world(outline), height_m)
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
