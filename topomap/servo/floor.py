"""The current camera's planar pose w.r.t. a keyframe, from the floor's pixels (docs/servo.md, "The floor, aligned").

Why: the relative pose from matched features (:mod:`topomap.servo.relpose`) cannot tell a sideways
step from a turn when every matched point is about as far away (the bas-relief ambiguity): looking
down a corridor, features match on the far wall and the far floor only, and a robot 0.3 m beside
its goal measured 0.0-0.1 m for seconds (fresh world 289 ep 8). The floor near the camera rarely
yields matched features, but its pixels are there: with the camera height known, the floor is a
plane of known place, so the keyframe's floor pixels map to the current image by a homography
fixed by the planar pose alone. Aligning them directly (normalised cross-correlation, no features)
measures the sideways offset from the near floor, where it moves the image most.

Conventions as :mod:`topomap.servo.pose`: ``X_cur = R_y(theta) (X_goal - c)``; the pose is reported
as a vehicle pose in the goal frame, ``x = c_Z`` forward, ``z = -c_X`` left, both in camera heights.

The search is hand-written because OpenCV's ECC / Lucas-Kanade align eight-parameter homographies
from a nearby start; here three parameters, a wide start and a repetitive floor ask for a grid first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.errors import ShapeError
from topomap.motion import wrap_angle

__all__ = ["FloorAlignment", "FloorAligner"]

NEAR_H = 5.0  # floor pixels closer than this many camera heights: the near floor carries the sideways offset
BLUR_PX = 1.5  # per-pixel noise and JPEG blocks are not the floor's texture
MIN_TEXTURE = 4.0  # grey-level spread of the keyframe's near floor below which it is plain paint: nothing to align
MIN_PIXELS = 400  # aligned floor samples below which the overlap is too small to judge
GRID_STEP_PX = 4  # sampling stride of the coarse grid search; the refinement samples every other pixel
PEAK_STEP_H = 0.1  # the peak's sharpness is judged against poses this far aside and ahead [camera heights]
TILE_COLUMNS, TILE_ROWS = 8, 2  # the near floor is scored per tile: walls and objects spoil some tiles, not the score
MIN_TILE_SAMPLES = 12  # coarse-grid samples a tile needs in view to count
MIN_TILES = 4  # textured tiles in view below which the floor is not judged
KEEP_TILES = 0.75  # the better fraction of the tiles in view that scores a pose
TRACK_REACH_H = 0.125  # tracking (``align(near=...)``): a docking robot moves a few cm per period [camera heights]
TRACK_TURN_RAD = math.radians(2.0)  # the heading predicted from the command, give or take a disturbed period


@dataclass(frozen=True)
class FloorAlignment:
    """A floor alignment: the current camera's planar pose in the goal camera's frame.

    ``x_h`` forward, ``z_h`` to the left [camera heights]; ``theta`` [rad] counter-clockwise;
    ``ncc``: the alignment's score, the mean normalised cross-correlation of the better
    ``KEEP_TILES`` of the floor's tiles (1 = identical); ``peak``: by
    how much it exceeds the best of the poses ``PEAK_STEP_H`` aside and ahead (a flat peak, as on
    a plain floor, measures nothing); ``pixels``: floor samples compared."""

    x_h: float
    z_h: float
    theta: float
    ncc: float
    peak: float
    pixels: int

    @property
    def distance_h(self) -> float:
        """Distance from the goal camera [camera heights]."""
        return math.hypot(self.x_h, self.z_h)

    def confident(self, min_ncc: float, min_peak: float) -> bool:
        """Whether the floor was aligned well enough to measure the pose."""
        return self.ncc >= min_ncc and self.peak >= min_peak and self.pixels >= MIN_PIXELS


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(image.astype(np.float32), (0, 0), BLUR_PX)


class FloorAligner:
    """Aligns a goal keyframe's near floor with current images.

    ``goal_image``: (H, W) or (H, W, 3) uint8 keyframe as ``goal_camera`` saw it (horizontal optical
    axis at the camera height, as the servo assumes). :attr:`textured` says whether its near floor
    has texture to align; :meth:`align` returns None where it has not or the overlap is too small."""

    def __init__(self, goal_image: np.ndarray, goal_camera: CameraIntrinsics):
        if goal_image.ndim not in (2, 3) or goal_image.dtype != np.uint8:
            raise ShapeError(f"goal_image must be an (H, W) or (H, W, 3) uint8 image, got {goal_image.shape} {goal_image.dtype}")
        g = _grey(goal_image)
        h, w = g.shape
        sx, sy = w / goal_camera.width, h / goal_camera.height  # a keyframe stored at another size than its intrinsics
        fx, fy, cx, cy = goal_camera.fx * sx, goal_camera.fy * sy, goal_camera.cx * sx, goal_camera.cy * sy
        y0 = min(int(math.ceil(cy + fy / NEAR_H)), h)
        self._samples, self._onehot, self._textured_tiles = {}, {}, {}
        for step in (GRID_STEP_PX, GRID_STEP_PX // 2):
            ys, xs = np.mgrid[y0:h:step, 0:w:step]
            vals = g[ys, xs].ravel().astype(np.float64)
            # tiles: TILE_COLUMNS across the width, TILE_ROWS from the near-floor line down
            col = np.minimum(xs.ravel() * TILE_COLUMNS // w, TILE_COLUMNS - 1)
            row = np.minimum((ys.ravel() - y0) * TILE_ROWS // max(h - y0, 1), TILE_ROWS - 1)
            tiles = row * TILE_COLUMNS + col
            n_tiles = TILE_ROWS * TILE_COLUMNS
            onehot = np.zeros((vals.size, n_tiles))
            onehot[np.arange(vals.size), tiles] = 1.0
            spread = np.array([vals[tiles == t].std() if np.any(tiles == t) else 0.0 for t in range(n_tiles)])
            Z = 1.0 / ((ys - cy) / fy).ravel()  # each sample on the floor, in camera heights from the keyframe
            self._samples[step] = (((xs - cx) / fx).ravel() * Z, Z, vals)
            self._onehot[step] = onehot
            self._textured_tiles[step] = spread >= MIN_TEXTURE
        self.textured = int(self._textured_tiles[GRID_STEP_PX].sum()) >= MIN_TILES

    def _ncc(self, poses: np.ndarray, cur: np.ndarray, camera: CameraIntrinsics, step: int) -> tuple[np.ndarray, np.ndarray]:
        """The floor's agreement for each row ``(theta, c_X, c_Z)`` of ``poses`` (K, 3): ``(score (K,),
        pixels compared (K,))``. The score is the mean normalised cross-correlation of the better
        ``KEEP_TILES`` of the keyframe's textured floor tiles in view: near a wall the bottom corners
        show the wall, which no floor pose aligns, and a robot beside its goal sees more of it."""
        X, Z, vals = self._samples[step]
        th, cX, cZ = poses[:, :1], poses[:, 1:2], poses[:, 2:3]
        dx, dz = X[None] - cX, Z[None] - cZ
        c, s = np.cos(th), np.sin(th)
        xc, zc = c * dx + s * dz, -s * dx + c * dz  # R_y(theta) (X - c)
        ok = zc > 0.3
        zc = np.where(ok, zc, 1.0)
        u = camera.fx * xc / zc + camera.cx
        v = camera.fy / zc + camera.cy
        hh, ww = cur.shape
        ok &= (u >= 0) & (u <= ww - 1) & (v >= 0) & (v <= hh - 1)
        b = cv2.remap(cur, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        w = ok.astype(np.float64)
        a = vals[None]
        onehot = self._onehot[step]  # (N, T)
        n = w @ onehot
        sa, sb = (w * a) @ onehot, (w * b) @ onehot
        saa, sbb, sab = (w * a * a) @ onehot, (w * b * b) @ onehot, (w * a * b) @ onehot
        nn = np.maximum(n, 1.0)
        cov = sab - sa * sb / nn
        var_a, var_b = np.maximum(saa - sa * sa / nn, 0.0), np.maximum(sbb - sb * sb / nn, 0.0)
        var = var_a * var_b
        # a plain patch (of the current image, or of the keyframe where the current one overlaps it)
        # agrees with nothing: its variance is rounding error, and so is the covariance, whose ratio
        # read millions on plain office floors
        flat = np.minimum(var_a, var_b) < (MIN_TEXTURE / 4.0) ** 2 * nn
        ncc = np.where(flat, 0.0, np.clip(cov / np.sqrt(np.where(flat, 1.0, var)), -1.0, 1.0))
        valid = (n >= MIN_TILE_SAMPLES * (GRID_STEP_PX / step) ** 2) & self._textured_tiles[step][None]
        ncc = np.where(valid, ncc, -np.inf)
        k = valid.sum(axis=1)
        best = -np.sort(-ncc, axis=1)  # descending; invalid tiles last
        half = np.maximum(np.ceil(KEEP_TILES * k).astype(int), 1)
        cum = np.cumsum(np.where(np.isfinite(best), best, 0.0), axis=1)
        score = np.where(k >= MIN_TILES, cum[np.arange(len(poses)), half - 1] / half, -1.0)
        return score, ok.sum(axis=1)

    def align(self, image: np.ndarray, camera: CameraIntrinsics, theta0: float = 0.0, *,
              reach_h: float = 0.75, turn_rad: float = math.radians(4.0),
              near: FloorAlignment | None = None) -> FloorAlignment | None:
        """The pose that aligns the keyframe's near floor with ``image`` (taken with ``camera``):
        a grid within ``reach_h`` camera heights of the goal and ``turn_rad`` of ``theta0`` (the
        servo's heading), then a Nelder-Mead refinement. ``near``: a recent alignment (tracking a
        docking robot) — the grid then spans only ``TRACK_REACH_H`` and ``TRACK_TURN_RAD`` around it,
        at about a fifth of the cost (the refinement is the same). None on a plain floor, with too little overlap, or where the
        best pose turned beyond ``turn_rad`` of ``theta0`` (not this floor)."""
        if not self.textured:
            return None
        cur = _grey(image)
        if cur.shape != (camera.height, camera.width):
            raise ShapeError(f"image is {cur.shape[1]}x{cur.shape[0]}, the camera {camera.width}x{camera.height}")
        if near is None:
            ths = theta0 + np.linspace(-turn_rad, turn_rad, 5)
            lat = np.arange(-reach_h, reach_h + 1e-9, 0.0625)
            fwd = np.arange(-reach_h, reach_h + 1e-9, 0.125)
        else:  # (cX, cZ) = (-z_h, x_h): the grid's axes are the keyframe camera's
            ths = near.theta + np.linspace(-TRACK_TURN_RAD, TRACK_TURN_RAD, 3)
            lat = -near.z_h + np.arange(-TRACK_REACH_H, TRACK_REACH_H + 1e-9, 0.0625)
            fwd = near.x_h + np.arange(-TRACK_REACH_H, TRACK_REACH_H + 1e-9, 0.0625)
        grid = np.array(np.meshgrid(ths, lat, fwd, indexing="ij")).reshape(3, -1).T
        best = None
        for chunk in np.array_split(grid, max(1, len(grid) // 400)):
            ncc, _ = self._ncc(chunk, cur, camera, GRID_STEP_PX)
            k = int(np.argmax(ncc))
            if best is None or ncc[k] > best[0]:
                best = (float(ncc[k]), chunk[k])
        if best is None or not best[0] > -1.0:
            return None
        from scipy.optimize import minimize  # scipy is heavy to import; only aligning needs it

        fine = GRID_STEP_PX // 2
        start = best[1]
        simplex = start + np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.03, 0], [0, 0, 0.06]])
        res = minimize(lambda p: -float(self._ncc(p[None], cur, camera, fine)[0][0]), start, method="Nelder-Mead",
                       options=dict(xatol=2e-3, fatol=1e-4, maxiter=200, initial_simplex=simplex))
        p = res.x
        ncc, n = self._ncc(p[None], cur, camera, fine)
        th, cX, cZ = (float(v) for v in p)
        if abs(wrap_angle(th - theta0)) > turn_rad:
            return None  # the features measure the heading well (the sideways offset is what they miss): a floor turned further is not this floor
        aside = np.array([[th, cX + dX, cZ + dZ] for dX, dZ in ((PEAK_STEP_H, 0), (-PEAK_STEP_H, 0), (0, PEAK_STEP_H), (0, -PEAK_STEP_H))])
        near, _ = self._ncc(aside, cur, camera, fine)
        return FloorAlignment(x_h=cZ, z_h=-cX, theta=th, ncc=float(ncc[0]), peak=float(ncc[0] - near.max()), pixels=int(n[0]))
