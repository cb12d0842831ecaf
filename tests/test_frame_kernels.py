"""The cheaper paths of a tracking frame agree with what they replaced: the tracker's ICP
kernel (`fit` and `track` run it) with `PoseTracker._icp`, on real frames of every built-in
object at random poses and seeds, up to rounding; planar's ray cast with the numpy one
(`render_prism_depth_numpy`), pixel for pixel; the window a tracking frame renders with the
full image, pixel for pixel and in what the tracker sees of it; `mask_pusher` and
`observe_boundary` with their numpy versions before (kept below), exactly."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from comexp.experiment.objects import load_objects
from comexp.method.frames import CameraSpec, DepthImage, Pose2D
from comexp.method.geometry import centroid as polygon_centroid
from comexp.method.observation import (
    MIN_HEIGHT_M,
    PerceptionError,
    TrackingView,
    floor_depth_m,
    mask_pusher,
    observe_boundary,
    perceive_first,
)
from comexp.method.rendering import (
    _prism_kernel,
    _prism_window,
    render_prism_depth,
    render_prism_depth_numpy,
    render_prism_window_depth,
)
from comexp.method.tracking import PoseTracker, _icp_kernel, _median_kernel

CAM = CameraSpec().model()
OBJECTS = load_objects()


def _frames(name: str, n: int, seed: int):
    """A tracker on the object's first image and n (moved-image view, seed yaw, seed
    translation) triples: the object moved by up to 4 cm and 40 deg, seeded up to 10 deg and
    5 mm off (a tracking frame's prediction error, and beyond)."""
    obj = OBJECTS[name]
    outline = np.asarray(obj.outline_cm, dtype=float) / 100.0
    height = obj.height_cm / 100.0
    rng = np.random.default_rng(seed)
    pose0 = Pose2D(*rng.uniform(-0.03, 0.03, 2), float(rng.uniform(-math.pi, math.pi)))
    perc, obs0 = perceive_first(render_prism_depth(CAM, outline, height, pose0))
    tracker = PoseTracker(perc, obs0)
    out = []
    for _ in range(n):
        move = rng.uniform([-0.04, -0.04, -0.7], [0.04, 0.04, 0.7])
        pose = Pose2D(pose0.x_m + move[0], pose0.y_m + move[1], pose0.yaw_rad + move[2])
        view = observe_boundary(render_prism_depth(CAM, outline, height, pose))
        # the frame's true pose (estimator frame in the world) plus a seed error
        truth = pose.to_world(pose0.to_object(np.array([perc.frame_pose.x_m, perc.frame_pose.y_m])))
        yaw0 = move[2] + float(rng.uniform(-0.17, 0.17))
        t0 = truth + rng.uniform(-0.005, 0.005, 2)
        out.append((view, yaw0, t0))
    return tracker, out


@pytest.mark.parametrize("name", sorted(OBJECTS))
def test_icp_kernel_is_the_numpy_icp_up_to_rounding(name):
    tracker, frames = _frames(name, 6, seed=sum(map(ord, name)))
    for view, yaw0, t0 in frames:
        for max_iter, tol_rad, tol_m in ((8, 1e-3, 1e-4), (40, 1e-7, 1e-8)):
            ref = tracker._icp(view.contour_m, yaw0, t0, max_iter, tol_rad, tol_m)
            new = tracker._icp_fast(view.contour_m, yaw0, t0, max_iter, tol_rad, tol_m)
            assert new.iterations == ref.iterations
            assert abs(new.pose.yaw_rad - ref.pose.yaw_rad) < 1e-9
            assert abs(new.pose.x_m - ref.pose.x_m) < 1e-10
            assert abs(new.pose.y_m - ref.pose.y_m) < 1e-10
            assert new.rms_px == pytest.approx(ref.rms_px, rel=1e-9, abs=1e-12)


def test_icp_kernel_moves_and_counts_like_the_numpy_icp():
    """Not a vacuous agreement: from a seed 0.15 rad off the kernel turns by about that much,
    in more than one iteration, and a wrong update (one iteration cut short) is caught."""
    tracker, frames = _frames("rect_8x5", 1, seed=3)
    view, yaw0, t0 = frames[0]
    ref = tracker._icp(view.contour_m, yaw0 + 0.15, t0, 8, 1e-3, 1e-4)
    new = tracker._icp_fast(view.contour_m, yaw0 + 0.15, t0, 8, 1e-3, 1e-4)
    assert ref.iterations > 1 and abs(ref.pose.yaw_rad - (yaw0 + 0.15)) > 0.05
    assert abs(new.pose.yaw_rad - ref.pose.yaw_rad) < 1e-9
    short = tracker._icp_fast(view.contour_m, yaw0 + 0.15, t0, ref.iterations - 1, 1e-3, 1e-4)
    assert abs(short.pose.yaw_rad - ref.pose.yaw_rad) > 1e-6


def test_an_icp_limit_cycle_ends_where_its_iterations_would():
    """A run that revisits a state (to the bit) cycles from there: the kernel ends it at once
    with the state and rms the iterations would reach at `max_iter`. Each run equals the
    same iterations one call at a time (max_iter=1 from each state), which never skip;
    among these frames some runs do cycle, with periods > 1."""
    cycles: list[int] = []
    for name in sorted(OBJECTS):
        tracker, frames = _frames(name, 6, seed=sum(map(ord, name)))
        args = (tracker.ref, tracker._ref_sq, tracker.ref_normals)
        gate = 4.0 * tracker.pixel_m
        for view, yaw0, t0 in frames:
            q = np.ascontiguousarray(view.contour_m)
            phi = -yaw0
            c, s = math.cos(phi), math.sin(phi)
            state = (phi, -(c * t0[0] - s * t0[1]), -(s * t0[0] + c * t0[1]))
            for max_iter in (40, 23):
                whole = _icp_kernel(q, *args, *state, gate, max_iter, 1e-7, 1e-8)
                seen, st = [state], state
                for it in range(1, max_iter + 1):
                    one = _icp_kernel(q, *args, *st, gate, 1, 1e-7, 1e-8)
                    st = one[1:4]
                    if st in seen and it < max_iter and max_iter == 40:
                        cycles.append(it - seen.index(st))
                    seen.append(st)
                    if one[5] == 1 and it < max_iter and whole[5] == it:
                        break  # converged at iteration `it`
                assert whole[:5] == (True, *st, one[4]), (name, max_iter)
    assert cycles and max(cycles) > 1, cycles


def test_the_icp_gate_s_median_is_numpy_s():
    """`_median_kernel` (selection, no sort) gives np.median's value to the bit: odd and
    even lengths, ties, one element."""
    rng = np.random.default_rng(7)
    for m in [1, 2, 3, 4, 5, 8, 63, 64, 111, 112, 200]:
        for d in (rng.random(m), np.round(rng.random(m) * 4) / 4, np.full(m, 0.25)):
            assert _median_kernel(d.copy(), np.empty(m)) == np.median(d), (m, d)


def test_singular_normal_equations_fall_back_to_the_numpy_icp():
    """Every reference normal alike (a degenerate outline): the kernel says so, and
    `_icp_fast` returns exactly `_icp`'s minimum-norm answer."""
    tracker, frames = _frames("square_7", 1, seed=5)
    view, yaw0, t0 = frames[0]
    tracker.ref_normals = np.tile([1.0, 0.0], (len(tracker.ref), 1))
    tracker.ref = tracker.ref * 0.0
    tracker._ref_sq = np.zeros(len(tracker.ref))
    ok, *_ = _icp_kernel(
        np.ascontiguousarray(view.contour_m),
        tracker.ref,
        tracker._ref_sq,
        tracker.ref_normals,
        -yaw0,
        0.0,
        0.0,
        4.0 * tracker.pixel_m,
        8,
        1e-3,
        1e-4,
    )
    assert not ok
    ref = tracker._icp(view.contour_m, yaw0, t0, 8, 1e-3, 1e-4)
    assert tracker._icp_fast(view.contour_m, yaw0, t0, 8, 1e-3, 1e-4) == ref


def _random_prisms(n: int, seed: int):
    """(outline, height, pose) of n random built-in objects, scaled 0.6-1.4, at random poses
    anywhere in view (some cut by the image border), plus poses on the pixel grid's axes."""
    rng = np.random.default_rng(seed)
    names = sorted(OBJECTS)
    for k in range(n):
        obj = OBJECTS[names[k % len(names)]]
        outline = np.asarray(obj.outline_cm, dtype=float) / 100.0 * rng.uniform(0.6, 1.4)
        yaw = float(rng.uniform(-math.pi, math.pi)) if k % 4 else 0.5 * math.pi * (k % 3)
        xy = rng.uniform(-0.25, 0.25, 2) if k % 5 == 0 else rng.uniform(-0.1, 0.1, 2)
        if k % 7 == 0:
            xy = np.zeros(2)  # centred, axis-aligned edges on pixel boundaries, if any
        yield outline, obj.height_cm / 100.0 * rng.uniform(0.5, 2.0), Pose2D(*xy, yaw)


def test_render_prism_depth_is_the_numpy_ray_cast_pixel_for_pixel():
    n_object_px = 0
    for outline, height, pose in _random_prisms(120, seed=11):
        new = render_prism_depth(CAM, outline, height, pose).depth_m
        ref = render_prism_depth_numpy(CAM, outline, height, pose).depth_m
        np.testing.assert_array_equal(new, ref)
        n_object_px += int(np.sum(ref < CAM.position_m[2]))
    assert n_object_px > 100_000  # the poses do show objects (top faces and walls)


def test_the_ray_cast_window_is_the_projections_bounding_box():
    """`_prism_window` (compiled extremes) is the box of the outline's `world_to_pixel`
    projections at the floor and at the top face, one pixel wider, clipped to the image:
    the pixels outside it, which no ray cast looks at, cannot see the prism."""
    for outline, height, pose in _random_prisms(120, seed=13):
        world = pose.to_world(outline)
        uv = np.concatenate(
            [CAM.world_to_pixel(world[:, 0], world[:, 1], z) for z in (0.0, height)]
        )
        u0 = max(math.floor(uv[:, 0].min()) - 1, 0)
        u1 = min(math.ceil(uv[:, 0].max()) + 1, CAM.width_px - 1)
        v0 = max(math.floor(uv[:, 1].min()) - 1, 0)
        v1 = min(math.ceil(uv[:, 1].max()) + 1, CAM.height_px - 1)
        want = (u0, u1, v0, v1) if u0 <= u1 and v0 <= v1 else None
        assert _prism_window(CAM, outline, height, pose) == want


def test_a_tracking_frame_s_window_is_the_full_image_s_and_tracks_the_same():
    """The window (`render_prism_window_depth`) holds the full image's pixels at the same
    world points, the full image is floor outside it, and the pusher mask and the boundary
    the tracker fits are the same, to the bit, with the pusher touching the object."""
    hz = CAM.position_m[2]
    n_cropped = 0
    for k, (outline, height, pose) in enumerate(_random_prisms(120, seed=12)):
        full = render_prism_depth(CAM, outline, height, pose)
        win = render_prism_window_depth(CAM, outline, height, pose)
        cam = win.camera
        u0, v0 = round(CAM.cx_px - cam.cx_px), round(CAM.cy_px - cam.cy_px)
        h, w = win.depth_m.shape
        assert (cam.width_px, cam.height_px) == (w, h)
        n_cropped += (w, h) != (CAM.width_px, CAM.height_px)
        np.testing.assert_array_equal(win.depth_m, full.depth_m[v0 : v0 + h, u0 : u0 + w])
        rest = full.depth_m.copy()
        rest[v0 : v0 + h, u0 : u0 + w] = hz
        assert np.all(rest == hz)
        world = pose.to_world(outline)
        corner = world[k % len(world)]
        out = corner - pose.to_world(np.zeros((1, 2)))[0]
        pusher = corner + 0.006 * out / np.linalg.norm(out)
        near = tuple(pose.to_world(np.zeros((1, 2)))[0])
        try:
            ref = observe_boundary(mask_pusher(full, tuple(pusher), 0.005), near)
        except PerceptionError:
            continue
        got = observe_boundary(mask_pusher(win, tuple(pusher), 0.005), near)
        np.testing.assert_array_equal(got.contour_m, ref.contour_m)
        np.testing.assert_array_equal(got.centroid_m, ref.centroid_m)
    assert n_cropped > 100


def test_render_prism_depth_pixels_on_an_edge_are_shapely_s():
    """A square whose edges lie exactly on pixel rays' top-face points: the kernel hands
    those pixels to shapely (boundary = not on the top face) and fills them in as the numpy
    reference does; left unfilled they would read as floor."""
    hz = CAM.position_m[2]
    h = 0.03
    step = (hz - h) / CAM.fx_px  # one pixel on the top face
    x0 = CAM.position_m[0] + (100 - CAM.cx_px) * step
    y0 = CAM.position_m[1] - (100 - CAM.cy_px) * step
    side = 20 * step
    sq = np.array([(x0, y0), (x0 + side, y0), (x0 + side, y0 - side), (x0, y0 - side)])
    pose = Pose2D(0.0, 0.0, 0.0)
    ref = render_prism_depth_numpy(CAM, sq, h, pose).depth_m
    new = render_prism_depth(CAM, sq, h, pose).depth_m
    np.testing.assert_array_equal(new, ref)
    cam = (*CAM.position_m[:2], CAM.cx_px, CAM.cy_px, CAM.fx_px, CAM.fy_px)
    out = np.full((CAM.height_px, CAM.width_px), hz)
    amb = _prism_kernel(sq, hz, h, cam, (0.0, 0.0, 1.0, 0.0), (90, 130, 90, 130), out, 1e-9)
    assert len(amb) >= 20  # a row or column of pixels on the edges was handed over
    v, u = amb[:, 0].astype(int), amb[:, 1].astype(int)
    assert np.all(out[v, u] == hz) and np.any(ref[v, u] < hz)


def _mask_pusher_before(img, pusher_xy_m, radius_m, margin_m=1e-3):
    """`mask_pusher` at a74eeeb (numpy camera calls)."""
    cam = img.camera
    depth = img.depth_m
    hz = floor_depth_m(cam)
    r = radius_m + margin_m
    x, y = pusher_xy_m
    corners = np.array([[x - r, y - r], [x + r, y + r]])
    uv = np.concatenate(
        [
            cam.world_to_pixel(corners[:, 0], corners[:, 1], 0.0),
            cam.world_to_pixel(corners[:, 0], corners[:, 1], 0.5 * hz),
        ]
    )
    u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + 1, cam.width_px - 1)
    v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
    v1 = min(int(np.ceil(uv[:, 1].max())) + 1, cam.height_px - 1)
    if u1 < u0 or v1 < v0:
        return img
    d = depth[v0 : v1 + 1, u0 : u1 + 1]
    vv, uu = np.nonzero(d < hz - MIN_HEIGHT_M)
    if len(vv) == 0:
        return img
    p = cam.pixel_to_world(uu + u0, vv + v0, d[vv, uu])
    hit = np.hypot(p[:, 0] - x, p[:, 1] - y) < r
    if not hit.any():
        return img
    out = depth.copy()
    out[vv[hit] + v0, uu[hit] + u0] = hz
    return DepthImage(out, cam)


