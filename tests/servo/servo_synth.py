"""Synthetic scenes for the servo tests: 3D points in a room, projected into cameras on a vehicle.

World: floor plan (x, z) with the docs/theory.md section 1 pose convention (x, z, theta), heights above
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


# ----------------------------------------------------------------------------- kinematics
def integrate(pose, u, dt: float):
    """Exact pose after ``dt`` under constant effective input ``u = (v_f, v_h, omega)``:
    ``xi' = G(theta) u`` (docs/theory.md eq. 1.7), the SE(2) exponential."""
    x, z, th = pose
    v_f, v_h, w = u
    a = w * dt
    if abs(a) < 1e-9:
        dxb, dzb = v_f * dt, v_h * dt
    else:
        s, c1 = math.sin(a), 1.0 - math.cos(a)
        dxb, dzb = (s * v_f - c1 * v_h) / w, (c1 * v_f + s * v_h) / w
    c, s = math.cos(th), math.sin(th)
    return (x + c * dxb - s * dzb, z + s * dxb + c * dzb, th + a)


class Disturbance:
    """Unknown input disturbance of realistic size: ``u_eff = (1 - slip) u + d(t)``.

    ``bias`` (d_f, d_h, d_omega) constant; ``sin_amp`` amplitudes at ``sin_hz``; ``slip`` fraction lost
    on every channel; ``walk`` random-walk intensities per channel [unit/sqrt(s)], seeded, reflected
    at ``walk_max``.
    """

    def __init__(self, bias=(0.0, 0.0, 0.0), sin_amp=(0.0, 0.0, 0.0), sin_hz=0.1, slip=0.0, walk=(0.0, 0.0, 0.0),
                 walk_max=(0.03, 0.03, 0.15), seed=0):
        self.bias = np.asarray(bias, float)
        self.sin_amp = np.asarray(sin_amp, float)
        self.sin_hz = sin_hz
        self.slip = slip
        self.walk = np.asarray(walk, float)
        self.walk_max = np.asarray(walk_max, float)
        self.rng = np.random.default_rng(seed)
        self.rw = np.zeros(3)

    def advance(self, dt):
        if self.walk.any():  # a random walk kept within realistic bounds (reflecting at +-walk_max)
            self.rw = self.rw + self.rng.normal(0, 1, 3) * self.walk * math.sqrt(dt)
            self.rw = np.where(np.abs(self.rw) > self.walk_max, np.sign(self.rw) * (2 * self.walk_max - np.abs(self.rw)), self.rw)

    def effective(self, u, t, unicycle: bool):
        d = self.bias + self.sin_amp * math.sin(2 * math.pi * self.sin_hz * t) + self.rw
        out = (1.0 - self.slip) * np.asarray(u, float) + d
        if unicycle:
            out[1] = 0.0
        return out


#: Disturbance presets of realistic size (task: d_omega ~0.15 rad/s, slip 15 %, forward bias 0.04 m/s).
DISTURBANCES = {
    "none": dict(),
    "omega": dict(bias=(0.0, 0.0, 0.15)),
    "bias": dict(bias=(0.04, 0.03, 0.15)),
    "sinusoidal": dict(sin_amp=(0.02, 0.02, 0.15), sin_hz=0.05),
    "slip": dict(slip=0.15),
    "walk": dict(walk=(0.01, 0.01, 0.05)),
    "harsh": dict(bias=(0.04, 0.03, 0.15), sin_amp=(0.01, 0.01, 0.05), sin_hz=0.05, slip=0.15, walk=(0.005, 0.005, 0.02)),
}


def disturbance(name: str, seed: int = 0) -> Disturbance:
    return Disturbance(**DISTURBANCES[name], seed=seed)


def drive(pose, u_cmd, dist: Disturbance, t: float, dt: float, unicycle: bool, substeps: int = 5):
    """Apply the command for ``dt`` with the disturbance sampled at ``substeps`` instants."""
    h = dt / substeps
    for k in range(substeps):
        dist.advance(h)
        pose = integrate(pose, dist.effective(u_cmd, t + k * h, unicycle), h)
    return pose


def servo_episode(servo, points, start, goal, dist: Disturbance, rng, *, dt=0.1, t_max=60.0, noise_px=0.5,
                  outliers=0.1, max_points=150, stop_when_converged=False, camera=CAMERA):
    """Closed loop from images only: project the points into the current and goal cameras, add pixel
    noise and outliers, run ``servo.step``, drive the vehicle with the disturbance. Returns the final
    pose in the goal frame and the list of outputs."""
    from topomap.motion import VehicleKind

    pose, last, t, outs = start, None, 0.0, []
    unicycle = servo.vehicle is VehicleKind.UNICYCLE
    while t < t_max:
        cur_px, goal_px, _ = matches(points, pose, goal, rng, noise_px=noise_px, outliers=outliers,
                                     max_points=max_points, camera=camera)
        out = servo.step(cur_px, goal_px, camera, dt, last)
        outs.append(out)
        if stop_when_converged and out.converged:
            break
        pose = drive(pose, out.command.as_tuple(), dist, t, dt, unicycle)
        last, t = out.command, t + dt
    return relative(pose, goal), outs


# ---------------------------------------------------------------------------- one scene for the relative-pose tests
POINTS = room_points(np.random.default_rng(42))
GOAL = (0.4, -0.2, 0.3)


def in_world(rel, goal=GOAL):
    """A pose given in the goal frame (x forward, z left, theta) -> world."""
    c, s = math.cos(goal[2]), math.sin(goal[2])
    return (goal[0] + c * rel[0] - s * rel[1], goal[1] + s * rel[0] + c * rel[1], goal[2] + rel[2])


def normalized_pair(rel, rng, noise_px=0.0, **kw):
    """Normalised matches (current, goal, indices of the points) of POINTS seen from ``in_world(rel)`` and GOAL."""
    cur = in_world(rel)
    cp, gp, idx = matches(POINTS, cur, GOAL, rng, noise_px=noise_px, **kw)
    return CAMERA.normalize(cp), CAMERA.normalize(gp), idx
