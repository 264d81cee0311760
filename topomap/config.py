"""Frozen configuration dataclasses and their named presets.

Every stage takes one frozen dataclass; a map stores the :class:`BuildConfig` it was built with
(as JSON, see :func:`to_dict` / :func:`from_dict`) so it remembers how it was made. Units are in
the field names or in the comment beside them.

Presets are plain dicts of ready-made configs: ``BUILD_PRESETS["default"]``. An unknown name raises
:class:`~topomap.errors.ConfigError` listing the valid ones (:func:`build_preset`).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field

from topomap.errors import ConfigError, unknown_choice

__all__ = [
    "FeatureConfig",
    "MatchConfig",
    "BuildConfig",
    "BUILD_PRESETS",
    "build_preset",
    "to_dict",
    "from_dict",
]


@dataclass(frozen=True)
class FeatureConfig:
    """Local features (see :mod:`topomap.features`)."""

    kind: str = "orb"  # a key of topomap.features.DETECTORS: orb | sift | akaze
    max_features: int = 1000  # keep the strongest N keypoints
    resize_max_px: int | None = None  # shrink images whose longest side exceeds this [px]
    upscale_min_px: int = 320  # enlarge images whose longest side is below this [px] (tiny cameras)
    fast_threshold: int = 12  # ORB FAST threshold; lower finds more corners on weak texture

    def __post_init__(self) -> None:
        if self.max_features < 8:
            raise ConfigError(f"max_features={self.max_features} is too small; use at least 8")
        if self.resize_max_px is not None and self.resize_max_px < 32:
            raise ConfigError(f"resize_max_px={self.resize_max_px} is too small; use at least 32")


@dataclass(frozen=True)
class MatchConfig:
    """Descriptor matching and geometric (epipolar) verification (see :mod:`topomap.matching`)."""

    ratio: float = 0.8  # Lowe ratio test threshold (best / second best distance)
    mutual: bool = True  # keep only mutual nearest neighbours
    ransac_px: float = 1.5  # epipolar inlier threshold at the working resolution [px]
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    min_inliers: int = 15  # fewer verified matches than this = "no geometric relation"
    seed: int = 0  # RANSAC random state

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"ratio={self.ratio} must lie in (0, 1]")
        if self.ransac_px <= 0:
            raise ConfigError(f"ransac_px={self.ransac_px} must be positive")
        if self.min_inliers < 8:
            raise ConfigError(f"min_inliers={self.min_inliers} must be at least 8 (fundamental matrix)")


@dataclass(frozen=True)
class BuildConfig:
    """Image sequence -> keyframes -> edges (see :mod:`topomap.build`)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    # A frame joins the current keyframe while they share at least this many verified matches;
    # below it a new node starts. Servoing along an edge needs many more than the 3-point minimum
    # (THESIS.md sections 3-4), hence far above 3.
    keyframe_min_inliers: int = 60
    # ... and while the verified matches keep at least this fraction of the keyframe's features.
    keyframe_min_ratio: float = 0.15
    # Loop closure: an edge joins two non-consecutive nodes sharing this many verified matches.
    loop_min_inliers: int = 40
    loop_min_inlier_ratio: float = 0.25  # ... and this fraction of the tentative matches
    loop_shortlist_k: int = 8  # appearance candidates checked geometrically per new node
    vocabulary_words: int = 1024  # visual words of the place-recognition index
    thumbnail_px: int = 128  # longest side of the stored thumbnails [px]
    store_images: bool = True  # store each keyframe image (PNG) in the map
    seed: int = 0  # every random choice (vocabulary k-means, RANSAC) derives from this

    def __post_init__(self) -> None:
        if self.keyframe_min_inliers < self.match.min_inliers:
            raise ConfigError(
                f"keyframe_min_inliers={self.keyframe_min_inliers} must be >= match.min_inliers={self.match.min_inliers}"
            )
        if self.loop_min_inliers < self.match.min_inliers:
            raise ConfigError(
                f"loop_min_inliers={self.loop_min_inliers} must be >= match.min_inliers={self.match.min_inliers}"
            )
        if not 0 <= self.keyframe_min_ratio < 1:
            raise ConfigError(f"keyframe_min_ratio={self.keyframe_min_ratio} must lie in [0, 1)")
        if self.loop_shortlist_k < 1:
            raise ConfigError("loop_shortlist_k must be at least 1")
        if self.vocabulary_words < 16:
            raise ConfigError("vocabulary_words must be at least 16")


BUILD_PRESETS: dict[str, BuildConfig] = {
    # ORB, 1000 features: real-time friendly, the default of `topomap build`.
    "default": BuildConfig(),
    # Fewer, cheaper features on downscaled images: long videos, slow machines.
    "fast": BuildConfig(
        features=FeatureConfig(max_features=500, resize_max_px=640),
        keyframe_min_inliers=40,
        loop_min_inliers=30,
        loop_shortlist_k=5,
    ),
    # SIFT, 2000 features: high-resolution photographs, wide baselines, loop-rich scenes.
    "accurate": BuildConfig(
        features=FeatureConfig(kind="sift", max_features=2000),
        match=MatchConfig(ratio=0.8, ransac_px=1.5),
        keyframe_min_inliers=80,
        loop_min_inliers=40,
        loop_shortlist_k=12,
    ),
    # Dense keyframes (teach-and-repeat): nodes close together, servoing between them is easy.
    "dense": BuildConfig(keyframe_min_inliers=120, keyframe_min_ratio=0.35),
}


def build_preset(name: str) -> BuildConfig:
    """The named :class:`BuildConfig`; unknown names list the valid ones."""
    try:
        return BUILD_PRESETS[name]
    except KeyError:
        raise unknown_choice("build preset", name, BUILD_PRESETS) from None


# ---------------------------------------------------------------------- (de)serialisation
def to_dict(cfg) -> dict:
    """A config dataclass as plain JSON-able dicts (nested configs become nested dicts)."""
    return dataclasses.asdict(cfg)


def from_dict(cls, data: dict):
    """Rebuild config ``cls`` from :func:`to_dict` output; unknown keys are rejected, missing ones default.

    Keys missing from ``data`` take today's defaults, so maps written by an older topomap load.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{cls.__name__} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(f"{cls.__name__} has no option(s) {', '.join(sorted(unknown))}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            value = from_dict(hint, value)
        elif typing.get_origin(hint) is tuple or (
            isinstance(hint, types.GenericAlias) and hint.__origin__ is tuple
        ):
            value = tuple(value)
        kwargs[f.name] = value
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise ConfigError(f"bad {cls.__name__}: {e}") from None
