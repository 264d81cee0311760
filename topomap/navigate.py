"""The navigation loop: localize -> plan -> servo toward each subgoal -> switch -> re-localize when lost.

This is the only control loop of topomap (docs/theory.md section 4). It sees what a robot sees: its
camera's images and intrinsics, the map, and the commands it sends. It never reads a pose — the
robot it drives is anything with ``camera``, ``render()`` and ``apply(command, dt)``
(:class:`RobotLike`; the simulator's ``sim.robot`` or a real robot driver).

Route following. The route is a chain of node subgoals (:class:`~topomap.plan.Planner`). Each control
period the current image is matched to the current subgoal's keyframe and the appearance servo turns
the matches into a command (:class:`~topomap.servo.servo.AppearanceServo`). An intermediate subgoal
counts as reached — and the next node becomes the target — when

* the servo's estimated distance to it falls below ``switch_distance_m``, or the robot has driven
  past it (its estimated position crossed the subgoal camera's plane, from the side it came) — with the heading
  within ``switch_heading_deg`` of the subgoal's (at the teach run's corners the next node is out of
  view until the robot has turned), or
* the next node of the route verifies with more inliers than the current one (and at least
  ``switch_min_inliers``): it is the better target now;

and in no case while the floor, with the camera height known, measures the subgoal farther than
``switch_floor_max_m`` (a view down a long corridor: the subgoal's scale from its neighbours can be
several times too small, and the nodes behind it match as well as it does), nor, on a taught chain
walked backwards, before the floor has been read (at most ``SWITCH_FLOOR_PERIODS`` periods).

The final goal is reached when the servo reports convergence for ``settle_steps`` periods in a row,
or when, aligned and close, it stops making progress (``settle_*`` in
:class:`~topomap.config.NavigateConfig`: a docked unicycle cannot remove a small sideways offset) —
and in both cases only if the image agrees (:class:`~topomap.agreement.GoalAgreement`): the verified
matches with the goal keyframe have moved less than ``arrive_image_error`` of the image width. Facing
a single wall the planar relative pose is ambiguous, so the pose estimate alone cannot certify arrival.
With the camera height known, the floor must agree too: the distance the lowest matched points measure
(median over the settle window) below ``arrive_floor_max_m``, measured in at least
``arrive_floor_min_fraction`` of the window's frames, or in the last ``arrive_floor_min_readings``
readings of the patience window where few frames resolve it — an unmeasured floor certifies nothing,
and the robot holds while the readings accumulate — wherever
the goal's keyframe shows a floor (a close wall filling the view hides it; there no image can measure
it, and image and servo decide, as without the height; so they do where a whole patience window at the
goal resolved the floor fewer than ``arrive_floor_min_readings`` times: its floor points do not match). The image
check looks at the image turned back by the servo's heading estimate: it judges the position. On long views the goal's scale from its
neighbours can be several times too small — the servo then believes it has arrived a quarter metre
out, where the image barely differs — so a refused arrival hands the servo the scale the floor measured.
The matched floor cannot see everything either: when every matched point is far (a view down a
corridor) a sideways step looks like a turn to the features, the floor's matched points included. So
an arrival the others agreed on is checked once more on the near floor's pixels, aligned directly
(:mod:`topomap.servo.floor`; where the goal's keyframe image is at hand and its near floor textured):
beyond the arrival's bound it is refused, and the servo docks on the floor's pose from then on.
The disturbance estimates carry from one subgoal to the next, and so does the heading: at a switch
the heading relative to the new subgoal is predicted from the heading relative to the old one and
the two keyframes' relative heading (their images' planar geometry, stored on the map's edges:
:mod:`topomap.relative_motion`), so a vehicle that does not
see the new subgoal yet — at a corner the next keyframe may lie a turn away — turns toward it
instead of holding still (:meth:`~topomap.servo.servo.AppearanceServo.reacquire_command`).

The start. An answer at ``LocalizeConfig.min_confidence`` is taken at once; a weaker one (at least
``start_verified_confidence``) only once the servo's geometry confirms it: its relative pose to the
node has ``switch_min_inliers`` inliers, and after a short turn (``start_confirm_every_s``, so the
place stays in view) it verifies again, with a heading that differs by the turn the two frames
measure between them. Otherwise the scan goes on; after a full turn that found nothing the robot
moves a step towards the turn's best-verified view and scans again while a quarter of the base
budget is left, and only then the start fails ("could not localize") rather than guess.

The bumper. A robot whose ``apply`` returns a report with ``collided`` (the simulator's
:class:`~topomap.sim.simulator.StepReport`; a contact sensor, not a pose) tells the navigator when it
touched something: no arrival is taken in contact (keyframes were taken clear of walls), and
``contact_blocked_steps`` periods of contact in a row while servoing are a blocked subgoal — the
navigator reverses the push for ``contact_reverse_s`` and recovers as below. Robots without the flag
never report contact.

A subgoal whose view has changed (posters moved or taken down since the teach run) may never verify.
When a subgoal gave no usable geometry for ``lost_after_steps`` periods from the moment it became the
target, and the node before it was the last to verify well, the navigator first drives the taught
step between them (:meth:`Navigator._taught_step`: straight ahead, its distance and turn from the two
keyframes' images), heading held by the previous keyframe's view, watching for the subgoal or the node
after it to verify; the servo takes over from whichever does. Only then is the subgoal lost.

Recovery (docs/theory.md section 4.4). After ``lost_after_steps`` periods without usable geometry,
when a subgoal is not reached within ``subgoal_timeout_s``, a look-alike fooled the goal's settle
test or the bumper reports the way blocked, the navigator stops and

1. backs off toward the last node that verified well (at least ``switch_min_inliers`` inliers): it
   drives the inverse of the commands sent since then (at most ``recover_backoff_s``, disturbance
   compensation kept) until that node verifies again or the bumper reports contact (the drift took
   it elsewhere: the way back is no longer the way it came) — it moves before it looks again;
2. re-localizes, turning in place to search (the estimated drift cancelled in translation as well as
   yaw, as when holding still: a turn under a forward bias otherwise wanders into walls): a node
   within ``recover_local_hops`` of that node that verifies is preferred; an answer farther away is
   taken only at ``recover_far_confidence`` (when calibrated), confirmed by a second look (a
   single frame of a look-alike place is not enough) and within reach of the distance the robot was
   commanded to drive since its track was last confirmed (a stretch of look-alikes answers twice;
   the robot's own motion bounds where it can be); after a full turn without either it moves a step
   towards the turn's best-verified view (else its most textured one) and turns again
   (``recover_search_moves``: a spot from which nothing verifies — pressed against a wall, past the
   goal's view — loses any node kept there again at once), and only then keeps the best weakly
   verified near node, else the last node that verified well (after a look-alike fooled the goal's
   settle test there is none: it re-localizes globally);
3. penalises the edge it was following and re-plans.

It does not give up while more than ``give_up_budget_fraction`` of the time budget is left and the
map offers a route: the first ``max_replans`` re-plans extend the budget to the new route's, later
ones do not. A final failure says why (what it lost, what it tried, the time left).
"""

from __future__ import annotations

import enum
import logging
import math
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import cv2
import networkx as nx
import numpy as np

from topomap.agreement import GoalAgreement
from topomap.camera import CameraIntrinsics
from topomap.config import LocalizeConfig, NavigateConfig, PlanConfig, ServoConfig
from topomap.errors import NoRouteError
from topomap.features import Features
from topomap.graph import EdgeKind, TopoMap
from topomap.localize import Localization, Localizer, Query
from topomap.matching import Verification, match_descriptors, scene_scale, verify
from topomap.motion import STOP, Command, VehicleKind, vehicle_kind, wrap_angle
from topomap.plan import Planner, Route
from topomap.relative_motion import SCALE_CLIP_FACTOR, KeyframePairs
from topomap.retrieval import thumbnail_descriptor
from topomap.self_supervision import keyframe_image as stored_keyframe_image
from topomap.servo.essential import rotation_y
from topomap.servo.floor import FloorAligner, FloorAlignment
from topomap.servo.pose import PoseStatus, RelativePose
from topomap.servo.relpose import relative_pose, relative_pose_with_scales
from topomap.servo.servo import AppearanceServo, ServoOutput, ServoStatus

__all__ = ["RobotLike", "NavStatus", "EventKind", "NavEvent", "NavOutcome", "Navigator"]

log = logging.getLogger(__name__)

#: A waypoint's undocking radius is at least this multiple of its (wide) docking radius.
WAYPOINT_UNDOCK_FACTOR = 1.7
#: The settle window counts only when at least this fraction of its steps has a pose estimate.
SETTLE_MIN_VALID_FRACTION = 0.8
#: The goal's image check undoes at most this much of the estimated heading [deg] (a wider warp
#: replicates too much border into the thumbnail).
DEROTATE_MAX_DEG = 5.0
#: While backing off, look for the node that verified well every this many periods.
BACKOFF_CHECK_EVERY = 3
#: The floor can certify an arrival only where the goal's keyframe shows it: at least this many of its
#: features below the floor line (a wall closer than the first floor the camera sees hides it).
FLOOR_MIN_KEYFRAME_POINTS = 10
#: The final approach tries the near floor (:meth:`Navigator._floor_in_reach`) every this many periods
#: until it aligns: a full search costs 0.25-0.9 s.
FLOOR_TRY_PERIODS = 5
#: An intermediate subgoal's floor check (``switch_floor_max_m``) takes the median of the readings of
#: the last this many periods, when at least ``SWITCH_FLOOR_MIN_READINGS`` of them measured the floor.
SWITCH_FLOOR_PERIODS = 10
SWITCH_FLOOR_MIN_READINGS = 3


class RobotLike(Protocol):
    """What the navigator needs from a robot: images, intrinsics, and a way to move (optionally a
    ``camera_height_m`` attribute, the camera's mounting height: it makes goal distances metric)."""

    @property
    def camera(self) -> CameraIntrinsics: ...

    def render(self) -> np.ndarray: ...

    def apply(self, command: Command, dt: float) -> object: ...


