"""Synthetic scenes for the servo tests: 3D points in a room, projected into cameras on a vehicle.

World: floor plan (x, z) with the THESIS.md section 1 pose convention (x, z, theta), heights above
the floor. The camera sits on the vehicle's rotation axis at ``CAM_HEIGHT`` with a horizontal optical
axis (OpenCV axes: X right, Y down, Z forward).
"""

from __future__ import annotations

import math

import numpy as np

from topomap.camera import CameraIntrinsics

CAM_HEIGHT = 0.7  # [m]
CAMERA = CameraIntrinsics.default(320, 240, 60.0)


def room_points(rng: np.random.Generator, n_wall=1600, n_floor=900, n_ceiling=300, half=(5.0, 4.0), height=2.5):
    """(M, 3) points (x, z, height): textured walls of a box room, its floor and ceiling."""
    hx, hz = half
    pts = []
    per = n_wall // 4
    for side in range(4):
        t = rng.uniform(-1, 1, per)
        h = rng.uniform(0.0, height, per)
        if side == 0:
            pts.append(np.column_stack([np.full(per, hx), t * hz, h]))
        elif side == 1:
            pts.append(np.column_stack([np.full(per, -hx), t * hz, h]))
        elif side == 2:
            pts.append(np.column_stack([t * hx, np.full(per, hz), h]))
        else:
            pts.append(np.column_stack([t * hx, np.full(per, -hz), h]))
    pts.append(np.column_stack([rng.uniform(-hx, hx, n_floor), rng.uniform(-hz, hz, n_floor), np.zeros(n_floor)]))
    pts.append(np.column_stack([rng.uniform(-hx, hx, n_ceiling), rng.uniform(-hz, hz, n_ceiling), np.full(n_ceiling, height)]))
    return np.vstack(pts)


def to_camera(points: np.ndarray, pose, cam_height: float = CAM_HEIGHT) -> np.ndarray:
    """World points (M, 3) -> camera-frame points (M, 3) for a vehicle at ``pose = (x, z, theta)``."""
    x, z, th = pose
    dx, dz = points[:, 0] - x, points[:, 1] - z
    fwd = dx * math.cos(th) + dz * math.sin(th)
    right = dx * math.sin(th) - dz * math.cos(th)
    return np.column_stack([right, cam_height - points[:, 2], fwd])


def project(points: np.ndarray, pose, camera: CameraIntrinsics = CAMERA, cam_height: float = CAM_HEIGHT):
    """Pixels (M, 2) and a visibility mask (in front, inside the image)."""
    P = to_camera(points, pose, cam_height)
    vis = P[:, 2] > 0.2
    px = np.full((len(P), 2), np.nan)
    px[vis] = camera.project(P[vis])
    vis &= (px[:, 0] >= 0) & (px[:, 0] <= camera.width - 1) & (px[:, 1] >= 0) & (px[:, 1] <= camera.height - 1)
    return px, vis


def relative(cur, goal):
    """Pose of ``cur`` in the frame of ``goal``: (x forward, z left, theta)."""
    dx, dz = cur[0] - goal[0], cur[1] - goal[1]
    c, s = math.cos(goal[2]), math.sin(goal[2])
    th = (cur[2] - goal[2] + math.pi) % (2 * math.pi) - math.pi
    return (c * dx + s * dz, -s * dx + c * dz, th)


def matches(points, cur, goal, rng, *, noise_px=0.5, outliers=0.0, max_points=300, camera=CAMERA, cam_height=CAM_HEIGHT):
    """Matched pixels (cur, goal) of the points both cameras see, with noise and outliers.

    Returns ``(cur_px, goal_px, true_idx)``; ``true_idx`` indexes ``points`` (-1 for an outlier).
    """
    pc, vc = project(points, cur, camera, cam_height)
    pg, vg = project(points, goal, camera, cam_height)
    idx = np.flatnonzero(vc & vg)
    if len(idx) > max_points:
        idx = np.sort(rng.choice(idx, max_points, replace=False))
    cur_px = pc[idx] + rng.normal(0, noise_px, (len(idx), 2))
    goal_px = pg[idx] + rng.normal(0, noise_px, (len(idx), 2))
    true_idx = idx.copy()
    n_out = int(round(outliers * len(idx)))
    if n_out:
        k = rng.choice(len(idx), n_out, replace=False)
        cur_px[k] = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (n_out, 2))
        true_idx[k] = -1
    return cur_px, goal_px, true_idx


def median_goal_depth(points, goal, idx, cam_height=CAM_HEIGHT) -> float:
    """The median-depth scale lambda of a set of points seen from the goal."""
    return float(np.median(to_camera(points[idx], goal, cam_height)[:, 2]))
