"""Vehicle kinds, commands, and the one angle wrap and channel clip (topomap.motion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topomap.errors import ConfigError
from topomap.motion import Command, VehicleKind, saturate, vehicle_kind, wrap_angle


def test_wrap_angle_is_half_open_and_keeps_scalars_and_arrays():
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)  # [-pi, pi): +pi maps to -pi
    assert wrap_angle(-math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert isinstance(wrap_angle(np.float64(7.0)), float)
    a = wrap_angle(np.array([0.0, 2 * math.pi + 0.1, -7.0]))
    assert isinstance(a, np.ndarray) and a.shape == (3,)
    assert np.allclose(a, [0.0, 0.1, -7.0 + 2 * math.pi])


def test_saturate_and_clipped_agree():
    assert saturate(2.0, 0.5) == 0.5 and saturate(-2.0, 0.5) == -0.5 and saturate(0.1, 0.5) == 0.1
    c = Command(1.0, -1.0, 3.0).clipped(0.3, 0.6)
    assert c == Command(0.3, -0.3, 0.6)


def test_vehicle_kind_parses_strings_and_rejects_unknown():
    assert vehicle_kind("OMNI") is VehicleKind.OMNI
    with pytest.raises(ConfigError, match="unicycle"):
        vehicle_kind("tank")
