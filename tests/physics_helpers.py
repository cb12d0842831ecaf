"""Helpers shared by the physics tests."""

from __future__ import annotations

from comexp.method.frames import Pose2D
from comexp.sim.protocol import push
from comexp.sim.scene import FloorSpec, SceneSpec


def nearby_starts(pose: Pose2D, n: int = 3) -> list[Pose2D]:
    """`pose` and starts 0.1-0.3 um and 1-3 urad away: a property that holds at one exact
    start only is luck of the floating point path, which differs between CPUs."""
    steps = [0.0, 1.0, -1.0, 3.0, -3.0][:n]
    return [
        Pose2D(pose.x_m + k * 1e-7, pose.y_m - k * 1e-7, pose.yaw_rad + k * 1e-6) for k in steps
    ]


def push_on_view(sim, floor, obj, pose, cmd, watch: bool, every: int = 1):
    """A push with the camera on (or off): its outcome, every frame's time, pusher and
    image sum, the still times and the state after. `every` > 1: a tracker that wants every
    `every`-th due frame (`frame_wanted`, asked ahead by a batching backend)."""
    sim.build(SceneSpec(floor, obj, initial_pose=pose))
    frames, still = [], []

    def wanted(t_s: float, driving: bool) -> bool:
        return round(t_s * 30.0) % every == 0

    out = push(
        sim,
        cmd,
        on_frame=lambda f: frames.append((f.t_s, f.pusher_xy_m, float(f.image.depth_m.sum()))),
        frame_interval_s=1.0 / 30.0 if watch else 0.0,
        on_still=still.append,
        frame_wanted=wanted if every > 1 else None,
    )
    return out, frames, still, sim.object_state()


BATCH_CASES = {  # floor, initial pose, contact, speed, push length: every way a batch stops
    "slide iso 40": (FloorSpec(0.3, 0.3), (0.0, 0.0, 0.3), (-0.05, 0.01), 0.4, 0.03),
    "sustained aniso 4": (FloorSpec(0.1, 1.0), (0.0, 0.0, 0.0), (-0.045, 0.012), 0.04, 0.03),
    "slide aniso 40": (FloorSpec(1.0, 0.1), (0.01, -0.02, 0.2), (-0.045, -0.01), 0.4, 0.03),
    "out of view": (FloorSpec(0.05, 0.05), (0.21, 0.0, 0.0), (0.165, 0.0), 0.4, 0.03),
    # a path of 115 steps: it ends in part of a chunk
    "part of a chunk": (FloorSpec(0.3, 0.3), (0.0, 0.0, 0.0), (-0.04, 0.01), 0.4, 0.0357),
}
