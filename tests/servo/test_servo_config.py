"""The servo part of topomap.config: presets, validation, JSON round trip."""

from __future__ import annotations

import json

import pytest

from topomap.config import (
    SERVO_PRESETS,
    RelativePoseConfig,
    ScaleConvention,
    ServoConfig,
    UnicycleLaw,
    from_dict,
    servo_preset,
    to_dict,
)
from topomap.errors import ConfigError


def test_presets_and_unknown_preset():
    assert set(SERVO_PRESETS) >= {"default", "uncompensated"}
    assert servo_preset("uncompensated").compensate is False
    assert servo_preset("floor").geometry.scale is ScaleConvention.CAMERA_HEIGHT
    assert servo_preset("aicardi").unicycle_law is UnicycleLaw.AICARDI
    with pytest.raises(ConfigError, match="unknown servo preset 'fast'; choose one of: aicardi, default"):
        servo_preset("fast")


@pytest.mark.parametrize("name", sorted(SERVO_PRESETS))
def test_round_trip_through_json(name):
    cfg = SERVO_PRESETS[name]
    back = from_dict(ServoConfig, json.loads(json.dumps(to_dict(cfg))))
    assert back == cfg


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(max_speed_mps=0.0), "max_speed_mps"),
        (dict(k_i=-1.0), "k_i"),
        (dict(unicycle_law="pid"), "choose one of: aicardi, scale_free"),
        (dict(dock_radius_m=0.3, undock_radius_m=0.1), "undock_radius_m"),
        (dict(pose_window=0), "pose_window"),
        (dict(pose_window=2.5), "pose_window"),
    ],
)
def test_bad_values_are_rejected(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        ServoConfig(**kwargs)


def test_geometry_config_validation():
    with pytest.raises(ConfigError, match="rotation_f_ratio"):
        RelativePoseConfig(rotation_f_ratio=1.0)
    with pytest.raises(ConfigError, match="unknown ServoConfig option|has no option"):
        from_dict(ServoConfig, {"warp_drive": 1})


def test_string_choices_become_enums():
    """Names (presets, CLI, JSON) are accepted and stored as the enums; unknown names list the choices."""
    assert RelativePoseConfig(scale="CAMERA_HEIGHT").scale is ScaleConvention.CAMERA_HEIGHT
    assert ServoConfig(unicycle_law="aicardi") == ServoConfig(unicycle_law=UnicycleLaw.AICARDI)
    assert json.loads(json.dumps(to_dict(ServoConfig())))["unicycle_law"] == "scale_free"
    with pytest.raises(ConfigError, match="choose one of: camera_height, median_depth"):
        RelativePoseConfig(scale="furthest")
