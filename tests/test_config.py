"""topomap.config: frozen build configs, presets, validation, JSON round trips."""

from __future__ import annotations

import dataclasses
import json

import pytest

from topomap.config import (
    BUILD_PRESETS,
    BuildConfig,
    FeatureConfig,
    LocalizeConfig,
    MatchConfig,
    build_preset,
    from_dict,
    to_dict,
)
from topomap.errors import ConfigError
from topomap.features import DETECTORS


def test_presets_are_valid_and_frozen():
    assert {"default", "fast", "accurate", "dense"} <= set(BUILD_PRESETS)
    for name, cfg in BUILD_PRESETS.items():
        assert build_preset(name) is cfg
        assert cfg.features.kind in DETECTORS, name
        assert cfg.keyframe_min_inliers > 3  # servoing needs far more than the 3-point minimum
    with pytest.raises(dataclasses.FrozenInstanceError):
        BUILD_PRESETS["default"].seed = 3  # type: ignore[misc]
    assert BUILD_PRESETS["default"] == BuildConfig()


def test_unknown_preset_lists_choices():
    with pytest.raises(ConfigError, match="unknown build preset 'turbo'; choose one of: accurate, default, dense, fast"):
        build_preset("turbo")


@pytest.mark.parametrize("name", sorted(BUILD_PRESETS))
def test_round_trip_through_json(name):
    cfg = BUILD_PRESETS[name]
    data = json.loads(json.dumps(to_dict(cfg)))
    assert from_dict(BuildConfig, data) == cfg


def test_from_dict_defaults_and_rejects():
    partial = {"keyframe_min_inliers": 70, "features": {"kind": "sift"}}
    cfg = from_dict(BuildConfig, partial)
    assert cfg.keyframe_min_inliers == 70 and cfg.features.kind == "sift"
    assert cfg.features.max_features == FeatureConfig().max_features and cfg.match == MatchConfig()
    with pytest.raises(ConfigError, match="no option"):
        from_dict(BuildConfig, {"warp_speed": 9})
    with pytest.raises(ConfigError, match="mapping"):
        from_dict(BuildConfig, [1, 2])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: FeatureConfig(max_features=4), "max_features"),
        (lambda: FeatureConfig(resize_max_px=16), "resize_max_px"),
        (lambda: MatchConfig(ratio=1.5), "ratio"),
        (lambda: MatchConfig(ransac_px=0), "ransac_px"),
        (lambda: MatchConfig(min_inliers=5), "min_inliers"),
        (lambda: BuildConfig(keyframe_min_inliers=10), "keyframe_min_inliers"),
        (lambda: BuildConfig(loop_min_inliers=10), "loop_min_inliers"),
        (lambda: BuildConfig(keyframe_min_ratio=1.0), "keyframe_min_ratio"),
        (lambda: BuildConfig(loop_shortlist_k=0), "loop_shortlist_k"),
        (lambda: BuildConfig(loop_edges_per_visit=-1), "loop_edges_per_visit"),
        (lambda: BuildConfig(loop_revisit_ratio=0.0), "loop_revisit_ratio"),
        (lambda: BuildConfig(vocabulary_words=4), "vocabulary_words"),
        (lambda: LocalizeConfig(bow_max_postings=0), "bow_max_postings"),
        (lambda: LocalizeConfig(bow_max_postings=1.5), "bow_max_postings"),
        (lambda: LocalizeConfig(declare_min_frame_ratio=0.9), "declare_min_frame_ratio"),
        (lambda: LocalizeConfig(declare_min_inliers=-1), "declare_min_inliers"),
        (lambda: LocalizeConfig(declare_min_frame_ratio=20.0), "declare_min_frame_ratio"),
    ],
)
def test_validation(make, match):
    with pytest.raises(ConfigError, match=match):
        make()