#: Matches whose azimuth change lies within this of the median turn agree on it (~2.4 px at 160 px, 60 deg wide).
GYRO_AGREEMENT_RAD = math.radians(1.0)


class NavStatus(str, enum.Enum):
    RUNNING = "running"
    ARRIVED = "arrived"  # the final goal's image was reached (servo converged)
    FAILED = "failed"  # could not localize, no route, or too many re-plans
    TIMEOUT = "timeout"  # the time budget ran out


class EventKind(str, enum.Enum):
    LOCALIZED = "localized"
    PLANNED = "planned"
    STEP = "step"
    SUBGOAL = "subgoal"  # an intermediate subgoal was reached; the next one is the target
    LOST = "lost"
    REPLANNED = "replanned"
    ARRIVED = "arrived"
    FAILED = "failed"
    TIMEOUT = "timeout"


@dataclass(frozen=True)
class NavEvent:
    """Something the navigator did. ``time_s``: robot time since the start [s]; ``subgoal``: the node
    being servoed to; ``route``: the current plan; ``servo``: the control step (STEP events);
    ``image``: the camera image of that step (not copied — do not modify); ``matches``: the pixels
    the step servoed on, ``(current (N, 2), subgoal keyframe (N, 2))`` float32 at the map's working
    resolution, row i matching row i (``servo.pose.inlier_mask`` marks those its pose kept)."""

    kind: EventKind
    time_s: float
    message: str = ""
    subgoal: int | None = None
    route: tuple[int, ...] = ()
    servo: ServoOutput | None = None
    localization: Localization | None = None
    command: Command | None = None
    image: np.ndarray | None = field(default=None, repr=False)
    matches: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)


@dataclass
class NavOutcome:
    """Summary of a navigation: what the robot itself can tell (no ground truth here)."""

    status: NavStatus = NavStatus.RUNNING
    message: str = ""
    start_node: int | None = None
    goal: int | None = None
    subgoals_reached: int = 0
    replans: int = 0
    duration_s: float = 0.0
    steps: int = 0
    route: tuple[int, ...] = ()
    final_estimate_m: float = math.nan  # servo's own estimate of the remaining distance [m]
    final_heading_estimate_deg: float = math.nan
    contact_periods: int = 0  # control periods the robot's bumper reported touching something


class _Failed(Exception):
    """Internal: ends the run with a status and a message."""

    def __init__(self, status: NavStatus, message: str):
        super().__init__(message)
        self.status = status


