"""What one control step of the navigator saw, for drawing: its matches and its numbers.

The navigator's STEP events carry the matched pixels the servo used (``NavEvent.matches``) and the
servo's output, whose pose marks the matches it kept; :func:`step_matches` packs them with the map's
working size, so drawings show exactly what the servo used. Nothing here is fed back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from topomap.graph import TopoMap

__all__ = ["StepMatches", "step_matches", "keyframe_image", "status_lines"]


@dataclass(frozen=True)
class StepMatches:
    """The matches a control step servoed on, at the map's working resolution.

    ``cur_px``: (N, 2) float32 pixels in the current image; ``goal_px``: (N, 2) float32 pixels of the
    same features in the subgoal keyframe; ``inlier``: (N,) bool, the matches the servo's planar pose
    kept (all False when it found no geometry); ``size``: ``(width, height)`` of both.
    """

    cur_px: np.ndarray
    goal_px: np.ndarray
    inlier: np.ndarray
    size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.cur_px)

    @classmethod
    def empty(cls, size: tuple[int, int]) -> StepMatches:
        z = np.zeros((0, 2), np.float32)
        return cls(z, z, np.zeros(0, bool), size)


def step_matches(tmap: TopoMap, ev) -> StepMatches:
    """The matches of a STEP event (empty when it carries none), with the servo's inliers."""
    size = tuple(tmap.working_size)
    if ev.matches is None or len(ev.matches[0]) == 0:
        return StepMatches.empty(size)
    cur, goal = (np.asarray(a, np.float32).reshape(-1, 2) for a in ev.matches)
    mask = getattr(getattr(ev.servo, "pose", None), "inlier_mask", None)
    inlier = np.asarray(mask, bool) if mask is not None and len(mask) == len(cur) else np.zeros(len(cur), bool)
    return StepMatches(cur, goal, inlier, size)


def keyframe_image(tmap: TopoMap, node: int) -> np.ndarray:
    """The node's keyframe, ``(H, W) uint8`` at the working resolution when the map holds it (else
    its thumbnail)."""
    n = tmap.nodes[node]
    return n.image if n.image is not None else n.thumbnail


def _fmt(x: float, spec: str, unit: str) -> str:
    if not math.isfinite(x):
        return "--"
    text = f"{x:{spec}}"
    if text.startswith("-") and float(text) == 0.0:  # "-0.00": a tiny negative value reads as noise
        text = "+" + text[1:] if "+" in spec else text[1:]
    return f"{text} {unit}"


def status_lines(ev, matches: StepMatches | None = None) -> list[str]:
    """The step's status as short text lines: time, servo status, subgoal and route position;
    estimated distance and heading; inliers; the command."""
    s = ev.servo
    route = list(ev.route)
    hop = f" ({route.index(ev.subgoal) + 1}/{len(route)} of the route to {route[-1]})" if ev.subgoal in route else ""
    lines = [f"t {ev.time_s:6.1f} s   {s.status.value.upper() if s else '':<11}  subgoal node {ev.subgoal}{hop}"]
    if s is not None:
        head = math.degrees(s.heading_error_rad) if math.isfinite(s.heading_error_rad) else math.nan
        n = len(matches) if matches is not None else s.pose.n_matches
        lines.append(f"estimated distance {_fmt(s.position_error_m, '.2f', 'm')}   heading {_fmt(head, '+.1f', 'deg')}"
                     f"   inliers {s.inliers}/{n}")
    c = ev.command
    if c is not None:
        lines.append(f"command  v {_fmt(c.v_f, '+.2f', 'm/s')}" + (f"  v_h {_fmt(c.v_h, '+.2f', 'm/s')}" if abs(c.v_h) > 0 else "")
                     + f"  w {_fmt(c.omega, '+.2f', 'rad/s')}")
    return lines
