"""Poses on the floor plan and the geometry of the vehicle-mounted camera (docs/theory.md section 1).

World points are ``(x, z, h)``: the floor-plan coordinates ``x, z`` [m] (x to the right, z upwards
in a plan drawing) and the height ``h`` above the floor [m]. A pose ``(x, z, theta)`` puts the
camera's optical centre at ``(x, z, camera_height_m)`` looking horizontally along heading ``theta``
(from the x axis, counter-clockwise). Camera axes follow OpenCV (X right, Y down, Z forward), so a
world point ``P`` projects to the pixel ``K (R P + t)`` with :func:`camera_from_world`'s ``R, t``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from topomap.camera import CameraIntrinsics

__all__ = ["Pose", "camera_from_world", "project_world_points", "CAMERA_HEIGHT_M"]

#: Default height of the optical centre above the floor [m].
CAMERA_HEIGHT_M = 0.8


class Pose(NamedTuple):
    """Vehicle (and camera) pose on the floor plan: ``x, z`` [m], heading ``theta`` [rad] from the x axis."""

    x: float
    z: float
    theta: float


def camera_from_world(pose: Pose | tuple[float, float, float], height_m: float = CAMERA_HEIGHT_M) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)``, (3, 3) and (3,) float64, mapping a world point ``(x, z, h)`` to camera coordinates ``R P + t``."""
    x, z, theta = (float(v) for v in pose)
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([
        [s, -c, 0.0],  # X: to the vehicle's right
        [0.0, 0.0, -1.0],  # Y: down
        [c, s, 0.0],  # Z: forward, along the heading
    ])
    t = -R @ np.array([x, z, float(height_m)])
    return R, t


def project_world_points(
    camera: CameraIntrinsics, pose: Pose | tuple[float, float, float], points: np.ndarray, height_m: float = CAMERA_HEIGHT_M
) -> np.ndarray:
    """Pixels (N, 2) float64 where world points (N, 3) ``(x, z, h)`` appear (``K [R|t]``; NaN behind the camera)."""
    R, t = camera_from_world(pose, height_m)
    P = np.asarray(points, dtype=float).reshape(-1, 3) @ R.T + t
    uv = camera.project(P)
    uv[P[:, 2] <= 0] = np.nan
    return uv