class _Settle:
    """Has the robot arrived at the final goal? (``settle_*`` of :class:`~topomap.config.NavigateConfig`.)

    Arrived when the servo reports convergence for ``settle_steps`` periods in a row, or when,
    aligned and close, it stops making progress — and in both cases only if the image agrees. A
    unicycle that stalls further out (within ``settle_patience_max_m``) settles there if the image
    agrees within the looser ``settle_patience_image_error``. ``false_arrival`` counts the periods
    in a row the servo believed it had arrived while the image disagreed (a look-alike place).
    ``floor_required`` (the camera height is known and the goal's keyframe shows the floor): an arrival
    needs the floor measured and agreeing. ``patient``: the patient settle may fire (a unicycle; an
    omnidirectional vehicle can remove any offset, and its stalls resolve: it keeps servoing)."""

    def __init__(self, config: NavigateConfig, floor_required: bool = False, patient: bool = True):
        self.config = config
        self.floor_required = floor_required
        self.patient = patient
        # (time, estimated distance, heading, distance the floor measures [m] or NaN)
        self.history: list[tuple[float, float, float, float]] = []
        self.converged_streak = 0
        self.false_arrival = 0

    def update(self, time_s: float, s: ServoOutput, image_ok: bool, loosely_agrees,
               floor_m: float = math.nan) -> str | None:
        """One period at the goal; ``loosely_agrees()``: the image agrees within the patience bound
        (asked only when needed); ``floor_m``: the distance the floor measures in this image [m] (NaN:
        unknown). Returns ``"precise"``, ``"settled"``, ``"far"`` (the servo and the image say
        arrived, the floor disagrees: :meth:`floor_scale` is the scale its frames measure, if any)
        or None (not arrived, or the floor it requires not measured yet: :meth:`floor_verdict`)."""
        cfg = self.config
        self.converged_streak = self.converged_streak + 1 if (s.converged and image_ok) else 0
        self.history.append((time_s, s.position_error_m, s.heading_error_rad, floor_m))
        stalled = self.stalled(cfg.settle_max_m, cfg.settle_window_s, cfg.settle_progress_m)
        self.false_arrival = self.false_arrival + 1 if ((s.converged or stalled) and not image_ok) else 0
        if self.converged_streak >= cfg.settle_steps or (image_ok and stalled):
            floor = self.floor_verdict(cfg.arrive_floor_max_m)
            if floor is not None:  # unmeasured: wait (the patient settle may still take it)
                return "precise" if floor else "far"
        if (self.patient and self.stalled(cfg.settle_patience_max_m, cfg.settle_patience_s, cfg.settle_patience_progress_m)
                and loosely_agrees()):
            floor = self.floor_verdict(cfg.settle_patience_max_m, cfg.settle_patience_s)
            if floor is not None:
                return "settled" if floor else "far"
        return None

    def _floor_readings(self, window_s: float | None) -> np.ndarray:
        """The floor distances measured over the last ``window_s`` (default the settle window), NaN
        where a frame measured none [m]."""
        return self._recent(3, self.config.settle_window_s if window_s is None else window_s)

    def _recent(self, column: int, window_s: float) -> np.ndarray:
        """Column ``column`` of :attr:`history` over its last ``window_s``."""
        now = self.history[-1][0]
        return np.array([h[column] for h in self.history if h[0] >= now - window_s])

    def floor_distance(self, window_s: float | None = None) -> float:
        """Median distance the floor measured over the last ``window_s`` (default the settle window)
        [m]; NaN when fewer than ``arrive_floor_min_fraction`` of its frames, and fewer than
        ``arrive_floor_min_readings``, measured it."""
        return self._measured_median(self._floor_readings(window_s))

    def _measured_median(self, floor: np.ndarray) -> float:
        """:meth:`floor_distance` of the readings ``floor`` (NaN where a frame measured none)."""
        cfg = self.config
        ok = np.isfinite(floor)
        if not ok.any() or (ok.mean() < cfg.arrive_floor_min_fraction and ok.sum() < cfg.arrive_floor_min_readings):
            return math.nan
        return float(np.median(floor[ok]))

    def floor_verdict(self, bound_m: float, window_s: float | None = None) -> bool | None:
        """Does the floor measure an arrival within ``bound_m``? Measured over the window: whether it
        does. Unmeasured and not required: True (nothing contradicts). Required (a goal's scale from
        its neighbours can be ten times too small on a deep view, where the image barely changes over
        a metre — the floor is the only metric witness left): the last ``arrive_floor_min_readings``
        readings of the patience window judge when it holds that many (a view whose floor one frame in
        five resolves: a median of 15 readings is as sure over 8 s as over 3); else False if the few
        readings there are lie beyond (their scale is the servo's next); else True once a whole patience
        window at the goal resolved the floor fewer times than that — the keyframe's floor points do
        not match from here (untextured floor), so no image taken here measures it, as where a close
        wall hides it: image and servo decide; else None: not known yet — the robot holds and the
        readings accumulate (a refusal would restart the window, and such a view would never be
        judged)."""
        cfg = self.config
        floor = self._floor_readings(window_s)
        d = self._measured_median(floor)
        if math.isfinite(d):
            return d < bound_m
        if not self.floor_required:
            return True
        recent = self._floor_readings(max(cfg.settle_patience_s, window_s or 0.0))
        recent = recent[np.isfinite(recent)][-cfg.arrive_floor_min_readings:]
        if len(recent) == cfg.arrive_floor_min_readings:
            return float(np.median(recent)) < bound_m
        few = floor[np.isfinite(floor)]
        if few.size and float(np.median(few)) >= bound_m:
            return False
        return True if self.floor_unmeasurable() else None

    def floor_unmeasurable(self) -> bool:
        """The last ``settle_patience_s`` at the goal (a whole window of history, on at least half of
        whose periods the servo put the goal within ``settle_patience_max_m``) resolved the floor fewer
        than ``arrive_floor_min_readings`` times: the floor this keyframe shows is not matched. Periods
        spent driving up to the goal do not count: from metres away no floor matches (fresh world 328
        ep 0 drove 37 s of its 40 toward its goal, then "arrived" 0.35 m beside it)."""
        cfg = self.config
        if not self.history or self.history[-1][0] - self.history[0][0] < cfg.settle_patience_s:
            return False
        dist = self._recent(1, cfg.settle_patience_s)
        if np.count_nonzero(dist <= cfg.settle_patience_max_m) < 0.5 * dist.size:  # NaN: blind, not near
            return False
        return int(np.isfinite(self._floor_readings(cfg.settle_patience_s)).sum()) < cfg.arrive_floor_min_readings

    def floor_scale(self, scale_m: float) -> float | None:
        """The goal's scale [m per scaled unit] the floor measured over the settle window, from the
        servo's distances at ``scale_m``; None without frames that measured both."""
        now = self.history[-1][0]
        rows = np.array([(h[1], h[3]) for h in self.history if h[0] >= now - self.config.settle_window_s])
        ok = np.isfinite(rows).all(axis=1) & (rows[:, 0] > 0)
        if not ok.any():
            return None
        return float(np.median(rows[ok, 1] / rows[ok, 0])) * scale_m

    def not_approaching(self, window_s: float, progress_m: float) -> bool:
        """Over the last ``window_s`` the estimated distance came less than ``progress_m`` closer
        (medians of the window's first and last quarters), or the image gave no estimate on more than
        ``1 - SETTLE_MIN_VALID_FRACTION`` of its periods, and it did not settle: a final goal servo
        pushing against a wall, or toward a place the image never agrees is the goal (longer than
        ``settle_patience_s``, the patient settle has had its chance to take a stall within reach)."""
        history = self.history
        if not history:  # a fresh window (the floor refused an arrival and rescaled)
            return False
        now = history[-1][0]
        if now - history[0][0] < window_s:
            return False
        dist = self._recent(1, window_s)
        ok = np.isfinite(dist)
        if ok.mean() < SETTLE_MIN_VALID_FRACTION:
            # blind on a fifth of a whole window's periods or more: the medians would read noise, and a
            # goal the image keeps losing is not being approached (lighting world 254 ep 2: 98 s, 0.2 m)
            return True
        dist = dist[ok]
        quarter = max(1, len(dist) // 4)
        first, last = float(np.median(dist[:quarter])), float(np.median(dist[-quarter:]))
        return bool(first - last < progress_m)

    def stalled(self, max_m: float, window_s: float, progress_m: float) -> bool:
        """Aligned, within ``max_m``, and less than ``progress_m`` of progress over ``window_s``.

        Medians, not extremes: under noisy disturbances the per-image estimates jitter by a few
        centimetres and degrees around a pose the servo can no longer improve."""
        history = self.history
        now = history[-1][0]
        if now - history[0][0] < window_s:
            return False
        window = np.array([h[1:3] for h in history if h[0] >= now - window_s])
        ok = np.isfinite(window).all(axis=1)
        if ok.mean() < SETTLE_MIN_VALID_FRACTION:
            return False
        dist, head = window[ok, 0], np.abs(window[ok, 1])
        half = len(dist) // 2
        progress = abs(float(np.median(dist[:half])) - float(np.median(dist[half:]))) if half else math.inf
        return bool(np.median(head) < math.radians(self.config.settle_heading_deg) and np.median(dist) < max_m
                    and progress < progress_m)


@dataclass
class _Leg:
    """The state of following one route (reset at every re-plan): ``nodes[i]`` is the subgoal,
    ``lost`` the periods in a row without usable geometry (not counting up to a half turn toward a
    subgoal outside the view: ``turning``), ``since_switch_s`` when the subgoal became the target."""

    nodes: list[int]
    settle: _Settle
    since_switch_s: float
    i: int = 0
    lost: int = 0
    turning: int = 0  # blind periods spent turning toward a subgoal outside the view
    seen: bool = False  # the subgoal gave the servo usable geometry since it became the target
    bridged: bool = False  # the taught step to the subgoal was driven blind (:meth:`Navigator._bridge`)
    floor_docking: bool = False  # the near floor refused an arrival: the servo docks on the floor's pose
    dock_heading: float = 0.0  # the heading the last floor alignment measured [rad]
    dock_since_s: float | None = None  # when the near floor first held an arrival back
    dock_last: FloorAlignment | None = None  # the last docking alignment (tracked from, the next period)
    periods_at_goal: int = 0  # periods with the final goal as the target
    last_heading: float = math.nan  # the servo's heading error to the final goal, last period [rad]
    last_reading_m: float = math.inf  # the nearer of last period's servo and matched-floor distances [m]
    near_floor_m: float | None = None  # the distance the near floor measured at the last arrival checked [m]

    def switch_to(self, i: int, time_s: float) -> None:
        """Make ``nodes[i]`` the subgoal from ``time_s``: its own blind, turning, seen and bridged state."""
        self.i, self.since_switch_s = i, time_s
        self.lost = self.turning = 0
        self.seen = self.bridged = False


class Navigator:
    """Drives a robot to a goal node of ``tmap`` from images alone.

    ``vehicle``: kinematics of the robot (unicycle / omni); ``localizer``: reused if given (a
    :class:`~topomap.localize.Localizer` over ``tmap``). Iterate :meth:`run` to drive; the outcome is
    in :attr:`outcome` afterwards.
    """

    def __init__(
        self,
        tmap: TopoMap,
        robot: RobotLike,
        vehicle: str | VehicleKind = VehicleKind.UNICYCLE,
        config: NavigateConfig | None = None,
        servo_config: ServoConfig | None = None,
        localize_config: LocalizeConfig | None = None,
        plan_config: PlanConfig | None = None,
        localizer: Localizer | None = None,
        keyframe_image: Callable[[int], np.ndarray | None] | None = None,
    ):
        self.map = tmap
        self.robot = robot
        self.vehicle = vehicle_kind(vehicle)
        self.config = config or NavigateConfig()
        base = servo_config or ServoConfig()
        self.servo = AppearanceServo(self.vehicle, base)
        # Waypoints need no precise docking: inside switch_distance_m the servo only turns to the
        # subgoal's heading (at the teach run's corners consecutive nodes differ by a turn).
        dock = max(base.dock_radius_m, self.config.switch_distance_m)
        self._waypoint_servo = {"dock_radius_m": dock, "undock_radius_m": max(base.undock_radius_m, WAYPOINT_UNDOCK_FACTOR * dock)}
        self._goal_servo = {"dock_radius_m": base.dock_radius_m, "undock_radius_m": base.undock_radius_m}
        self.localizer = localizer or Localizer(tmap, localize_config or LocalizeConfig())
        self.planner = Planner(tmap, plan_config or PlanConfig())
        # keyframe-pair geometry: stored on the map's edges, computed for maps without it
        self.pairs = KeyframePairs(tmap, self.servo.config.geometry)
        self.agreement = GoalAgreement(tmap, self.config.arrive_image_error, self.config.arrive_descriptor_fraction)
        # the robot's images are processed at the map's working resolution
        self.camera = robot.camera.fitted_to(*tmap.working_size)
        self._half_fov_rad = math.atan2(0.5 * self.camera.width, self.camera.fx)
        # the periods a blind half turn takes at the servo's turn rate
        self._turn_steps = math.ceil(math.pi / self.servo.config.max_turn_rps / self.config.control_period_s)
        self.outcome = NavOutcome()
        self._time = 0.0
        self._last_command: Command | None = None
        self._estimate = None  # the servo's latest disturbance estimate
        # (features, periods moved by then) of the last two images: the visual gyro's pair (_gyro_turn)
        self._latest_look: tuple[Features, int] | None = None
        self._previous_look: tuple[Features, int] | None = None
        self._servo_time: float | None = None  # time of the servo's last step [s]
        self._here: int | None = None  # the node the robot was last localized at
        self._approach_side: float | None = None  # side of the subgoal camera the robot comes from
        self._subgoal_floor_m: deque[float] = deque(maxlen=SWITCH_FLOOR_PERIODS)  # the floor's distance to the subgoal [m]
        self._subgoal_waits_for_floor = False
        self._last_good: int | None = None  # the last node that verified well
        # (node, distance commanded by then) where the track was last confirmed: what bounds how far
        # away the robot can be since
        self._confirmed: tuple[int, float] | None = None
        self._commanded_m = 0.0  # distance commanded so far (translation, compensation included) [m]
        self._floor_graph: nx.Graph | None = None  # the map's edges weighted by their floor length
        self._steps: dict[tuple[int, int], tuple[float, float, float] | None] = {}  # taught steps (_taught_step)
        # commands sent since the last good verification (what backing off inverts)
        self._trail: deque[Command] = deque(maxlen=self._periods(self.config.recover_backoff_s))
        self._tried: dict[str, float] = {}  # what recovery did, for the final message
        # (a, b), a < b -> legs that failed after crossing the loop closure or one of its cluster
        self._loop_failures: Counter[tuple[int, int]] = Counter()
        self._contact_streak = 0  # periods in a row the bumper reported contact
        height = self.config.camera_height_m
        self._camera_height_m = height if height is not None else getattr(robot, "camera_height_m", None)
        # a goal's keyframe image, for the near floor's alignment (default: the images held in tmap)
        self._keyframe_image = keyframe_image or (lambda node: stored_keyframe_image(tmap, node))
        self._floor_aligners: dict[int, FloorAligner | None] = {}

    # ------------------------------------------------------------------ robot I/O
    def _scan_step(self, duration_s: float | None = None) -> float:
        """Turn in place for ``duration_s`` (default ``scan_every_s``; the estimated disturbance
        compensated, translation as well as yaw); returns the angle turned [rad]."""
        cfg = self.config
        # the body-frame drift the hold cancels does not stop while turning: uncompensated, a 12.8 s
        # search turn under a 4 cm/s bias wanders tens of centimetres, into walls (docs/navigation.md)
        hold = self._hold_command()
        # the yaw as before, the hold's or not: the uncompensated servo's search turn keeps its rate
        d_omega = self._estimate.d_omega if self._estimate is not None and self._estimate.ready else 0.0
        turn = Command(hold.v_f, hold.v_h, cfg.scan_turn_rps - d_omega).for_vehicle(self.vehicle)
        turned = 0.0
        duration_s = cfg.scan_every_s if duration_s is None else duration_s
        for _ in range(self._periods(duration_s)):
            self._move(turn)
            turned += cfg.scan_turn_rps * cfg.control_period_s
        return turned

    def _look(self, localizing: bool = False) -> tuple[np.ndarray, Query]:
        image = self.robot.render()
        # the vocabulary words only serve global localization, not the servo's matching each period
        q = self.localizer.prepare(image, words=localizing)
        self._previous_look, self._latest_look = self._latest_look, (q.features, self.outcome.steps)
        return image, q

    def _gyro_turn(self) -> float | None:
        """The camera's turn [rad] between the last two images when exactly one period's command
        (``_last_command``) lies between them (a visual gyro), None when it is not measured (no such
        pair, or fewer than the geometry's ``min_inliers`` matches agreeing on one turn).

        A turn about the vertical axis shifts every point's azimuth by the same angle whatever its
        height; one period's translation adds a parallax the median ignores. Hand-written: a median
        of azimuth differences, where a relative pose over so short a baseline confuses part of the
        turn with a sideways step (the bas-relief ambiguity of docs/servo.md)."""
        if self._previous_look is None or self._latest_look is None:
            return None
        (a, steps_a), (b, steps_b) = self._previous_look, self._latest_look
        if steps_b != steps_a + 1 or len(a) == 0 or len(b) == 0:
            return None
        m = match_descriptors(b, a, self.map.config.match)
        need = self.servo.config.geometry.min_inliers
        if len(m) < need:
            return None
        turns = (np.arctan(self.camera.normalize(b.keypoints[m.ia].astype(float))[:, 0])
                 - np.arctan(self.camera.normalize(a.keypoints[m.ib].astype(float))[:, 0]))
        turn = float(np.median(turns))
        agree = np.abs(turns - turn) < GYRO_AGREEMENT_RAD
        return float(np.median(turns[agree])) if agree.sum() >= need else None

    def _move(self, command: Command, trail: bool = False) -> bool:
        """Apply ``command`` for one period; returns whether the robot's bumper reported contact
        (a ``collided`` flag on what ``apply`` returns; robots without one never report it)."""
        dt = self.config.control_period_s
        if trail:
            self._trail.append(command)
        report = self.robot.apply(command, dt)
        self._time += dt
        self._commanded_m += math.hypot(command.v_f, command.v_h) * dt
        self._last_command = command
        self.outcome.steps += 1
        contact = getattr(report, "collided", False) is True
        self._contact_streak = self._contact_streak + 1 if contact else 0
        if contact:
            self.outcome.contact_periods += 1
        return contact

    def _periods(self, duration_s: float) -> int:
        """Control periods in ``duration_s`` (at least one)."""
        return max(1, int(round(duration_s / self.config.control_period_s)))

    def _hold_command(self) -> Command:
        """The command that stands still, cancelling the disturbances the servo has estimated."""
        return self.servo.hold_command(self._estimate) if self._estimate is not None else STOP

    def _undone(self, cmd: Command, hold: Command, turn: bool = True) -> Command:
        """The inverse of ``cmd``'s intent with ``hold``'s compensation kept (a command is compensation
        plus intent); ``turn=False`` undoes only its translation."""
        omega = 2 * hold.omega - cmd.omega if turn else hold.omega
        back = Command(2 * hold.v_f - cmd.v_f, 2 * hold.v_h - cmd.v_h, omega)
        return back.clipped(self.servo.config.max_speed_mps, self.servo.config.max_turn_rps).for_vehicle(self.vehicle)

    def _hold(self) -> None:
        """Stand still for one period, cancelling the disturbances the servo has estimated."""
        self._move(self._hold_command())

    def _match(self, q: Query, node: int) -> Verification:
        return verify(q.features, self.map.nodes[node].features, self.map.config.match)

    # ------------------------------------------------------------------ localization
    def _localize(self) -> Iterator[NavEvent]:
        """Global localization from the current image; turns in place to scan when unsure, and moves
        to scan elsewhere while the time budget lasts. Sets ``self._here``; raises _Failed when no
        place is recognised in any of the turns.

        An answer at ``min_confidence`` is taken at once; a weaker one (at least
        ``start_verified_confidence``) once the servo's geometry confirms it (:meth:`_start_pose`);
        after a full turn without either, the best answer of at least ``start_fallback_confidence``
        the geometry confirmed, once its view is found again (:meth:`_face_again`). After a turn that
        found nothing, while more than ``give_up_budget_fraction`` of ``time_budget_base_s`` is left,
        the robot drives up to ``start_search_step_m`` towards the view of the turn whose answer
        verified best (:meth:`_search_move`) and scans again: the start's view may be one the map cannot tell (a
        plain wall, a panel moved since the teach run), a step away it may not be."""
        cfg = self.config
        best: Localization | None = None
        turns = 0  # a move to scan elsewhere comes between two turns
        # a turn and a step more must fit in the share of the budget the start may use
        turn_and_step_s = 2.0 * math.pi / cfg.scan_turn_rps + cfg.start_search_step_m / cfg.start_search_speed_mps
        while True:
            found, fallback, best, towards = self._start_turn(best)
            turns += 1
            if found is None and fallback is not None and self._face_again(fallback[0].node):
                found = fallback
            if found is not None or cfg.start_search_step_m == 0 or (
                    self._time + turn_and_step_s > (1.0 - cfg.give_up_budget_fraction) * cfg.time_budget_base_s):
                break
            self._search_move(towards)
        if found is None:
            conf = best.confidence if best else 0.0
            # the confidence is appearance's; an answer its geometry did not verify is not declared
            declarable = best is not None and best.confidence >= self.localizer.config.min_confidence
            checked = f", {best.inliers} verified inliers" if declarable else ""
            seen = f"; node {fallback[0].node} was not seen again in a second turn" if fallback is not None else ""
            where = f"after {turns} full turns and {turns - 1} moves" if turns > 1 else "after a full turn"
            raise _Failed(NavStatus.FAILED, f"could not localize in the map {where} (best confidence {conf:.2f}{checked}){seen}")
        loc, why = found
        if turns > 1:
            why += f", after {turns - 1} move{'s' if turns > 2 else ''} to scan elsewhere"
        self._here = loc.node
        yield NavEvent(EventKind.LOCALIZED, self._time, f"at node {loc.node} ({why})", subgoal=loc.node, localization=loc)

    def _start_turn(self, best: Localization | None
                    ) -> tuple[tuple[Localization, str] | None, tuple[Localization, str] | None, Localization | None, float]:
        """One full scanning turn of the start (see :meth:`_localize`): (the answer taken and why, or
        None; the best confirmed answer below ``start_verified_confidence``, or None; the most
        confident answer so far, ``best`` included; the turn from the robot's heading now to the
        view whose answer verified with the most inliers, else the one with the most features [rad])."""
        cfg = self.config
        turned = 0.0
        found: tuple[Localization, str] | None = None
        fallback: tuple[Localization, str] | None = None  # the best confirmed answer below start_verified_confidence
        pending: tuple[Localization, RelativePose, Query] | None = None  # (answer, its pose, that frame)
        weakest = min(cfg.start_verified_confidence, cfg.start_fallback_confidence)  # worth confirming
        towards, most = 0.0, (-1, -1)
        while True:
            image, q = self._look(localizing=True)
            if pending is not None:  # the previous frame's candidate: does its geometry hold after the turn?
                cand, pose, before = pending
                # the heading loop is the confirmation; after the turn the view may hold half the inliers
                again = self._start_pose(q, cand.node, min_inliers=self.map.config.match.min_inliers)
                turn = self._frame_heading(q, before)  # the turn as the two images measure it
                if (again is not None and math.isfinite(turn) and abs(wrap_angle(again.theta - pose.theta - turn))
                        < math.radians(cfg.start_confirm_heading_deg)):
                    why = (f"confidence {cand.confidence:.2f}, confirmed by its geometry in two frames "
                           f"({pose.inliers} and {again.inliers} inliers)")
                    if cand.confidence >= cfg.start_verified_confidence:
                        found = (cand, why)
                        break
                    if fallback is None or cand.confidence > fallback[0].confidence:
                        fallback = (cand, why + ", the best of a full turn")
                pending = None
            loc = self.localizer.localize_query(q)
            if best is None or loc.confidence > best.confidence:
                best = loc
            # the view to move towards: the one whose answer verified best, else the most textured
            score = (loc.inliers, len(q.features))
            if score > most and turned < 2 * math.pi:
                towards, most = turned, score
            if loc.localized:
                found = (loc, f"confidence {loc.confidence:.2f}")
                break
            if loc.confidence >= weakest and (pose := self._start_pose(q, loc.node)) is not None:
                pending = (loc, pose, q)
            if turned >= 2 * math.pi and pending is None:
                break
            # a short turn before the confirming frame keeps the candidate's place in view
            turned += self._scan_step(cfg.start_confirm_every_s if pending is not None else None)
        self._hold()
        return found, fallback, best, towards - turned

    def _search_move(self, turn_rad: float, what: str = "start search moves") -> None:
        """Turn by ``turn_rad`` (wrapped; towards a search turn's best-verified view, a place
        the map nearly recognised, or its most textured one, open space rather than a wall close by)
        and drive forward up to ``start_search_step_m`` at ``start_search_speed_mps``, the estimated
        disturbance compensated, stopping at the first contact. ``what`` names the move in the
        failure's summary."""
        cfg = self.config
        turn = wrap_angle(turn_rad) % (2.0 * math.pi)  # the scan turns one way only
        turned = 0.0
        while turned + 0.5 * cfg.scan_turn_rps * cfg.control_period_s < turn:
            turned += self._scan_step(cfg.control_period_s)
        hold = self._hold_command()
        ahead = Command(hold.v_f + cfg.start_search_speed_mps, hold.v_h, hold.omega).for_vehicle(self.vehicle)
        for _ in range(self._periods(cfg.start_search_step_m / cfg.start_search_speed_mps)):
            if self._move(ahead):
                self._count(f"{what} ended by contact")
                break
        self._hold()
        self._count(what)

    def _face_again(self, node: int) -> bool:
        """Turn on, at most one more full turn, until ``node``'s keyframe verifies again (the match's
        ``min_inliers``): the start's best answer was seen some way back, and its first subgoal is
        that view. Finding it again at about the heading it was first seen is one more look."""
        turned = 0.0
        while turned < 2 * math.pi:
            turned += self._scan_step()
            _, q = self._look(localizing=True)
            if self._start_pose(q, node, min_inliers=self.map.config.match.min_inliers) is not None:
                self._hold()
                return True
        self._hold()
        return False

    def _pose_against(self, q: Query, other: Features, other_camera: CameraIntrinsics | None = None
                      ) -> RelativePose | None:
        """The servo's relative pose of the image of ``q`` in the image of ``other`` (seen by
        ``other_camera``, default the robot's) from their verified matches; None when they do not verify."""
        v = verify(q.features, other, self.map.config.match)
        if not v.verified:
            return None
        use = v.inlier_matches
        return relative_pose(q.features.keypoints[use.ia], other.keypoints[use.ib], self.camera,
                             self.servo.config.geometry, goal_camera=other_camera)

    def _frame_heading(self, q: Query, before: Query) -> float:
        """Heading of the image of ``q`` relative to the image of ``before`` [rad]; NaN without a pose."""
        pose = self._pose_against(q, before.features)
        return pose.theta if pose is not None and pose.has_heading else math.nan

    def _start_pose(self, q: Query, node: int, min_inliers: int | None = None) -> RelativePose | None:
        """The servo's relative pose of the image of ``q`` in ``node``'s keyframe when it has a heading
        from at least ``min_inliers`` (default ``switch_min_inliers``) inliers, else None."""
        need = self.config.switch_min_inliers if min_inliers is None else min_inliers
        pose = self._pose_against(q, self.map.nodes[node].features, self.map.camera)
        return pose if pose is not None and pose.has_heading and pose.inliers >= need else None

    def _plan(self, start: int, goal: int) -> Route:
        try:
            return self.planner.route(start, goal)
        except NoRouteError as e:
            raise _Failed(NavStatus.FAILED, str(e)) from None

    # ------------------------------------------------------------------ main loop
    def run(self, goal: int, start_node: int | None = None) -> Iterator[NavEvent]:
        """Navigate to ``goal``; ``start_node`` skips the initial global localization (trusted)."""
        self.map.node(goal)  # unknown ids fail before the robot moves
        if start_node is not None:
            self.map.node(start_node)
        out = self.outcome = NavOutcome(goal=int(goal))
        self._trail.clear()
        self._tried = {}
        try:
            if start_node is None:
                yield from self._localize()
            else:
                self._here = int(start_node)
            out.start_node = self._here
            self._last_good = self._here
            self._confirmed = (self._here, self._commanded_m)
            route = self._plan(self._here, goal)
            out.route = tuple(route.nodes)
            yield NavEvent(EventKind.PLANNED, self._time, f"route of {route.hops} hops: {list(route.nodes)}",
                           subgoal=route.nodes[0], route=tuple(route.nodes))
            budget = self.config.time_budget_base_s + self.config.time_budget_s_per_hop * max(1, route.hops)
            yield from self._follow(route, goal, budget)
        except _Failed as f:
            self._move(STOP)
            out.status = f.status
            out.message = str(f)
            kind = EventKind.TIMEOUT if f.status is NavStatus.TIMEOUT else EventKind.FAILED
            yield NavEvent(kind, self._time, str(f), route=out.route)
        out.duration_s = self._time

    def _target(self, nodes: list[int], i: int, heading_prior: float | None = None) -> None:
        """Point the servo at ``nodes[i]``: new references, docking radius of a waypoint or of the
        goal; ``heading_prior``: the predicted heading relative to it [rad], if any."""
        # the side of the subgoal camera the robot comes from: behind it (x < 0) when following the
        # taught direction, in front of it when driving the route backwards
        self._approach_side = None
        self._subgoal_floor_m.clear()  # the floor's distances to the previous subgoal
        # a subgoal behind the camera (a taught chain walked backwards) whose keyframe shows floor
        # waits for the floor before a switch counts (_floor_says_far)
        self._subgoal_waits_for_floor = (i > 0 and self._camera_height_m is not None
                                         and self.planner.against_taught(nodes[i - 1], nodes[i]) and self.shows_floor(nodes[i]))
        normals, scale = self.pairs.goal_view(nodes[i], self._camera_height_m, self.servo.config.nominal_scale_m)
        self.servo.retarget(normals, scale if i == len(nodes) - 1 else None, heading_prior)  # metric at the goal
        self.servo.reconfigure(**(self._goal_servo if i == len(nodes) - 1 else self._waypoint_servo))

    def _derotated(self, q: Query, v: Verification, cur_px: np.ndarray, goal_px: np.ndarray, heading_rad: float
                   ) -> tuple[Query, Verification]:
        """The image of ``q`` and its verified matches turned about the camera centre by the servo's
        heading estimate (at most DEROTATE_MAX_DEG) to the goal keyframe's orientation, for the goal's
        image check: its flow and thumbnail then measure the position, not the heading, which has
        its own tolerance — one degree of yaw moves the whole image about 1.5 % of its width, and
        the flow bound is 2 %."""
        if not v.verified or not math.isfinite(heading_rad) or len(cur_px) == 0:
            return q, v
        bound = math.radians(DEROTATE_MAX_DEG)
        theta = float(np.clip(heading_rad, -bound, bound))
        K = self.camera.K
        H = K @ rotation_y(-theta) @ np.linalg.inv(K)
        p = np.c_[cur_px, np.ones(len(cur_px))] @ H.T
        flow = float(np.median(np.linalg.norm(p[:, :2] / p[:, 2:] - goal_px, axis=1)))
        if q.descriptor.size:
            h, w = q.image.shape[:2]
            turned = cv2.warpPerspective(q.image, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            q = replace(q, descriptor=thumbnail_descriptor(turned, self.localizer.descriptor_size, self.localizer.descriptor_patch))
        return q, replace(v, flow_px=flow)

    def _rescale(self, leg: _Leg) -> None:
        """The floor contradicted an arrival: the goal's scale is off. Take the scale the floor measured
        (within the range a goal's scale may take) and judge arrival on a fresh window."""
        nominal = self.servo.config.nominal_scale_m
        measured = leg.settle.floor_scale(self.servo.scale_m)
        if measured is not None:
            self.servo.rescale(float(np.clip(measured, nominal / SCALE_CLIP_FACTOR, SCALE_CLIP_FACTOR * nominal)))
        self._count("arrivals the floor refused")
        leg.settle = self._new_settle(leg.nodes[-1])

    def _new_settle(self, goal: int) -> _Settle:
        return _Settle(self.config, floor_required=self._camera_height_m is not None and self.shows_floor(goal),
                       patient=self.vehicle is VehicleKind.UNICYCLE)

    def shows_floor(self, node: int) -> bool:
        """Whether ``node``'s keyframe shows the floor the arrival check measures. A view filled by a
        close wall does not (its features all lie above the floor line): no image taken there can
        measure the floor, so requiring it would refuse every arrival — image and servo decide."""
        y = self.map.camera.normalize(self.map.nodes[node].features.keypoints)[:, 1]  # as the servo's floor sees them
        return int(np.count_nonzero(y > self.servo.config.geometry.floor_min_y)) >= FLOOR_MIN_KEYFRAME_POINTS

    def _floor_aligner(self, node: int) -> FloorAligner | None:
        """The near-floor aligner of ``node``'s keyframe; None without the camera height, the keyframe's
        image, floor in its view or texture on it (plain paint: nothing to align)."""
        if node not in self._floor_aligners:
            aligner = None
            if self.config.arrive_floor_align and self._camera_height_m is not None and self.shows_floor(node):
                image = self._keyframe_image(node)
                if image is not None:
                    aligner = FloorAligner(image, self.map.camera)
            self._floor_aligners[node] = aligner if aligner is not None and aligner.textured else None
        return self._floor_aligners[node]

    def _aligned_floor(self, node: int, image: np.ndarray, heading_rad: float,
                       near: FloorAlignment | None = None, min_ncc: float | None = None) -> FloorAlignment | None:
        """The robot's pose relative to ``node`` from its near floor in ``image``, if the alignment is
        confident (:meth:`FloorAlignment.confident`; at ``min_ncc``, default ``floor_align_min_ncc``).
        ``near``: last period's alignment, tracked from (a small search around it; the full search
        where that is not confident)."""
        aligner = self._floor_aligner(node)
        if aligner is None:
            return None
        cfg = self.config
        cam = self.robot.camera.fitted_to(image.shape[1], image.shape[0])
        theta0 = heading_rad if math.isfinite(heading_rad) else 0.0
        min_ncc = cfg.floor_align_min_ncc if min_ncc is None else min_ncc
        for around in ((near, None) if near is not None else (None,)):
            a = aligner.align(image, cam, theta0, near=around)
            if a is not None and a.confident(min_ncc, cfg.floor_align_min_peak):
                return a
        return None

    def _near_floor_refuses(self, leg: _Leg, arrived: str, dock: FloorAlignment | None, image: np.ndarray,
                            s: ServoOutput) -> bool:
        """Whether the near floor refuses the arrival the servo, the image and the matched floor agreed
        on: aligned (this period's docking alignment, or one made now), it puts the robot beyond the
        arrival's bound. Looking down a corridor every matched point is far, and far points cannot
        tell a sideways step from a turn: the robot stood 0.26-0.33 m beside its goal, "arrived"
        (fresh worlds 289 ep 8, 286 ep 9). A refusal starts a fresh settle, docking on the floor's pose."""
        cfg = self.config
        near = dock if dock is not None else self._aligned_floor(leg.nodes[-1], image, s.heading_error_rad,
                                                                  min_ncc=cfg.floor_refuse_min_ncc)
        if near is None:
            leg.near_floor_m = None
            return False
        leg.near_floor_m = near.distance_h * self._camera_height_m
        bound = cfg.arrive_floor_max_m if arrived == "precise" else cfg.settle_patience_max_m
        if leg.near_floor_m < bound:
            if near.ncc < cfg.floor_align_min_ncc:
                return False  # an alignment below the steering threshold may refuse, never steer
            # within the bound: an omni docks closer on the floor's pose while floor_dock_patience_s lasts
            # (a unicycle's sideways docking turns it until the keyframe's near floor leaves the view)
            target = cfg.floor_dock_target_m if self.vehicle is VehicleKind.OMNI else None
            if target is None or leg.near_floor_m < target or (
                    leg.dock_since_s is not None and self._time - leg.dock_since_s >= cfg.floor_dock_patience_s):
                return False
            self._count("arrivals held to dock closer")
        else:
            self._count("arrivals the near floor refused")
        if leg.dock_since_s is None:
            leg.dock_since_s = self._time
        leg.floor_docking, leg.dock_heading, leg.dock_last = True, near.theta, near
        leg.settle = self._new_settle(leg.nodes[-1])
        return True

    def _floor_in_reach(self, leg: _Leg) -> bool:
        """Whether to try the near floor on the final approach this period (an omni vehicle only; every
        ``FLOOR_TRY_PERIODS``): last period's servo or matched floor put the goal within
        ``floor_approach_m``. Near a goal the features' pose can jump 0.03-1.4 m between frames
        (world 254 ep 1 under ``lighting``) where the near floor measures it to a centimetre."""
        cfg = self.config
        return (cfg.floor_approach_m is not None and self.vehicle is VehicleKind.OMNI and self._camera_height_m is not None
                and leg.periods_at_goal % FLOOR_TRY_PERIODS == 0 and leg.last_reading_m < cfg.floor_approach_m)

    def _predicted(self, a: FloorAlignment | None) -> FloorAlignment | None:
        """Last period's alignment turned by the command since (a docking unicycle turns ~3 deg a period)."""
        if a is None or self._last_command is None:
            return a
        return replace(a, theta=a.theta + self._last_command.omega * self.config.control_period_s)

    def _floor_pose(self, a: FloorAlignment) -> RelativePose:
        """A floor alignment as the servo's pose measurement (its scale)."""
        k = self._camera_height_m / self.servo.scale_m
        return RelativePose(PoseStatus.OK, theta=a.theta, x_s=a.x_h * k, z_s=a.z_h * k, inliers=a.pixels)

    def _start_leg(self, nodes: list[int]) -> _Leg:
        """The one place a route's loop state starts (first plan and every re-plan)."""
        leg = _Leg(list(nodes), self._new_settle(nodes[-1]), self._time)
        self._target(leg.nodes, leg.i)
        return leg

    def _follow(self, route: Route, goal: int, budget_s: float) -> Iterator[NavEvent]:
        cfg, out = self.config, self.outcome
        leg = self._start_leg(route.nodes)
        while True:
            nodes, i = leg.nodes, leg.i
            if self._time > budget_s:
                raise _Failed(NavStatus.TIMEOUT, f"time budget of {budget_s:.0f} s exhausted at subgoal {nodes[i]}")
            sub = nodes[i]
            final = i == len(nodes) - 1
            image, q = self._look()
            v = self._match(q, sub)
            use = v.inlier_matches if v.verified else v.matches
            cur_px, goal_px = q.features.keypoints[use.ia], self.map.nodes[sub].features.keypoints[use.ib]
            # docking on the near floor (an arrival it refused): its pose steers, where it aligns
            dock = self._aligned_floor(sub, image, leg.dock_heading, self._predicted(leg.dock_last)) if final and leg.floor_docking else None
            if final and not leg.floor_docking and self._floor_in_reach(leg):
                dock = self._aligned_floor(sub, image, leg.last_heading)
                if dock is not None and dock.distance_h * self._camera_height_m < self.config.floor_approach_m:
                    leg.floor_docking = True  # the near floor steers the final approach from here
                    self._count("final approaches on the near floor")
                else:
                    dock = None
            if self._servo_time is not None:  # periods driven without the servo (turns, moves) since its last step
                self.servo.age(self._time - self._servo_time - cfg.control_period_s)
            self._servo_time = self._time
            # approaching on the near floor, the features steer where they lie within floor_approach_gate_m of
            # it (finer on a good view; the floor's own error reaches ~0.05 m); after a refusal or a hold the floor steers
            s = self.servo.step(cur_px, goal_px, self.camera, cfg.control_period_s, self._last_command,
                                goal_camera=self.map.camera, measured=None if dock is None else self._floor_pose(dock),
                                features_within_s=None if leg.dock_since_s is not None
                                else cfg.floor_approach_gate_m / self.servo.scale_m)
            leg.dock_last = dock
            if dock is not None:
                leg.dock_heading = dock.theta
            matched_floor_m = self._floor_m(s)
            if final:
                leg.periods_at_goal += 1
                leg.last_heading = s.heading_error_rad
                leg.last_reading_m = min(s.position_error_m, matched_floor_m) if math.isfinite(matched_floor_m) else s.position_error_m
            yield NavEvent(EventKind.STEP, self._time, s.status.value, subgoal=sub, route=tuple(nodes), servo=s,
                           command=s.command, image=image, matches=(cur_px, goal_px))
            self._estimate = s.disturbance
            if s.status is ServoStatus.LOST and cfg.visual_gyro:  # no goal heading: the turn between images
                self._estimate = self.servo.observe_turn(cfg.control_period_s, self._last_command, self._gyro_turn())
            leg.seen = leg.seen or s.status is not ServoStatus.LOST
            if v.inliers >= cfg.switch_min_inliers and s.status is not ServoStatus.LOST:
                self._last_good = sub
                self._confirmed = (sub, self._commanded_m)
                self._trail.clear()
            out.final_estimate_m = s.position_error_m
            out.final_heading_estimate_deg = math.degrees(s.heading_error_rad) if math.isfinite(s.heading_error_rad) else math.nan

            # -- final goal: settle
            if final:
                # the matched floor stays a witness of its own until the near floor has held an arrival back
                floor_m = matched_floor_m if dock is None or leg.dock_since_s is None else dock.distance_h * self._camera_height_m
                qa, va = self._derotated(q, v, cur_px, goal_px, s.heading_error_rad)
                arrived = leg.settle.update(
                    self._time, s, self.agreement.agrees(qa, va, sub),
                    lambda: self.agreement.agrees(qa, va, sub, cfg.settle_patience_image_error), floor_m)
                if arrived == "far":
                    self._rescale(leg)
                elif arrived and self._near_floor_refuses(leg, arrived, dock, image, s):
                    pass  # docks on the floor's pose from here
                elif arrived and not self._contact_streak:  # never touching: keyframes were taken clear of walls
                    self._move(STOP)
                    out.status = NavStatus.ARRIVED
                    floor = leg.settle.floor_distance(cfg.settle_patience_s if arrived == "settled" else None)
                    out.message = f"arrived at node {goal}" + (
                        "" if arrived == "precise" else f" (settled {s.position_error_m:.2f} m off by its estimate: no further progress)") + (
                        f" (the floor measures {floor:.2f} m)" if math.isfinite(floor) else
                        " (its view shows no floor to measure)" if self._camera_height_m is not None and not leg.settle.floor_required
                        else f" (its floor not matched: under {cfg.arrive_floor_min_readings} readings in "
                        f"{cfg.settle_patience_s:.0f} s)" if leg.settle.floor_unmeasurable() else "") + (
                        f" (the near floor aligns {leg.near_floor_m:.2f} m off)" if leg.near_floor_m is not None else "") + (
                        f" (docked on the near floor for {self._time - leg.dock_since_s:.0f} s)"
                        if leg.dock_since_s is not None else " (approached on the near floor)" if leg.floor_docking else "")
                    yield NavEvent(EventKind.ARRIVED, self._time, out.message, subgoal=goal, route=tuple(nodes))
                    return
            # -- intermediate subgoal: switch?
            else:
                reason = self._switch_reason(q, s, nodes[i + 1], v)
                if reason:
                    # heading relative to the next subgoal = relative to this one + this one's relative to it
                    here = s.heading_error_rad if math.isfinite(s.heading_error_rad) else s.disturbance.theta
                    prior = here + self._keyframe_heading(sub, nodes[i + 1]) if math.isfinite(here) else None
                    leg.switch_to(leg.i + 1, self._time)
                    out.subgoals_reached += 1
                    self._target(nodes, leg.i, prior if prior is not None and math.isfinite(prior) else None)
                    yield NavEvent(EventKind.SUBGOAL, self._time, f"reached {sub} ({reason}); next {nodes[leg.i]}",
                                   subgoal=nodes[leg.i], route=tuple(nodes))
                    continue
            # -- lost or stuck: re-localize and re-plan
            if self._turning_toward(s) and leg.turning < self._turn_steps:
                leg.turning += 1  # a subgoal a turn away is not lost while the turn lasts
            else:
                leg.lost = leg.lost + 1 if s.status is ServoStatus.LOST else 0
                leg.turning = leg.turning if s.status is ServoStatus.LOST else 0
            if (leg.lost >= cfg.lost_after_steps and not leg.seen and not leg.bridged and i > 0
                    and nodes[i - 1] == self._last_good):
                leg.bridged = True
                j = self._bridge(nodes, i)
                if j is not None:  # a view of the route verifies again: the servo takes over from there
                    step = f"drove the taught step from {nodes[i - 1]} (the view of {sub} did not verify)"
                    if j > i:
                        leg.switch_to(j, self._time)
                        out.subgoals_reached += 1
                        msg = f"reached {sub} ({step}); next {nodes[j]}"
                    else:  # the same subgoal, blind count restarted; its step is not driven twice
                        leg.lost = leg.turning = 0
                        leg.since_switch_s = self._time
                        msg = f"{step}; {sub} verifies now"
                    self._target(nodes, leg.i)
                    yield NavEvent(EventKind.SUBGOAL, self._time, msg, subgoal=nodes[leg.i], route=tuple(nodes))
                    continue
            stuck = (self._time - leg.since_switch_s > cfg.subgoal_timeout_s if not final else
                     leg.settle.not_approaching(cfg.goal_no_progress_s, cfg.goal_no_progress_m))
            fooled = leg.settle.false_arrival >= cfg.lost_after_steps
            blocked = self._contact_streak >= cfg.contact_blocked_steps
            if leg.lost >= cfg.lost_after_steps or stuck or fooled or blocked:
                why = ("lost sight of" if leg.lost >= cfg.lost_after_steps else
                       "was fooled by a look-alike of" if fooled else
                       "was blocked on the way to" if blocked else "could not reach")
                if blocked:
                    self._count("blocked by contact")
                    self._reverse(self._last_command or STOP)
                prev = nodes[i - 1] if i > 0 else None
                if prev is not None:
                    self.planner.penalize(prev, sub)
                self._blame_loop_closures(nodes[:i + 1])
                yield NavEvent(EventKind.LOST, self._time, f"{why} subgoal {sub}", subgoal=sub, route=tuple(nodes))
                out.replans += 1
                left = budget_s - self._time
                if out.replans > cfg.max_replans and left <= cfg.give_up_budget_fraction * budget_s:
                    raise _Failed(NavStatus.FAILED, f"gave up after {out.replans - 1} re-plans ({why} subgoal {sub}; "
                                  f"tried: {self._tried_summary()}; {max(0.0, left):.0f} s of {budget_s:.0f} s left)")
                self._hold()
                if fooled:  # the goal "verified" at a look-alike place: no ground to back off to
                    self._last_good = self._confirmed = None
                yield from self._recover()
                new = self._plan(self._here, goal)
                if out.replans <= cfg.max_replans:
                    budget_s = max(budget_s, self._time + cfg.time_budget_base_s + cfg.time_budget_s_per_hop * max(1, new.hops))
                out.route = tuple(new.nodes)
                leg = self._start_leg(new.nodes)
                yield NavEvent(EventKind.REPLANNED, self._time, f"new route {leg.nodes}", subgoal=leg.nodes[0],
                               route=tuple(leg.nodes))
                continue
            self._move(s.command, trail=True)

    def _bridge(self, nodes: list[int], i: int) -> int | None:
        """Drive the taught step from ``nodes[i - 1]`` (where the robot is: the last node that verified
        well) to ``nodes[i]``, whose view never verified, disturbances compensated, up to a quarter
        beyond it, watching for ``nodes[i]`` or the node after it to verify (``switch_min_inliers``).
        The heading follows the step's turn by the view of ``nodes[i - 1]`` while that verifies (a
        visual compass: the estimated yaw disturbance alone let a harsh one turn the robot 40 deg in
        6 s). Returns the index of the node that verified; None when the step is not straight
        (:meth:`_taught_step`), neither verified or the bumper reported contact (recovery's back-off
        undoes the step: it is on the trail)."""
        cfg, prev = self.config, nodes[i - 1]
        step = self._taught_step(prev, nodes[i])
        if step is None:
            return None
        dist, bearing, turn = step
        periods = self._periods(dist / cfg.bridge_speed_mps)
        duration = periods * cfg.control_period_s
        max_turn = self.servo.config.max_turn_rps
        self._count("taught steps driven blind")
        for k in range(periods + periods // 4):
            _, q = self._look()
            for j, node in enumerate(nodes[i:i + 2]):
                if self._match(q, node).inliers >= cfg.switch_min_inliers:
                    return i + j
            hold = self._hold_command()
            pose = self._pose_against(q, self.map.nodes[prev].features, self.map.camera)
            steer = 0.0
            if pose is not None and pose.has_heading:  # the turn so far, as planned, minus the one seen
                steer = float(np.clip(min(1.0, k / periods) * turn - pose.theta, -max_turn, max_turn))
            omega = hold.omega + turn / duration + steer  # an arc: its chord has the step's bearing, half the turn
            if self.vehicle is VehicleKind.UNICYCLE:
                cmd = Command(hold.v_f + cfg.bridge_speed_mps, hold.v_h, omega)
            else:
                cmd = Command(hold.v_f + cfg.bridge_speed_mps * math.cos(bearing),
                              hold.v_h + cfg.bridge_speed_mps * math.sin(bearing), omega)
            if self._move(cmd.clipped(self.servo.config.max_speed_mps, max_turn).for_vehicle(self.vehicle), trail=True):
                self._count("blind steps ended by contact")
                break
        self._hold()
        return None

    def _taught_step(self, a: int, b: int) -> tuple[float, float, float] | None:
        """How the teach run drove from keyframe ``a`` to keyframe ``b`` of a sequential edge, from
        their images: (distance [m], bearing of ``b`` from ``a`` [rad, left positive], heading of ``b``
        relative to ``a`` [rad]); None unless it is a straight step forward within ``bridge_max_m``,
        ``bridge_max_bearing_deg`` and ``bridge_max_turn_deg`` (camera height known). The distance is
        the pair's in the median-depth convention times the keyframes' scale from their neighbours
        (:meth:`KeyframePairs.goal_view`, as the servo's goal); the bearing is half the turn, as on
        an arc the teach run drove forward: a pose's translation direction off a wall errs by 15-25 deg
        where its heading errs by 2-4."""
        cfg = self.config
        if cfg.bridge_max_m is None or self._camera_height_m is None:
            return None
        if (a, b) not in self._steps:
            self._steps[(a, b)] = None
            edge, fa, fb = self.map.edge(a, b), self.map.nodes[a].features, self.map.nodes[b].features
            v = verify(fb, fa, self.map.config.match) if edge is not None and edge.kind is EdgeKind.SEQUENTIAL else None
            if v is not None and v.verified:
                use = v.inlier_matches
                pose, rho, _ = relative_pose_with_scales(fb.keypoints[use.ia], fa.keypoints[use.ib], self.map.camera,
                                                         self.servo.config.geometry)
                scales = [self.pairs.goal_view(n, self._camera_height_m, self.servo.config.nominal_scale_m)[1] for n in (b, a)]
                scale = next((sc for sc in scales if sc is not None), None)
                forward = pose.status is PoseStatus.OK and pose.x_s > 0 and abs(math.atan2(pose.z_s, pose.x_s)) <= math.pi / 4
                if forward and rho is not None and scale is not None and math.isfinite(pose.theta):
                    self._steps[(a, b)] = (rho * scale, 0.5 * pose.theta, pose.theta)
        step = self._steps[(a, b)]
        if step is None:
            return None
        dist, bearing, turn = step
        straight = abs(turn) <= math.radians(cfg.bridge_max_turn_deg) and abs(bearing) <= math.radians(cfg.bridge_max_bearing_deg)
        return step if straight and 0 < dist <= cfg.bridge_max_m else None

    def _blame_loop_closures(self, travelled: list[int]) -> None:
        """A leg failed after travelling ``travelled`` (up to the lost subgoal): count one failure
        against each loop closure it crossed within ``distrust_within_hops`` of the loss (and their
        clusters); distrust those that reached ``distrust_loop_after``. A loop closure between
        look-alike walls (repeated photographs, a symmetric corridor) verifies like a true one, and
        re-localization then finds the robot where the claim put it, so re-plans cross it again and
        again: only repeated failure tells."""
        after = self.config.distrust_loop_after
        if after <= 0:
            return
        recent = travelled[-(self.config.distrust_within_hops + 1):]
        crossed = [(min(a, b), max(a, b)) for a, b in zip(recent[:-1], recent[1:]) if self.planner.is_loop_claim(a, b)]
        self._loop_failures.update({k for key in crossed for k in self.planner.loop_cluster(*key)})
        for key in crossed:
            if self._loop_failures[key] >= after and key not in self.planner.distrusted:
                self._count("loop closures distrusted", len(self.planner.distrust(*key)))

    # ------------------------------------------------------------------ recovery
    def _recover(self) -> Iterator[NavEvent]:
        """After a loss: back off toward the last node that verified well, then re-localize near it
        (searching by turning in place). Sets ``self._here``; never fails."""
        backed = self._back_off()
        if backed > 0:
            self._count("backed off", backed)
        yield from self._relocalize()

    def _back_off(self) -> float:
        """Drive the inverse of the commands sent since the last good verification, newest first,
        until that node verifies again. Returns the time driven [s]."""
        cfg, target = self.config, self._last_good
        trail = list(self._trail)[::-1]
        self._trail.clear()
        if target is None or not trail:
            return 0.0
        hold = self._hold_command()
        driven = 0.0
        for k, cmd in enumerate(trail):
            if k % BACKOFF_CHECK_EVERY == 0 and k > 0:
                _, q = self._look()
                if self._match(q, target).inliers >= cfg.switch_min_inliers:
                    break
            driven += cfg.control_period_s
            if self._move(self._undone(cmd, hold)):
                self._count("back-offs ended by contact")
                break  # the drift took it elsewhere: the way back is not the way it came
        self._hold()
        return driven

    def _reverse(self, pushing: Command) -> None:
        """Drive the translation of ``pushing`` backwards (compensation kept, no turn) for
        ``contact_reverse_s`` or until the bumper reports contact again."""
        back = self._undone(pushing, self._hold_command(), turn=False)
        self._contact_streak = 0
        for _ in range(self._periods(self.config.contact_reverse_s)):
            if self._move(back):
                break

    def _near(self, node: int | None) -> set[int]:
        """The nodes within ``recover_local_hops`` of ``node`` (empty for None)."""
        if node is None:
            return set()
        return set(nx.single_source_shortest_path_length(self.map.graph, node, cutoff=self.config.recover_local_hops))

    def _relocalize(self) -> Iterator[NavEvent]:
        """Re-localize after a loss, turning in place to search: prefer a verified node near the last
        good one; take a far answer only confident, within reach of where the track was last confirmed
        (:meth:`_within_reach`) and confirmed by a second look; after a full turn with neither, move
        a step towards the turn's best-verified view and turn again (``recover_search_moves`` times,
        :meth:`_search_move`); then take the best weakly verified near node of the last turn, else
        keep the last good node (or the last localization)."""
        cfg, min_inliers = self.config, self.map.config.match.min_inliers
        near = self._near(self._last_good)
        # the localizer's ranking among the near nodes only (appearance and inliers: the node with
        # the most inliers may be one looking down the same corridor from metres away)
        away = [n for n in self.map.nodes if n not in near]
        turned, far, found = 0.0, None, None
        best_local: tuple[int, int] | None = None  # (inliers, node) of the best weakly verified near node
        moves, towards, most = 0, 0.0, (-1, -1, -1)  # a move to search elsewhere comes between two turns
        while found is None:
            _, q = self._look(localizing=True)
            inliers = 0
            if near:
                local = self.localizer.localize_query(q, exclude=away)
                inliers = local.verification.inliers if local.verification is not None else 0
                if inliers >= cfg.switch_min_inliers:
                    if cfg.recover_scale_tolerance is None:
                        found = (local.node, f"verified near node {self._last_good} ({inliers} inliers)")
                    else:
                        node, inliers, scale = self._nearest_verified(q, local)
                        at = f", the scene at {scale:.2f}x" if math.isfinite(scale) else ""
                        found = (node, f"verified near node {self._last_good} ({inliers} inliers{at})")
                    break
                if inliers >= min_inliers and (best_local is None or inliers > best_local[0]):
                    best_local = (inliers, local.node)
            loc = self.localizer.localize_query(q)
            if loc.localized and loc.node in near:
                found = (loc.node, f"confidence {loc.confidence:.2f}")
                break
            confident = loc.localized and (loc.confidence >= cfg.recover_far_confidence or not loc.calibrated)
            if confident and not self._within_reach(loc.node):
                self._count("far answers out of reach")
                confident = False
            if confident and far is not None and (far == loc.node or far in self.map.neighbours(loc.node)):
                found = (loc.node, f"confidence {loc.confidence:.2f}, confirmed by a second look")
                self._count("far re-localizations")
                break
            far = loc.node if confident else None
            # the view to move towards: a near node's best verification, else any, else the most textured
            score = (inliers, loc.inliers, len(q.features))
            if score > most and turned < 2 * math.pi:
                towards, most = turned, score
            if turned >= 2 * math.pi:
                if moves >= cfg.recover_search_moves or cfg.start_search_step_m == 0:
                    break
                self._hold()
                self._count("searched", math.degrees(turned))
                self._search_move(towards - turned, "recovery search moves")
                moves += 1
                # what the last turn saw weakly was seen from elsewhere
                turned, far, best_local, towards, most = 0.0, None, None, 0.0, (-1, -1, -1)
                continue
            turned += self._scan_step()  # search: turn for scan_every_s, then look again
        self._hold()
        if turned > 0:
            self._count("searched", math.degrees(turned))
        confirmed = found is not None  # a weak near node or the last good one confirms nothing
        if found is None:
            if best_local is not None:
                found = (best_local[1], f"best near node {self._last_good} ({best_local[0]} inliers)")
            elif self._last_good is not None or self._here is not None:
                keep = self._last_good if self._last_good is not None else self._here
                found = (keep, "nothing verified in a full turn: kept the last good node")
            else:
                raise _Failed(NavStatus.FAILED, "could not localize in the map after a full turn")
        self._count("re-localizations")
        if confirmed:
            self._confirmed = (found[0], self._commanded_m)
        self._here = found[0]
        yield NavEvent(EventKind.LOCALIZED, self._time, f"at node {found[0]} ({found[1]})", subgoal=found[0])

    def _within_reach(self, node: int) -> bool:
        """Whether the robot can be at ``node``: within ``recover_reach_slack_m`` plus
        ``recover_reach_factor`` x the distance it was commanded to drive since the track was last
        confirmed, along the map's edges measured on the floor from the node it was confirmed at.
        An edge its keyframes cannot measure counts as no distance (a turn in place; the reach errs
        towards taking the answer); a loop edge counts the slack more: it is appearance's claim of one
        place, which a stretch of look-alikes fakes (docs/navigation.md, "Far answers within reach").
        True when nothing bounds it: no confirmation, no camera height."""
        cfg = self.config
        if cfg.recover_reach_slack_m is None or self._confirmed is None or self._camera_height_m is None:
            return True
        if self._floor_graph is None:
            lengths = self.pairs.floor_lengths_m(self._camera_height_m)
            g = nx.Graph()
            g.add_nodes_from(self.map.nodes)
            g.add_weighted_edges_from(
                (a, b, lengths.get((a, b), 0.0) + (0.0 if e.kind is EdgeKind.SEQUENTIAL else cfg.recover_reach_slack_m))
                for (a, b), e in self.map.edges.items())
            self._floor_graph = g
        at, since = self._confirmed
        reach = cfg.recover_reach_slack_m + cfg.recover_reach_factor * (self._commanded_m - since)
        return node in nx.single_source_dijkstra_path_length(self._floor_graph, at, cutoff=reach)

    def _nearest_verified(self, q: Query, local: Localization) -> tuple[int, int, float]:
        """Of the near nodes the localizer shortlisted, the one the robot is at. Among those that verify
        with ``switch_min_inliers`` (the servo's matcher), the ones showing the scene at the frame's
        scale within ``recover_scale_tolerance`` (:func:`~topomap.matching.scene_scale`), the most
        inliers first; without one, the scale closest to the frame's — a keyframe metres farther down
        the same view verifies as well, often with more inliers; with no such node, the best verified.
        Returns (node, inliers, scale of the scene in the frame over the keyframe; NaN if not chosen by it)."""
        shortlist = [local.node] + [c.node for c in local.candidates if c.node != local.node and c.inliers >= 0]
        checks = [(n, self._match(q, n)) for n in shortlist]
        good = [(n, v) for n, v in checks if v.inliers >= self.config.switch_min_inliers]
        if not good:
            node, v = max(checks, key=lambda c: c[1].inliers)  # the first of equals: the localizer's order
            return node, v.inliers, math.nan
        scales = [scene_scale(q.features, self.map.nodes[n].features, v, self.camera, self.map.camera) for n, v in good]
        off = [abs(math.log(sc)) if math.isfinite(sc) and sc > 0 else math.inf for sc in scales]
        inside = [i for i in range(len(good)) if off[i] < math.log(self.config.recover_scale_tolerance)]
        k = (max(inside, key=lambda i: (good[i][1].inliers, -i)) if inside
             else min(range(len(good)), key=lambda i: (off[i], -good[i][1].inliers)))
        return good[k][0], good[k][1].inliers, scales[k]

    def _count(self, what: str, amount: float = 1.0) -> None:
        self._tried[what] = self._tried.get(what, 0.0) + amount

    def _tried_summary(self) -> str:
        """What recovery did so far, in words (the final failure message)."""
        t = self._tried
        parts = []
        if "backed off" in t:
            parts.append(f"backed off {t['backed off']:.0f} s toward nodes that verified well")
        if "searched" in t:
            parts.append(f"turned {t['searched']:.0f} deg in place searching")
        if "recovery search moves" in t:
            parts.append(f"moved {t['recovery search moves']:.0f} times to search elsewhere after turns that verified nothing")
        if "re-localizations" in t:
            parts.append(f"re-localized {t['re-localizations']:.0f} times ({t.get('far re-localizations', 0):.0f} far)")
        if "far answers out of reach" in t:
            parts.append(f"refused {t['far answers out of reach']:.0f} far answers out of reach")
        if "blocked by contact" in t:
            parts.append(f"reversed out of contact {t['blocked by contact']:.0f} times")
        if "back-offs ended by contact" in t:
            parts.append(f"ended {t['back-offs ended by contact']:.0f} back-offs at contact")
        if "loop closures distrusted" in t:
            parts.append(f"distrusted {t['loop closures distrusted']:.0f} loop closures")
        if "arrivals the floor refused" in t:
            parts.append(f"took the floor's scale at the goal {t['arrivals the floor refused']:.0f} times")
        if "arrivals the near floor refused" in t:
            parts.append(f"docked on the near floor after {t['arrivals the near floor refused']:.0f} refused arrivals")
        if "taught steps driven blind" in t:
            ended = t.get("blind steps ended by contact", 0)
            parts.append(f"drove {t['taught steps driven blind']:.0f} taught steps past subgoals that did not verify"
                         + (f" ({ended:.0f} ended at contact)" if ended else ""))
        return ", ".join(parts) or "nothing"

    def _turning_toward(self, s: ServoOutput) -> bool:
        """Blind, and the dead-reckoned heading to the subgoal still puts it outside the camera's
        view: the servo is turning toward it (at a corner taught as a turn in place the next
        keyframe lies a turn away; docs/theory.md section 4.4 keeps it in the field of view)."""
        theta = s.disturbance.theta
        return s.status is ServoStatus.LOST and math.isfinite(theta) and abs(theta) > self._half_fov_rad

    def _keyframe_heading(self, a: int, b: int) -> float:
        """Heading of keyframe ``a`` relative to keyframe ``b`` from their images [rad]; NaN when
        their matches give no planar pose."""
        pair = self.pairs.motion(a, b)
        return math.nan if pair is None else pair.theta_rad

    def _switch_reason(self, q: Query, s: ServoOutput, nxt: int, v: Verification) -> str:
        """Why the current intermediate subgoal counts as reached, or ``""``. Not while the floor
        measures it farther than ``switch_floor_max_m`` (:meth:`_floor_says_far`)."""
        cfg = self.config
        if self._floor_says_far(s):
            return ""
        aligned = math.isfinite(s.heading_error_rad) and abs(s.heading_error_rad) < math.radians(cfg.switch_heading_deg)
        if s.status is not ServoStatus.LOST and aligned:
            if math.isfinite(s.position_error_m) and s.position_error_m < cfg.switch_distance_m:
                return f"estimated {s.position_error_m:.2f} m away"
            if s.pose.status is PoseStatus.OK:
                if self._approach_side is None:
                    self._approach_side = math.copysign(1.0, s.pose.x_s)
                elif s.pose.x_s * self._approach_side < 0:
                    return "driven past it"
        vn = self._match(q, nxt)
        if vn.inliers >= cfg.switch_min_inliers and vn.inliers > v.inliers:
            return f"next node matches better ({vn.inliers} vs {v.inliers} inliers)"
        return ""

    def _floor_m(self, s: ServoOutput) -> float:
        """The distance to the servo's goal the floor measures in this image [m]; NaN without the
        camera height or a floor reading."""
        return s.floor_distance_h * self._camera_height_m if self._camera_height_m is not None else math.nan

    def _floor_says_far(self, s: ServoOutput) -> bool:
        """Records this period's floor reading of the current subgoal; True when the median of the last
        ``SWITCH_FLOOR_PERIODS`` readings (at least ``SWITCH_FLOOR_MIN_READINGS`` of them measured)
        exceeds ``switch_floor_max_m``. Driving a straight corridor against the taught direction, each
        node behind looks down the same corridor: the servo said "0.19 m away" and the next node
        "matched better" 1.2-2 m out, while the floor measured 1.0-1.8 m (fresh office world 259 ep 3).

        On a taught chain walked backwards, also True while the floor has not been heard yet: fewer
        than ``SWITCH_FLOOR_MIN_READINGS`` readings in the ``SWITCH_FLOOR_PERIODS`` periods since the
        subgoal became the target, where its keyframe shows floor. Such a subgoal lies behind the
        camera, and the first estimates of it are the ones most often several times short: switches
        cascaded through three nodes in one period, to a subgoal 1.8 m behind whose posters had been
        moved (``moved`` world 254 ep 3). Ahead of the camera a switch made early leaves the next
        subgoal in view; behind it, each early switch takes the next one farther out of its view."""
        bound = self.config.switch_floor_max_m
        if bound is None or self._camera_height_m is None:
            return False
        self._subgoal_floor_m.append(self._floor_m(s))
        floor = np.array(self._subgoal_floor_m)
        floor = floor[np.isfinite(floor)]
        if len(floor) < SWITCH_FLOOR_MIN_READINGS:
            return self._subgoal_waits_for_floor and len(self._subgoal_floor_m) < SWITCH_FLOOR_PERIODS
        return float(np.median(floor)) > bound
