"""Relative pose for appearance servoing: planar 3-point RANSAC vs OpenCV's 5-point essential matrix.

Same synthetic matches for both (a textured room, 0.5 px noise, 20 % outliers, random planar poses
of the current camera around the goal camera; docs/theory.md section 3):

* topomap: ``topomap.servo.relative_pose`` — planar essential matrix, 3-point MSAC scored in both
  image coordinates, robust refinement, scale; also its RANSAC stage alone;
* baseline: ``cv2.findEssentialMat`` (5-point, RANSAC, 1 px) + ``cv2.recoverPose``.

Prints time per call, the ratio against the baseline, and accuracy (heading error, error of the
translation direction in the floor plane). Run: ``python benchmarks/bench_servo.py [--trials N]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "servo"))  # the synthetic scenes
from servo_synth import CAMERA, matches, room_points  # noqa: E402

from topomap.config import RelativePoseConfig  # noqa: E402
from topomap.motion import wrap_angle  # noqa: E402
from topomap.servo.essential import ransac_planar_essential  # noqa: E402
from topomap.servo.pose import PoseStatus  # noqa: E402
from topomap.servo.relpose import relative_pose  # noqa: E402


def scenes(trials: int, n_points: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = room_points(rng)
    out = []
    while len(out) < trials:
        goal = (rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(-math.pi, math.pi))
        rel = (rng.uniform(-2.0, 0.5), rng.uniform(-1.0, 1.0), rng.uniform(-0.5, 0.5))
        if math.hypot(rel[0], rel[1]) < 0.2:
            continue  # translation direction needs a baseline; both methods are compared where it exists
        c, s = math.cos(goal[2]), math.sin(goal[2])
        cur = (goal[0] + c * rel[0] - s * rel[1], goal[1] + s * rel[0] + c * rel[1], goal[2] + rel[2])
        cp, gp, _ = matches(pts, cur, goal, rng, noise_px=0.5, outliers=0.2, max_points=n_points)
        if len(cp) >= 30:
            out.append((cp, gp, rel))
    return out


def opencv_pose(cp, gp):
    E, _ = cv2.findEssentialMat(gp, cp, CAMERA.K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, _ = cv2.recoverPose(E, gp, cp, CAMERA.K)
    theta = math.atan2(R[0, 2], R[2, 2])  # X_cur = R X_goal + t, R ~ R_y(theta)
    c = -R.T @ t.ravel()  # current camera centre in the goal frame
    return theta, math.atan2(-c[0], c[2])  # phi = atan2(z, x) with x = c_Z, z = -c_X


def topomap_pose(cp, gp, cfg):
    rp = relative_pose(cp, gp, CAMERA, cfg)
    if rp.status is not PoseStatus.OK:
        return None
    return rp.theta, rp.phi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--points", type=int, default=200)
    args = ap.parse_args()
    cv2.setRNGSeed(0)
    data = scenes(args.trials, args.points)
    cfg = RelativePoseConfig()
    rows = {}
    for name, fn in (
        ("opencv 5-point (baseline)", lambda cp, gp: opencv_pose(cp, gp)),
        ("topomap planar 3-point", lambda cp, gp: topomap_pose(cp, gp, cfg)),
    ):
        th_err, dir_err, fails, t_total = [], [], 0, 0.0
        for cp, gp, rel in data:
            t0 = time.perf_counter()
            res = fn(cp, gp)
            t_total += time.perf_counter() - t0
            if res is None:
                fails += 1
                continue
            th_err.append(abs(math.degrees(wrap_angle(res[0] - rel[2]))))
            dir_err.append(abs(math.degrees(wrap_angle(res[1] - math.atan2(rel[1], rel[0])))))
        rows[name] = (t_total / len(data) * 1e3, np.array(th_err), np.array(dir_err), fails)
    # the RANSAC stage alone
    t0 = time.perf_counter()
    for cp, gp, _ in data:
        ransac_planar_essential(CAMERA.normalize(gp), CAMERA.normalize(cp), cfg.ransac_px / CAMERA.fx, seed=0)
    rows["topomap 3-point MSAC only"] = ((time.perf_counter() - t0) / len(data) * 1e3, None, None, 0)

    base_ms = rows["opencv 5-point (baseline)"][0]
    print(f"{len(data)} scenes, {args.points} matches max, 0.5 px noise, 20 % outliers, 320x240, 60 deg HFOV\n")
    print(f"{'method':28s} {'ms/call':>8s} {'ratio':>6s} {'heading err deg':>22s} {'direction err deg':>22s} {'fails':>5s}")
    print(f"{'':28s} {'':8s} {'':6s} {'median':>7s} {'p90':>7s} {'max':>6s} {'median':>7s} {'p90':>7s} {'max':>6s}")
    for name, (ms, th, dr, fails) in rows.items():
        if th is None:
            print(f"{name:28s} {ms:8.2f} {ms / base_ms:6.2f}")
            continue
        print(
            f"{name:28s} {ms:8.2f} {ms / base_ms:6.2f} {np.median(th):7.3f} {np.percentile(th, 90):7.3f} {th.max():6.2f}"
            f" {np.median(dr):7.3f} {np.percentile(dr, 90):7.3f} {dr.max():6.2f} {fails:5d}"
        )
    print("\nratio = time per call / baseline time per call (lower is faster)")


if __name__ == "__main__":
    main()
