"""Appearance servoing: relative pose from two images, control laws, disturbance observer (docs/theory.md section 3).

Typical use, one call per control period::

    servo = AppearanceServo("unicycle", servo_preset("default"))
    out = servo.step(matched_cur_px, matched_goal_px, camera, dt, last_command)
    robot.apply(out.command, dt)          # out.converged, out.status, out.position_error_s, ...

The parts are usable on their own: :func:`relative_pose` (planar essential matrix, RANSAC, scaled
polar pose), the pure laws :func:`unicycle_law` / :func:`omni_law`, and the
:class:`DisturbanceObserver`. Modules: ``relpose`` (the relative pose, in stages) with its solvers
``essential``, ``homography`` and ``lm`` and its results in ``pose``; ``two_point`` (the dynamic
2-point mode); ``laws``; ``disturbance`` (the observer); ``servo`` (the loop step).
"""

from topomap.servo.disturbance import DisturbanceEstimate, DisturbanceObserver
from topomap.servo.laws import omni_law, unicycle_law
from topomap.servo.pose import PoseStatus, RelativePose, ScaleConvention
from topomap.servo.relpose import relative_pose
from topomap.servo.servo import AppearanceServo, ServoOutput, ServoStatus

__all__ = [
    "AppearanceServo",
    "ServoOutput",
    "ServoStatus",
    "PoseStatus",
    "RelativePose",
    "ScaleConvention",
    "relative_pose",
    "unicycle_law",
    "omni_law",
    "DisturbanceEstimate",
    "DisturbanceObserver",
]
