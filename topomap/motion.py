"""Vehicle kinds and velocity commands shared by the servo (which computes them) and any vehicle
(the simulator or a real robot) that executes them — docs/theory.md section 1, eq. 1.7-1.8.

The commanded input is ``u = (v_f, v_h, omega)``: forward and sideways (leftward) speed in the
vehicle frame and turning rate. A unicycle has ``v_h = 0``. Pose ``xi = (x, z, theta)``:
``xi' = G(theta) (u + d)`` with ``G = [[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]]``, so in the floor
plan drawn with x to the right and z upwards, theta and omega turn counter-clockwise and v_h points
to the vehicle's left.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from topomap.errors import parse_enum

__all__ = ["VehicleKind", "Command", "vehicle_kind", "wrap_angle", "saturate"]


def wrap_angle(a):
    """Angle(s) [rad] wrapped to [-pi, pi): a float for a scalar, an array for an array."""
    if np.ndim(a):
        return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
    return (float(a) + math.pi) % (2 * math.pi) - math.pi


def saturate(x: float, limit: float) -> float:
    """``x`` clipped to ``[-limit, limit]`` (one channel of a command)."""
    return max(-limit, min(limit, x))


class VehicleKind(str, enum.Enum):
    """Kinematic model of the vehicle (docs/theory.md section 1)."""

    UNICYCLE = "unicycle"  # u = (v_f, 0, omega)
    OMNI = "omni"  # u = (v_f, v_h, omega)


def vehicle_kind(name: str | VehicleKind) -> VehicleKind:
    """Parse a vehicle name; an unknown one lists the valid choices."""
    return parse_enum(VehicleKind, name, "vehicle")


@dataclass(frozen=True)
class Command:
    """Velocity command ``u`` in the vehicle frame.

    ``v_f`` forward speed [m/s], ``v_h`` sideways speed, positive to the vehicle's left [m/s],
    ``omega`` turning rate, positive counter-clockwise in the floor plan [rad/s].
    """

    v_f: float = 0.0
    v_h: float = 0.0
    omega: float = 0.0

    def __post_init__(self) -> None:
        for name in ("v_f", "v_h", "omega"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"command {name}={v} is not finite")  # a bug in the caller, not user input

    def as_tuple(self) -> tuple[float, float, float]:
        return (self.v_f, self.v_h, self.omega)

    def clipped(self, max_speed_mps: float, max_turn_rps: float) -> Command:
        """The same command with each channel saturated to the given limits."""
        return Command(saturate(self.v_f, max_speed_mps), saturate(self.v_h, max_speed_mps), saturate(self.omega, max_turn_rps))

    def for_vehicle(self, kind: VehicleKind) -> Command:
        """Drop the sideways channel for a unicycle."""
        return Command(self.v_f, 0.0, self.omega) if kind is VehicleKind.UNICYCLE else self


STOP = Command()
