"""Re-exports `comexp.method.scene`: the frames and units of a scene."""

from comexp.method.scene import (
    GRAVITY_M_S2,
    CameraModel,
    CameraSpec,
    DepthImage,
    FloorSpec,
    ObjectSpec,
    ObjectState,
    Point2,
    Polygon2,
    Pose2D,
    PushCommand,
    PusherSpec,
    SceneSpec,
    SimSettings,
    tilt_deg,
    wrap_angle,
)

__all__ = [
    "CameraModel",
    "CameraSpec",
    "DepthImage",
    "FloorSpec",
    "GRAVITY_M_S2",
    "ObjectSpec",
    "ObjectState",
    "Point2",
    "Polygon2",
    "Pose2D",
    "PushCommand",
    "PusherSpec",
    "SceneSpec",
    "SimSettings",
    "tilt_deg",
    "wrap_angle",
]