def _observe_boundary_before(img, near_xy_m=None, reach_m=0.15, max_points=64):
    """`observe_boundary` at a74eeeb (numpy camera calls)."""
    cam = img.camera
    depth = img.depth_m
    h, w = depth.shape
    u0, v0, u1, v1 = 0, 0, w - 1, h - 1
    if near_xy_m is not None:
        x, y = near_xy_m
        xs, ys = np.array([x - reach_m, x + reach_m]), np.array([y + reach_m, y - reach_m])
        uv = cam.world_to_pixel(xs, ys, 0.0)
        u0, u1 = max(int(uv[0, 0]), 0), min(int(math.ceil(uv[1, 0])), w - 1)
        v0, v1 = max(int(uv[0, 1]), 0), min(int(math.ceil(uv[1, 1])), h - 1)
    win = depth[v0 : v1 + 1, u0 : u1 + 1]
    above = (np.isfinite(win) & (win < floor_depth_m(cam) - MIN_HEIGHT_M)).astype(np.uint8)
    contours, _ = cv2.findContours(above, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise PerceptionError("no object above the floor in the tracking frame", "left_view")
    c = max(contours, key=len)[:, 0, :]
    if len(c) > max_points:
        c = c[:: math.ceil(len(c) / max_points)]
    cu, cv_ = c[:, 0] + u0, c[:, 1] + v0
    contour = cam.pixel_to_world(cu, cv_, depth[cv_, cu])[:, :2]
    centre = polygon_centroid(contour) if len(contour) >= 3 else contour.mean(axis=0)
    return TrackingView(contour, centre)


def _with_pusher(img, xy, radius_m, top_m):
    """The image with a vertical cylinder (the pusher) drawn in: every pixel whose ray meets
    its top disc reads the top's depth (nearer than what was there)."""
    cam = img.camera
    depth = img.depth_m.copy()
    dz = cam.position_m[2] - top_m
    v, u = np.mgrid[0 : cam.height_px, 0 : cam.width_px]
    p = cam.pixel_to_world(u, v, np.full(u.shape, dz))
    on = np.hypot(p[..., 0] - xy[0], p[..., 1] - xy[1]) < radius_m
    depth[on] = np.minimum(depth[on], dz)
    return DepthImage(depth, cam)


def test_mask_pusher_and_observe_boundary_are_exactly_what_they_were():
    rng = np.random.default_rng(7)
    hit = 0
    for outline, height, pose in _random_prisms(60, seed=13):
        img = render_prism_depth(CAM, outline, height, pose)
        # the pusher touching the outline somewhere (or off, or out of view)
        k = int(rng.integers(len(outline)))
        edge = pose.to_world(outline[[k, (k + 1) % len(outline)]])
        mid = edge.mean(axis=0) + rng.normal(0.0, 0.01, 2)
        radius = float(rng.uniform(0.004, 0.008))
        img = _with_pusher(img, mid, radius, float(rng.uniform(0.02, 0.06)))
        xy = (float(mid[0] + rng.normal(0, 1e-4)), float(mid[1]))
        # an engine's own renderer may give float32 depths: compared in their precision
        img32 = DepthImage(img.depth_m.astype(np.float32), img.camera)
        for im in (img32, img):
            a, b = mask_pusher(im, xy, radius), _mask_pusher_before(im, xy, radius)
            assert (a is im) == (b is im)
            assert a.depth_m.dtype == b.depth_m.dtype
            np.testing.assert_array_equal(a.depth_m, b.depth_m)
        hit += a is not img
        for near in (None, (pose.x_m, pose.y_m), tuple(rng.uniform(-0.3, 0.3, 2))):
            try:
                ref = _observe_boundary_before(a, near)
            except PerceptionError:
                with pytest.raises(PerceptionError):
                    observe_boundary(a, near)
                continue
            new = observe_boundary(a, near)
            np.testing.assert_array_equal(new.contour_m, ref.contour_m)
            np.testing.assert_array_equal(new.centroid_m, ref.centroid_m)
    assert hit > 20  # the pusher was in view and masked in most images
