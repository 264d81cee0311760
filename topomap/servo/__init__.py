"""Appearance servoing: relative pose from two images, control laws, disturbance observer (docs/theory.md section 3).

Typical use, one call per control period::

    servo = AppearanceServo("unicycle", servo_preset("default"))
    out = servo.step(matched_cur_px, matched_goal_px, camera, dt, last_command)
    robot.apply(out.command, dt)          # out.converged, out.status, out.position_error_s, ...

The parts are usable on their own: :func:`relative_pose` (planar essential matrix, RANSAC, scaled
polar pose), the pure laws :func:`unicycle_law` / :func:`omni_law`, and the
:class:`DisturbanceObserver`.
"""

from topomap.servo.pose import PoseStatus, RelativePose, ScaleConvention
from topomap.servo.relpose import relative_pose, relative_pose_normalized
from topomap.servo.laws import LawState, aicardi_command, aicardi_coordinates, omni_law, unicycle_law
from topomap.servo.disturbance import DisturbanceEstimate, DisturbanceObserver
from topomap.servo.servo import AppearanceServo, ServoOutput, ServoStatus

__all__ = [
    "AppearanceServo",
    "ServoOutput",
    "ServoStatus",
    "PoseStatus",
    "RelativePose",
    "ScaleConvention",
    "relative_pose",
    "relative_pose_normalized",
    "LawState",
    "aicardi_coordinates",
    "aicardi_command",
    "unicycle_law",
    "omni_law",
    "DisturbanceEstimate",
    "DisturbanceObserver",
]
