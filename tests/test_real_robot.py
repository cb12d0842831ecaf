"""The real-robot path: pushes observed in the world frame with the object's poses, an outline's
region and contact candidates, and the examples of docs/real_robot.md (no simulator)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import shapely

from comexp.method.estimator import (
    EstimatorSettings,
    ObservedPush,
    WorldPush,
    estimate_com,
    estimate_com_world,
    outline_contacts,
    region_from_outline,
)
from comexp.method.frames import Pose2D

DOC = Path(__file__).resolve().parents[1] / "docs" / "real_robot.md"
PX = 0.0025  # grid spacing (m) of the frame-equivalence cases
BOX = np.array([(-0.05, -0.03), (0.05, -0.03), (0.05, 0.03), (-0.05, 0.03)])


def _world_direction(pose: Pose2D, direction) -> np.ndarray:
    return pose.to_world(direction) - pose.to_world((0.0, 0.0))


def _torque_z(P, N, G) -> float:
    """z of (P - G) x N, written out here (not the estimator's cross2): the sign of the turn."""
    return float((P[0] - G[0]) * N[1] - (P[1] - G[1]) * N[0])


# --- (a) the world-frame path is the object-frame path ------------------------------------------

# a known object-frame case: contacts off the grid's lines (no region point lies on a push line,
# so rounding in the frame changes cannot move a point from one side to the other)
G_A = np.array([0.02, -0.01])
OBJECT_PUSHES = [
    ((0.0013, -0.03), (0.0, 1.0)),
    ((-0.05, 0.0012), (1.0, 0.0)),
    ((0.0212, 0.03), (0.0, -1.0)),
    ((0.05, -0.0138), (-1.0, 0.0)),
]


def _turn_deg(P, N, G, gain_deg_per_cm: float = 4.0) -> float:
    return gain_deg_per_cm * 100.0 * _torque_z(P, N, G)


def _poses(turns_deg: list[float]) -> list[Pose2D]:
    """The object's poses before each push and after the last: far from the world origin,
    moved between pushes, turned by the pushes' turns, across yaw = -pi on the way."""
    moves = [(0.03, 0.05), (-0.07, 0.06), (-0.03, 0.05), (0.02, -0.04)]
    poses = [Pose2D(0.12, -0.07, -3.05)]
    for (dx, dy), turn in zip(moves, turns_deg, strict=True):
        p = poses[-1]
        yaw = math.remainder(p.yaw_rad + math.radians(turn), 2 * math.pi)
        poses.append(Pose2D(p.x_m + dx, p.y_m + dy, yaw))
    return poses


@pytest.mark.parametrize("method", ["paper", "magnitude"])
def test_world_path_equals_the_object_frame_path_at_a_nonzero_pose(method):
    settings = EstimatorSettings(method=method)
    local = [ObservedPush(P, N, _turn_deg(P, N, G_A)) for P, N in OBJECT_PUSHES]
    poses = _poses([push.rotation_deg for push in local])
    assert poses[0].yaw_rad < -3.0 and poses[-1].yaw_rad > 2.9  # the yaw wrapped
    # the same pushes seen from the world; the turns of the last two given by the poses after
    world = []
    for k, ((P, N), push) in enumerate(zip(OBJECT_PUSHES, local, strict=True)):
        before = poses[k]
        extra = {"rotation_deg": push.rotation_deg} if k < 2 else {"pose_after": poses[k + 1]}
        world.append(
            WorldPush(
                pose_before=before,
                contact_m=tuple(before.to_world(P)),
                direction=tuple(_world_direction(before, N)),
                **extra,
            )
        )
    result = estimate_com_world(BOX, world, pixel_m=PX, settings=settings)
    region, com = estimate_com(region_from_outline(BOX, PX), local, PX, settings)
    np.testing.assert_array_equal(result.region_m, region)
    np.testing.assert_allclose(result.com_object_m, com, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.com_world_m, poses[0].to_world(com), rtol=0, atol=1e-12)
    assert result.first_pose == poses[0]
    for seen, given in zip(result.pushes, local, strict=True):  # the conversion itself
        np.testing.assert_allclose(seen.contact_m, given.contact_m, atol=1e-12)
        np.testing.assert_allclose(seen.direction, given.direction, atol=1e-12)
        assert seen.rotation_deg == pytest.approx(given.rotation_deg, abs=1e-9)
    # and the estimate is the known case's: the region kept the true CoM
    assert np.min(np.linalg.norm(region - G_A, axis=1)) < PX


def test_turn_from_poses_is_wrapped_and_ccw_positive():
    """yaw 3.10 -> -3.10 rad is a small CCW turn (+4.8 deg), not -355 deg."""
    push = WorldPush((0, 0, 3.10), (0.05, 0.0), (-1.0, 0.0), pose_after=(0.0, 0.0, -3.10))
    assert push.turn_deg == pytest.approx(math.degrees(2 * math.pi - 6.2))
    assert WorldPush((0, 0, 0.2), (0.05, 0.0), (-1, 0), pose_after=(0, 0, 0.1)).turn_deg < 0
    # a measured turn is taken as it is, beyond half a turn too
    assert WorldPush((0, 0, 0), (0.05, 0.0), (-1, 0), rotation_deg=250.0).turn_deg == 250.0


def test_world_push_normalises_and_checks_its_inputs():
    push = WorldPush(Pose2D(0.1, 0.2, 0.3), [0.05, 0.0], (-3.0, 4.0), rotation_deg=1.5)
    assert push.direction == pytest.approx((-0.6, 0.8))
    assert isinstance(push.pose_before, Pose2D)
    with pytest.raises(ValueError, match="exactly one"):
        WorldPush((0, 0, 0), (0.05, 0.0), (-1, 0))
    with pytest.raises(ValueError, match="exactly one"):
        WorldPush((0, 0, 0), (0.05, 0.0), (-1, 0), rotation_deg=1.0, pose_after=(0, 0, 0))
    with pytest.raises(ValueError, match="non-zero"):
        WorldPush((0, 0, 0), (0.05, 0.0), (0, 0), rotation_deg=1.0)


def test_frame_mistakes_are_refused():
    pose = Pose2D(0.3, -0.2, 1.2)
    push = WorldPush(pose, tuple(pose.to_world((0.0, -0.03))), (0.0, 1.0), rotation_deg=-3.0)
    with pytest.raises(ValueError, match="centroid"):
        estimate_com_world(BOX + [0.01, 0.0], [push], pixel_m=PX)
    with pytest.raises(ValueError, match="at least one push"):
        estimate_com_world(BOX, [], pixel_m=PX)
    # the yaw given in degrees: the contact lands ~half a metre off the outline
    deg = WorldPush((0.3, -0.2, 68.75), push.contact_m, push.direction, rotation_deg=-3.0)
    with pytest.raises(ValueError, match="push 1: .* cm from the outline"):
        estimate_com_world(BOX, [push, deg], pixel_m=PX)
    estimate_com_world(BOX, [push, deg], pixel_m=PX, max_contact_offset_m=None)  # unchecked


# --- the outline's helpers -----------------------------------------------------------------------


def test_outline_contacts_lie_on_the_edges_with_inward_normals_away_from_corners():
    L = np.array([(0, 0), (0.08, 0), (0.08, 0.03), (0.03, 0.03), (0.03, 0.07), (0, 0.07)])
    poly = shapely.Polygon(L)
    P, N = outline_contacts(L, spacing_m=0.005, corner_clearance_m=0.006)
    assert len(P) > 20
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0)
    assert shapely.distance(shapely.LinearRing(L), shapely.points(P)).max() < 1e-12
    assert shapely.contains(poly, shapely.points(P + 0.001 * N)).all()  # inward
    assert not shapely.contains(poly, shapely.points(P - 0.001 * N)).any()
    corners = L  # every vertex turns by 90 deg, the reflex one at (0.03, 0.03) included
    assert np.linalg.norm(P[:, None] - corners[None], axis=2).min() >= 0.006
    gaps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert gaps.min() == pytest.approx(0.005)  # spacing along an edge
    # the vertex order does not matter
    P2, N2 = outline_contacts(L[::-1], spacing_m=0.005, corner_clearance_m=0.006)
    assert {tuple(p) for p in np.round(P2, 9)} == {tuple(p) for p in np.round(P, 9)}
    # a fine polygon of a disc has no corners: contacts all the way round
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    disc = 0.04 * np.column_stack([np.cos(t), np.sin(t)])
    Pd, Nd = outline_contacts(disc, spacing_m=0.005)
    assert len(Pd) == int(shapely.LinearRing(disc).length // 0.005)
    assert (np.einsum("ij,ij->i", Nd, -Pd / np.linalg.norm(Pd, axis=1, keepdims=True)) > 0.99).all()


def test_region_from_outline_is_the_convex_hull_grid():
    U = np.array([(-0.04, -0.03), (0.04, -0.03), (0.04, 0.03), (0.02, 0.03), (0.02, -0.01)])
    U = np.vstack([U, [(-0.02, -0.01), (-0.02, 0.03), (-0.04, 0.03)]])
    region = region_from_outline(U, 0.002)
    hull = shapely.Polygon(U).convex_hull
    # one point per grid cell of the hull (points on its boundary excluded), not of the U
    assert len(region) == pytest.approx(hull.area / 0.002**2, rel=0.1)
    assert len(region) > 1.3 * shapely.Polygon(U).area / 0.002**2
    assert ((region[:, 0] > -0.02) & (region[:, 0] < 0.02) & (region[:, 1] > 0.0)).any()  # notch
    np.testing.assert_allclose(region / 0.002, np.round(region / 0.002), atol=1e-9)  # grid


# --- (b) end to end: an outline, pushes observed in the world, the CoM ---------------------------

G_B = np.array([0.022, -0.011])  # the true CoM, object frame of BOX
# where the pushes go (the nearest contact candidates): lever arms of both signs about G_B
TARGETS = [(0.0, -0.03), (-0.05, -0.02), (0.04, -0.03), (0.05, 0.005), (0.01, 0.03), (-0.05, 0.01)]


def _observed_episode(gain_deg_per_cm: float) -> tuple[list[WorldPush], list[float]]:
    """A stand-in robot: each push turns the object about its CoM by gain x the torque arm
    (sign = the torque's, CCW positive) and slides the CoM 3 cm along the push, the poses
    rounded as a tracker would report them (0.1 mm, 1 mrad)."""
    contacts, normals = outline_contacts(BOX, spacing_m=0.005)
    pose = Pose2D(0.10, 0.05, 0.5)
    pushes, arms = [], []
    for target in TARGETS:
        j = int(np.argmin(np.linalg.norm(contacts - target, axis=1)))
        P_w = pose.to_world(contacts[j])
        N_w = _world_direction(pose, normals[j])
        G_w = pose.to_world(G_B)
        arm = _torque_z(P_w, N_w, G_w)  # computed in the world: independent of the conversion
        yaw = pose.yaw_rad + math.radians(gain_deg_per_cm * 100.0 * arm)
        origin = G_w + 0.03 * N_w - Pose2D(0.0, 0.0, yaw).to_world(G_B)
        after = Pose2D(round(origin[0], 4), round(origin[1], 4), round(yaw, 3))
        pushes.append(WorldPush(pose, tuple(P_w), tuple(N_w), pose_after=after))
        arms.append(arm)
        pose = after
    return pushes, arms


# bounds from the measured errors (mm), with about twice that margin: paper 3.11 (gain 1),
# 2.31 (gain 4); magnitude 0.48, 0.52; the region keeps 117, 81 of 851 points
@pytest.mark.parametrize("gain_deg_per_cm", [1.0, 4.0])
def test_end_to_end_rectangle_lands_near_the_true_com(gain_deg_per_cm):
    pushes, arms = _observed_episode(gain_deg_per_cm)
    assert min(arms) < -0.005 and max(arms) > 0.005, "lever arms of both signs"
    assert all(
        math.copysign(1, p.turn_deg) == math.copysign(1, a)
        for p, a in zip(pushes, arms, strict=True)
    )
    paper = estimate_com_world(BOX, pushes, pixel_m=0.0027)
    assert np.linalg.norm(paper.com_object_m - G_B) < 0.006
    assert np.min(np.linalg.norm(paper.region_m - G_B, axis=1)) < 0.0027  # G kept
    assert len(paper.region_m) < 0.25 * len(region_from_outline(BOX, 0.0027))
    G_world = pushes[0].pose_before.to_world(G_B)
    assert np.linalg.norm(paper.com_world_m - G_world) < 0.006
    mag = estimate_com_world(BOX, pushes, 0.0027, EstimatorSettings(method="magnitude"))
    assert np.linalg.norm(mag.com_object_m - G_B) < 0.0015


# --- (c) the documented examples run -------------------------------------------------------------


def _doc_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_documented_examples_run(capsys):
    blocks = _doc_blocks()
    assert len(blocks) == 4, (
        "the world-frame example, Algorithm 1 in the loop, object frame, recorded pushes"
    )
    scope: dict = {}
    for block in blocks[:2]:  # in order, in one scope, as a reader would paste them
        exec(compile(block, str(DOC), "exec"), scope)  # noqa: S102 - our own document
    result = scope["result"]
    # the example's log was made with the CoM at (2.2, -1.1) cm, as the page says
    assert "(2.2, -1.1) cm" in DOC.read_text()
    assert np.linalg.norm(result.com_object_m - [0.022, -0.011]) < 0.006
    np.testing.assert_allclose(result.com_world_m, result.first_pose.to_world(result.com_object_m))
    # it says the first push turned the object clockwise: CoM right of the push line
    first = result.pushes[0]
    assert first.rotation_deg < 0 and first.contact_m[0] < 0.022
    assert first.direction == pytest.approx((0.0, 1.0), abs=2e-3)
    assert scope["estimator"].region_px < len(region_from_outline(scope["outline_m"], 0.0027))
    assert "CoM, object frame" in capsys.readouterr().out


def test_the_object_frame_example_runs():
    """`estimate_com` on pushes already in the object frame (the page's own region grid)
    gives a sensible answer."""
    (block,) = [b for b in _doc_blocks() if "ObservedPush(" in b]
    scope: dict = {}
    exec(compile(block, str(DOC), "exec"), scope)  # noqa: S102 - our own document
    region, estimate = scope["region"], scope["estimate_m"]
    # a CW rotation from a +x push at y = 1 cm puts the CoM below that line; the small
    # rotation of the +y push at x = 0 keeps the 10 px band around x = 0
    assert len(region) > 0
    assert np.all(region[:, 1] < 0.01)
    assert np.all(np.abs(region[:, 0]) <= 10 * 0.0027 + 1e-9)
    assert np.allclose(estimate, region.mean(axis=0))


def test_the_recorded_pushes_example_runs(capsys):
    """The page's `comexp-real` example from Python: the estimators and the replay on the
    shared recorded pushes (skipped where they are not)."""
    from test_real_logs import SHARED

    if not (SHARED / "abs").is_dir():
        pytest.skip(f"the shared recorded pushes are not at {SHARED} (set COMEXP_REAL_DATA)")
    (block,) = [b for b in _doc_blocks() if "read_pushes(" in b]
    block = block.replace('"../shared/data/mit-push-train"', repr(str(SHARED)))
    scope: dict = {}
    exec(compile(block, str(DOC), "exec"), scope)  # noqa: S102 - our own document
    out = capsys.readouterr().out
    assert out.count("\n") == 6 and "turn sign right on 45 of 45" in out
    assert 0.12 < float(out.splitlines()[-1]) < 0.25  # the pusher's friction from the force
