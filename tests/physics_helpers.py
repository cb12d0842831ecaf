"""Helpers shared by the physics tests."""

from __future__ import annotations

from comexp.method.scene import Pose2D


def nearby_starts(pose: Pose2D, n: int = 3) -> list[Pose2D]:
    """`pose` and starts 0.1-0.3 um and 1-3 urad away: a property that holds at one exact
    start only is luck of the floating point path, which differs between CPUs."""
    steps = [0.0, 1.0, -1.0, 3.0, -3.0][:n]
    return [
        Pose2D(pose.x_m + k * 1e-7, pose.y_m - k * 1e-7, pose.yaw_rad + k * 1e-6) for k in steps
    ]
