"""Frozen configuration dataclasses and their named presets.

Every stage takes one frozen dataclass; a map stores the :class:`BuildConfig` it was built with
(as JSON, see :func:`to_dict` / :func:`from_dict`) so it remembers how it was made. Units are in
the field names or in the comment beside them.

Presets are plain dicts of ready-made configs: ``BUILD_PRESETS["default"]``. An unknown name raises
:class:`~topomap.errors.ConfigError` listing the valid ones (:func:`build_preset`).
"""

from __future__ import annotations

import dataclasses
import enum
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from topomap.errors import ConfigError, choose, parse_enum, unknown_choice

_P = typing.TypeVar("_P")

__all__ = [
    "FeatureConfig",
    "MatchConfig",
    "BuildConfig",
    "LocalizeConfig",
    "BUILD_PRESETS",
    "build_preset",
    "to_dict",
    "from_dict",
    "preset_with_overrides",
]


class ScaleConvention(str, enum.Enum):
    """What the unknown scale lambda of a relative pose is (:mod:`topomap.servo.pose`)."""

    MEDIAN_DEPTH = "median_depth"  # the goal image's median inlier depth
    CAMERA_HEIGHT = "camera_height"  # the camera's height above the (visible, textured) floor


def scale_convention(name: str | ScaleConvention) -> ScaleConvention:
    """Parse a scale convention name; an unknown one lists the valid choices."""
    return parse_enum(ScaleConvention, name, "scale convention")


class UnicycleLaw(str, enum.Enum):
    """The unicycle's steering law away from the goal (docs/theory.md section 3, :mod:`topomap.servo.laws`)."""

    SCALE_FREE = "scale_free"  # steers with the observed ratio (v + d_v) / e: right for any scale
    AICARDI = "aicardi"  # Aicardi's nominal law: exact only when lambda = nominal_scale_m


def parse_unicycle_law(name: str | UnicycleLaw) -> UnicycleLaw:
    """Parse a unicycle law name; an unknown one lists the valid choices."""
    return parse_enum(UnicycleLaw, name, "unicycle law")


#: Most keypoints per image: 100k SIFT descriptors already take 51 MB per image.
MAX_FEATURES = 100_000


@dataclass(frozen=True)
class FeatureConfig:
    """Local features (see :mod:`topomap.features`)."""

    kind: str = "orb"  # a key of topomap.features.DETECTORS: orb | sift | akaze
    max_features: int = 1000  # keep the strongest N keypoints
    resize_max_px: int | None = None  # shrink images whose longest side exceeds this [px]
    upscale_min_px: int = 480  # enlarge images whose longest side is below this [px]: tiny cameras
    # leave ORB's scale pyramid no room (corridor 160x120: exhaustive Recall@1 0.46 at 320 px, 0.70 at 480)
    max_upscale: float = 3.0  # ... but never by more than this: beyond it keypoints sit on interpolation artefacts
    fast_threshold: int = 12  # ORB FAST threshold; lower finds more corners on weak texture

    def __post_init__(self) -> None:
        if self.max_features < 8:
            raise ConfigError(f"max_features={self.max_features} is too small; use at least 8")
        if self.max_features > MAX_FEATURES:
            raise ConfigError(f"max_features={self.max_features} is too large; use at most {MAX_FEATURES}")
        if self.resize_max_px is not None and self.resize_max_px < 32:
            raise ConfigError(f"resize_max_px={self.resize_max_px} is too small; use at least 32")


#: Robust estimators for the fundamental matrix of a verification (``MatchConfig.ransac_method``).
RANSAC_METHODS = {"magsac": "OpenCV USAC MAGSAC++", "prosac": "OpenCV USAC PROSAC (best descriptor matches first)"}


@dataclass(frozen=True)
class MatchConfig:
    """Descriptor matching and geometric (epipolar) verification (see :mod:`topomap.matching`)."""

    ratio: float = 0.8  # Lowe ratio test threshold (best / second best distance)
    mutual: bool = True  # keep only mutual nearest neighbours
    ransac_px: float = 1.5  # epipolar inlier threshold at the working resolution [px]
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    # magsac: OpenCV USAC MAGSAC++; prosac: USAC PROSAC, hypotheses drawn from the best descriptor
    # matches first (Chum & Matas 2005) — as many inliers in half the iterations (localization)
    ransac_method: str = "magsac"
    min_inliers: int = 15  # fewer verified matches than this = "no geometric relation"
    seed: int = 0  # RANSAC random state

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"ratio={self.ratio} must lie in (0, 1]")
        if self.ransac_px <= 0:
            raise ConfigError(f"ransac_px={self.ransac_px} must be positive")
        if self.min_inliers < 8:
            raise ConfigError(f"min_inliers={self.min_inliers} must be at least 8 (fundamental matrix)")
        if self.ransac_method not in RANSAC_METHODS:
            raise unknown_choice("ransac_method", self.ransac_method, RANSAC_METHODS)


#: How keyframe images and thumbnails are encoded in the map (``BuildConfig.image_format``).
IMAGE_FORMATS = {"jpeg": "lossy, quality BuildConfig.image_quality", "png": "lossless"}


@dataclass(frozen=True)
class CalibrationConfig:
    """Self-supervised calibration of localization confidence at build / index time
    (:mod:`topomap.self_supervision`): ``queries`` keyframes give four samples each; maps with fewer
    than ``min_nodes`` nodes are left uncalibrated (under ~200 samples fit the seven weights poorly)."""

    enabled: bool = True
    queries: int = 60
    min_nodes: int = 50

    def __post_init__(self) -> None:
        if self.queries < 10 or self.min_nodes < 10:
            raise ConfigError("calibration queries and min_nodes must be at least 10")


@dataclass(frozen=True)
class BuildConfig:
    """Image sequence -> keyframes -> edges (see :mod:`topomap.build`)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    # A frame joins the current keyframe while they share at least this many verified matches;
    # below it a new node starts. Servoing along an edge needs many more than the 3-point minimum
    # (docs/theory.md sections 3-4), hence far above 3.
    keyframe_min_inliers: int = 60
    # ... and while the verified matches keep at least this fraction of the keyframe's features ...
    keyframe_min_ratio: float = 0.1
    # ... and moved less than this fraction of the image width (median): servoing across a large
    # image motion (a corner turned in one step) pushes the features out of view.
    keyframe_max_flow: float = 0.15
    # Loop closure: an edge joins two non-consecutive nodes sharing this many verified matches.
    loop_min_inliers: int = 40
    loop_min_inlier_ratio: float = 0.25  # ... and this fraction of the tentative matches
    loop_shortlist_k: int = 8  # appearance candidates checked geometrically per new node, within its
    # own sequence and again among the other sequences (so --append links to the existing map)
    # Nodes of one sequence fewer than this many sequential steps apart are not loop candidates:
    # they are already joined by a short path (a shortcut there closes no loop).
    loop_min_separation: int = 3
    # Sparser loop closures (RTAB-Map-like; both off by default: the denser graph's neighbourhoods make
    # the localizer more confident and the navigator starts more often, docs/build.md "Loop closures"):
    # keep, of a new node's verified candidates, the best (most inliers) of each *visit* — candidates
    # of another stretch of the chains fewer than loop_min_separation steps apart — 0 keeps all ...
    loop_edges_per_visit: int = 0
    # ... and take a candidate of the node's own sequence only where the camera left the place and came
    # back: some keyframe of the chain between them scores under this fraction of the candidate's
    # appearance score against the node (down a corridor every keyframe still shows its far end, and
    # a "loop" there joins places metres apart). None: no such test.
    loop_revisit_ratio: float | None = None
    # A loop closure needs this many of its inliers above the image's centre row in both images (off
    # the floor for a level camera): floors repeat (tiles, carpet), and a match on the floor alone
    # aliases by a tile — simulated offices held loop edges 2-18 m and up to 180 deg long that way.
    loop_min_off_floor_inliers: int = 10
    vocabulary_words: int = 65536  # upper bound on visual words; the map's descriptors decide (8 per word)
    thumbnail_px: int = 128  # longest side of the stored thumbnails [px]
    store_images: bool = True  # store each keyframe image in the map (False: maps that only localize)
    # Keyframe images and thumbnails: jpeg (lossy, ~6x smaller than png on camera images) or png.
    # Nothing in localization or navigation reads them (features and descriptors are stored apart):
    # they are for people and plots, so a modest JPEG quality keeps maps compact (docs/build.md).
    image_format: str = "jpeg"
    image_quality: int = 40  # JPEG quality of the keyframe images, 1..100
    thumbnail_quality: int = 85  # JPEG quality of the thumbnails, 1..100
    seed: int = 0  # every random choice (vocabulary k-means, RANSAC, calibration samples) derives from this
    # --append: a keyframe of the new experience is linked to the place the sequence filter answers
    # (over the other experiences) at this probability or more, where no loop closure joins it; None:
    # no alignment (topomap.alignment; a false link is worse than a missing one)
    align_min_confidence: float | None = 0.95
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def __post_init__(self) -> None:
        if self.keyframe_min_inliers < self.match.min_inliers:
            raise ConfigError(
                f"keyframe_min_inliers={self.keyframe_min_inliers} must be >= match.min_inliers={self.match.min_inliers}"
            )
        if self.align_min_confidence is not None and not 0.0 < self.align_min_confidence <= 1.0:
            raise ConfigError(f"align_min_confidence={self.align_min_confidence} must lie in (0, 1] (or None: no alignment)")
        if self.loop_min_inliers < self.match.min_inliers:
            raise ConfigError(
                f"loop_min_inliers={self.loop_min_inliers} must be >= match.min_inliers={self.match.min_inliers}"
            )
        if not 0 <= self.keyframe_min_ratio < 1:
            raise ConfigError(f"keyframe_min_ratio={self.keyframe_min_ratio} must lie in [0, 1)")
        if not 0 < self.keyframe_max_flow <= 1:
            raise ConfigError(f"keyframe_max_flow={self.keyframe_max_flow} must lie in (0, 1]")
        if self.loop_shortlist_k < 1:
            raise ConfigError("loop_shortlist_k must be at least 1")
        if not 0 <= self.loop_min_off_floor_inliers <= self.loop_min_inliers:
            raise ConfigError(f"loop_min_off_floor_inliers={self.loop_min_off_floor_inliers} must lie in "
                              f"[0, loop_min_inliers={self.loop_min_inliers}]")
        if self.loop_revisit_ratio is not None and not self.loop_revisit_ratio > 0:
            raise ConfigError(f"loop_revisit_ratio={self.loop_revisit_ratio} must be > 0 (or None: no revisit test)")
        if self.loop_edges_per_visit < 0:
            raise ConfigError("loop_edges_per_visit must be >= 0 (0: keep every verified loop candidate)")
        if self.vocabulary_words < 16:
            raise ConfigError("vocabulary_words must be at least 16")
        if self.image_format not in IMAGE_FORMATS:
            raise unknown_choice("image format", self.image_format, IMAGE_FORMATS)
        for name in ("image_quality", "thumbnail_quality"):
            if not 1 <= getattr(self, name) <= 100:
                raise ConfigError(f"{name}={getattr(self, name)} must lie in 1..100")
        if self.thumbnail_px < 8:
            raise ConfigError(f"thumbnail_px={self.thumbnail_px} is too small; use at least 8")


@dataclass(frozen=True)
class LocalizeConfig:
    """Frame -> node (see :mod:`topomap.localize`). Scores are in robust z-units of appearance."""

    descriptor: str = "auto"  # auto | fused | bow | thumbnail (topomap.localize.DESCRIPTORS)
    shortlist_k: int = 10  # nodes verified geometrically per query
    # fused descriptor on maps with more nodes than this: thumbnails are compared only for the
    # bag-of-words' best thumbnail_candidates nodes (all 100k thumbnails: ~35 ms per query; 2000: ~1 ms)
    thumbnail_candidates: int = 2000
    # At most this many postings read per query, its rarest words first (None: all): bounds the work on
    # huge maps, but costs recall where common words carry the match (docs/build.md, "Query at 1M").
    bow_max_postings: int | None = None
    # Verification matches a query descriptor only against the node's descriptors under the same
    # vocabulary-tree node (at the deepest level with <= match_groups nodes), ORB-SLAM's guided search:
    # ~0.3 ms instead of ~1.8 ms per candidate. Binary matches must also lie within guided_max_hamming
    # bits of ORB's 256, the same share of a longer descriptor's (AKAZE: 114 of 488): a group may offer
    # a single candidate, where the ratio test cannot judge (ORB-SLAM: 50).
    # Corridor, measured: 64 bits let chance inliers through (castle frames "localized" in sequence
    # mode on 27 % of frames), 56 and 60 none; R@1 single 0.631 / 0.640, AUC 0.529 / 0.505 (brute
    # force 0.622 / 0.449), sequence R@1 0.856 either way.
    guided_matching: bool = True
    match_groups: int = 2048
    guided_max_hamming: int = 60
    # The shortlist's RANSAC: PROSAC, 1000 hypotheses at most (the map's matcher: MAGSAC, 2000). On the
    # corridor's shortlists it verifies more right candidates (0.76 vs 0.71) in 0.95 ms instead of 1.76.
    verify_ransac_method: str = "prosac"
    verify_max_iters: int = 1000
    inlier_weight: float = 0.3  # score per verified inlier beyond chance (single frame) [z-units]
    beta: float = 0.4  # sharpness of the softmax turning scores into probabilities [1/z-unit]
    # Below min_confidence an answer is "unknown". On a calibrated map (topomap.calibration) the
    # confidence is the estimated probability that the answer is right, so 0.9 keeps the precision of
    # declared answers at about 0.95 (their mean probability); uncalibrated, it is the raw softmax mass.
    min_confidence: float = 0.9
    # A single frame is declared only when its answer verifies with at least this many inliers: look-alike
    # places (a repeated photograph, tiled floor) verify at 15-28 and the calibration, fitted on the map's
    # own views, can still give them 0.9-0.99 (docs/localization.md, "Chance-level verifications")
    declare_min_inliers: int = 25
    use_calibration: bool = True  # use the map's calibration when it has one fitted for this scoring
    # temporal filter (sequence mode): states are (node, speed along the map's sequence chain)
    max_speed_nodes: float = 1.5  # fastest motion along a chain [nodes/frame], both directions
    speed_step_nodes: float = 0.25  # resolution of the speed states [nodes/frame]
    # per frame, to the next faster or slower speed state: a camera keeps its speed (a speed holds
    # over SeqSLAM's 10-frame window with probability 0.74; at 0.1 the belief spread and lost the
    # track over dark frames, docs/localization.md)
    speed_change_probability: float = 0.03
    graph_hop_probability: float = 0.05  # per frame, along any map edge (loop closures, other sequences)
    jump_probability: float = 1e-3  # spread uniformly each frame: recovery after a kidnapping
    # "not in this map": a virtual place beside the map's states (as FAB-MAP's and RTAB-Map's).
    # Appearance scores cannot tell it (a frame from elsewhere scores like a mapped one against
    # the best of N nodes); geometry can: the filter's best node verifies (>= min_inliers epipolar
    # inliers) on about half the frames of a mapped place (corridor queries: 0.52) and on none of
    # an unmapped one's (castle, Nordland against the corridor: 0/60). Frames without the features to
    # verify leave the split unchanged, so appearance-only maps (Nordland) never go "elsewhere".
    elsewhere_state: bool = True
    verified_in_map: float = 0.3  # P(best node verifies | in the map), cautious
    verified_elsewhere: float = 0.01  # P(best node verifies | elsewhere): perceptual aliasing
    # ... with at least this many inliers: below it a verification is no evidence either way (chance
    # alignments with a look-alike place reach 15-19 inliers; docs/localization.md has the figures)
    elsewhere_min_inliers: int = 25
    # Appearance-only maps weigh "in the map" against "elsewhere" by how well each frame follows the
    # motion model (SequenceLocalizer); one frame moves the odds by at most this factor.
    max_frame_ratio: float = 10.0
    # ... and declares `localized` only on a frame that itself favours the map by this ratio: right
    # after the camera leaves the map the belief of the frames before would carry over (one frame
    # of another place declared at 0.91, measured: docs/localization.md)
    declare_min_frame_ratio: float = 1.2
    leave_probability: float = 0.02  # per frame, from the map to elsewhere
    enter_probability: float = 0.02  # per frame, from elsewhere back into the map
    # Degraded frames (night, noise, exposure): each node's score is also compared with its own
    # scores over the last recent_frames frames (SeqSLAM's contrast enhancement, along time) — a
    # node that matches every frame, e.g. a dark keyframe at night, says nothing about where the
    # camera is — weighted by how degraded the frame is (0 on a frame like the map's). 0 = off.
    recent_frames: int = 20
    # ... and on clean frames too by this much: a node that scores high against every frame (the
    # corridor's far end, seen from half its length) held a standing-still belief while the camera
    # walked 10 frames away from it (docs/localization.md)
    recent_min_weight: float = 0.4
    recent_min_spread: float = 0.5  # [z-units] a node's scores varying less than this: the same view

    def __post_init__(self) -> None:
        if self.shortlist_k < 0:
            raise ConfigError("shortlist_k must be >= 0")
        if self.match_groups < 1 or self.guided_max_hamming < 0 or self.verify_max_iters < 1 or self.thumbnail_candidates < 1:
            raise ConfigError("match_groups, verify_max_iters and thumbnail_candidates must be >= 1, guided_max_hamming >= 0")
        budget = self.bow_max_postings
        if budget is not None and (not isinstance(budget, int) or isinstance(budget, bool) or budget < 1):
            raise ConfigError(f"bow_max_postings={self.bow_max_postings!r} must be a positive integer or None")
        if self.verify_ransac_method not in RANSAC_METHODS:
            raise unknown_choice("verify_ransac_method", self.verify_ransac_method, RANSAC_METHODS)
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError(f"min_confidence={self.min_confidence} must lie in [0, 1]")
        for name in ("speed_change_probability", "graph_hop_probability", "jump_probability", "leave_probability",
                     "enter_probability"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ConfigError(f"{name} must lie in [0, 1)")
        if not 1.0 <= self.declare_min_frame_ratio <= self.max_frame_ratio:
            raise ConfigError("declare_min_frame_ratio must lie in [1, max_frame_ratio]")
        if not 0.0 <= self.recent_min_weight <= 1.0:
            raise ConfigError(f"recent_min_weight={self.recent_min_weight} must lie in [0, 1]")
        if self.elsewhere_min_inliers < 0 or self.declare_min_inliers < 0:
            raise ConfigError("elsewhere_min_inliers and declare_min_inliers must be >= 0")
        if not 0.0 < self.verified_elsewhere < self.verified_in_map < 1.0:
            raise ConfigError("need 0 < verified_elsewhere < verified_in_map < 1")
        if self.recent_frames < 0 or not self.recent_min_spread > 0:
            raise ConfigError("recent_frames must be >= 0 and recent_min_spread > 0")
        if self.max_frame_ratio < 1.0:
            raise ConfigError("max_frame_ratio must be >= 1")
        if self.beta <= 0 or self.speed_step_nodes <= 0 or self.max_speed_nodes < 0:
            raise ConfigError("beta and speed_step_nodes must be positive, max_speed_nodes >= 0")


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


def preset_with_overrides(spec: str, what: str, presets: Mapping[str, _P], names: Iterable[str]
                          ) -> tuple[_P, list[tuple[str, str]]]:
    """Split ``"PRESET"``, ``"key=value,..."`` or ``"PRESET,key=value,..."``: the named preset of
    ``presets`` (``"none"`` when no preset is named) and the ``(key, raw value)`` overrides, each key
    one of ``names``; the caller converts the values. Errors name ``what`` ("disturbance", ...)."""
    parts = [p.strip() for p in str(spec).split(",") if p.strip()]
    base = presets["none"]
    if parts and "=" not in parts[0]:
        base = choose(presets, parts.pop(0), f"{what} preset")
    names = set(names)
    items = []
    for p in parts:
        key, eq, val = p.partition("=")
        key = key.strip()
        if not eq:
            raise ConfigError(f"{what} item {p!r} must be key=value (only the first item may name a preset)")
        if key not in names:
            raise unknown_choice(f"{what} setting", key, names)
        items.append((key, val))
    return base, items


def build_preset(name: str) -> BuildConfig:
    """The named :class:`BuildConfig`; unknown names list the valid ones."""
    return choose(BUILD_PRESETS, name, "build preset")


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


# ---------------------------------------------------------------------- appearance servoing
# (docs/theory.md section 3; used by topomap.servo)
@dataclass(frozen=True)
class RelativePoseConfig:
    """Planar relative pose from matched points (see :mod:`topomap.servo.relpose`)."""

    ransac_px: float = 1.5  # inlier threshold on the reprojection error (depth eliminated) [px]
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 512  # 3-point hypotheses at most ...
    ransac_min_iters: int = 128  # ... and at least (wrong-heading models can gather many inliers)
    min_inliers: int = 12  # fewer inliers than this = TOO_FEW_INLIERS (3 is the bare minimum)
    seed: int = 0  # RANSAC random state
    scale: ScaleConvention = ScaleConvention.MEDIAN_DEPTH  # what lambda is (a name is accepted too)
    # The translation counts as observable when it explains the inliers this much better than a
    # pure rotation does (trimmed F statistic; ~1 means no evidence); otherwise PURE_ROTATION.
    rotation_f_ratio: float = 1.5
    min_abs_y: float = 0.02  # |y| below this (normalised, ~horizon) carries no depth ratio
    floor_min_y: float = 0.08  # camera_height scale: of the points this far below the horizon...
    floor_fraction: float = 0.3  # ... this lowest fraction (in the image) is taken to lie on the floor
    # The inliers count as one plane (a wall) when the planar-motion homography explains this
    # fraction of them (>= 1 disables); its solutions then replace the essential matrix's, which
    # slides along the wall's ambiguity. Only solutions with at least plane_min_visible of the
    # points on the plane's visible side are kept, and only when the translation is at least
    # plane_min_t_over_d of the plane's distance: nearer the goal every scene fits a homography
    # (parallax too small to tell a wall from a room). (median_depth scale only.)
    plane_inlier_fraction: float = 0.9
    plane_min_visible: float = 0.9
    plane_min_t_over_d: float = 0.05

    def __post_init__(self) -> None:
        if self.ransac_px <= 0:
            raise ConfigError(f"ransac_px={self.ransac_px} must be positive")
        if not 0 < self.ransac_confidence < 1:
            raise ConfigError(f"ransac_confidence={self.ransac_confidence} must lie in (0, 1)")
        if self.ransac_max_iters < 1:
            raise ConfigError("ransac_max_iters must be at least 1")
        if self.min_inliers < 3:
            raise ConfigError(f"min_inliers={self.min_inliers} must be at least 3 (docs/theory.md section 3)")
        object.__setattr__(self, "scale", scale_convention(self.scale))
        if self.rotation_f_ratio <= 1:
            raise ConfigError(f"rotation_f_ratio={self.rotation_f_ratio} must exceed 1")
        if not 0 < self.floor_fraction <= 1:
            raise ConfigError(f"floor_fraction={self.floor_fraction} must lie in (0, 1]")


@dataclass(frozen=True)
class ObserverConfig:
    """Disturbance observer (see :mod:`topomap.servo.disturbance`); noise levels of its Kalman filters."""

    # the two measurement noises below are floors: each filter takes the noise measured over its
    # last noise_window images where that is larger (second differences; 0 = the floors only)
    heading_noise_rad: float = 0.003  # std of one relative-heading measurement [rad]
    position_noise_s: float = 0.004  # std of one scaled-position measurement [lambda]
    noise_window: int = 10
    d_omega_walk: float = 0.05  # random-walk intensity of d_omega [rad/s per sqrt(s)]
    # std of one turn rate measured between consecutive images (observe_turn): wider than what they
    # measure (docs/servo.md), so that one such turn alone does not make the estimate `ready`
    turn_rate_noise_rps: float = 0.15
    d_omega_max: float = 0.5  # |d_omega_hat| is clipped to this [rad/s]
    forward_walk: float = 0.02  # random-walk intensity of the forward parameters [per sqrt(s)]
    # A new goal's first measured heading further than this from its predicted heading (the
    # previous goal's composed with the two keyframes') is a wrong reconstruction, up to three in a
    # row, and the prediction stays (None: the first measurement always replaces it) [deg]
    prior_gate_deg: float | None = 30.0

    def __post_init__(self) -> None:
        for name in ("heading_noise_rad", "position_noise_s", "d_omega_walk", "turn_rate_noise_rps", "d_omega_max", "forward_walk"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"observer {name}={getattr(self, name)} must be positive")
        if self.prior_gate_deg is not None and not 0 < self.prior_gate_deg <= 180:
            raise ConfigError(f"observer prior_gate_deg={self.prior_gate_deg} must lie in (0, 180] or be None")
        if isinstance(self.noise_window, bool) or not isinstance(self.noise_window, int) or self.noise_window < 0:
            raise ConfigError(f"observer noise_window={self.noise_window!r} must be a whole number >= 0")


@dataclass(frozen=True)
class ServoConfig:
    """Appearance servo: geometry + observer + control law (see :mod:`topomap.servo`).

    Positions reach the laws divided by the unknown scale lambda; the gains assume lambda equals
    ``nominal_scale_m`` (docs/theory.md section 3: a wrong guess only changes the loop gain).
    """

    geometry: RelativePoseConfig = field(default_factory=RelativePoseConfig)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    max_speed_mps: float = 0.3  # saturation of v_f and v_h [m/s]
    max_turn_rps: float = 0.6  # saturation of omega [rad/s]
    nominal_scale_m: float = 3.0  # lambda_0: metres per scaled unit assumed by the gains [m]
    # unicycle, Aicardi 1995 in polar coordinates (docs/theory.md section 3)
    unicycle_law: UnicycleLaw = UnicycleLaw.SCALE_FREE  # (a name is accepted too)
    gamma: float = 0.4  # forward gain [1/s]
    k_alpha: float = 1.2  # bearing gain k [1/s]
    h: float = 1.5  # weight of theta_A in the Lyapunov function
    # omnidirectional and final alignment
    k_p: float = 0.5  # position gain [1/s]
    k_theta: float = 1.0  # heading gain [1/s]
    k_i: float = 0.15  # integral gain on the scaled position error [1/s^2]
    integral_limit_mps: float = 0.08  # |integral action| at most this [m/s]
    integral_zone_m: float = 0.4  # integrate only this close to the goal (anti wind-up) [m] ...
    stall_time_s: float = 2.0  # ... and, unicycle outside the dock radius, only after this long ...
    stall_progress_m: float = 0.01  # ... without getting this much closer [m]
    compensate: bool = True  # cancel d_omega_hat and use integral action; False = nominal laws
    # near the goal a unicycle stops steering by the bearing (undefined at the goal) and aligns
    dock_radius_m: float = 0.06  # enter alignment inside this distance [m] ...
    undock_radius_m: float = 0.25  # ... and leave it beyond this one [m]
    position_tol_m: float = 0.03  # converged: estimated distance below this [m] ...
    heading_tol_deg: float = 1.5  # ... and |heading error| below this [deg]
    # the laws see the median of the last pose_window poses, each moved on by the motion predicted
    # since it was measured (facing a close wall one image's position scatters by ~0.1 m); 1 = raw
    pose_window: int = 5

    def __post_init__(self) -> None:
        for name in ("max_speed_mps", "max_turn_rps", "nominal_scale_m", "gamma", "k_alpha", "h", "k_p", "k_theta"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"servo {name}={getattr(self, name)} must be positive")
        for name in ("k_i", "integral_limit_mps", "integral_zone_m", "dock_radius_m", "position_tol_m", "heading_tol_deg"):
            if getattr(self, name) < 0:
                raise ConfigError(f"servo {name}={getattr(self, name)} must not be negative")
        object.__setattr__(self, "unicycle_law", parse_unicycle_law(self.unicycle_law))
        if self.undock_radius_m < self.dock_radius_m:
            raise ConfigError("undock_radius_m must be at least dock_radius_m")
        if isinstance(self.pose_window, bool) or not isinstance(self.pose_window, int) or self.pose_window < 1:
            raise ConfigError(f"servo pose_window={self.pose_window!r} must be a whole number of images >= 1")


SERVO_PRESETS: dict[str, ServoConfig] = {
    # Disturbance-compensating servo; unicycles use Aicardi's scale-free variant (steering with the
    # observed ratio r = (v + d_v) / e); median-depth scale.
    "default": ServoConfig(),
    # The same laws without d_omega cancellation nor integral action (the baseline of the benchmarks).
    "uncompensated": ServoConfig(compensate=False),
    # Aicardi's nominal law (r = gamma cos(alpha): exact only when lambda = nominal_scale_m).
    "aicardi": ServoConfig(unicycle_law=UnicycleLaw.AICARDI),
    # Metric scale from the camera height (needs a textured floor); nominal_scale_m = camera height.
    "floor": ServoConfig(geometry=RelativePoseConfig(scale=ScaleConvention.CAMERA_HEIGHT), nominal_scale_m=0.7),
}


def servo_preset(name: str) -> ServoConfig:
    """The named :class:`ServoConfig`; unknown names list the valid ones."""
    return choose(SERVO_PRESETS, name, "servo preset")


__all__ += ["ScaleConvention", "scale_convention", "UnicycleLaw", "parse_unicycle_law", "RelativePoseConfig", "ObserverConfig", "ServoConfig", "SERVO_PRESETS", "servo_preset"]


# ---------------------------------------------------------------------- route planning
# (docs/theory.md section 4: edge weight = how hard the servo along it is; used by topomap.plan)
@dataclass(frozen=True)
class PlanConfig:
    """Edge costs and re-planning (see :mod:`topomap.plan`). Costs are in *hops*: one easy edge ~ 1.

    A verified edge costs ``hop_cost + inlier_weight / (q + inlier_softening)
    + flow_weight * flow_px / diagonal_px`` with ``q = (inliers - n0) / n0`` the margin above the
    matcher's chance level ``n0 = match.min_inliers``; an edge below ``n0`` costs ``unverified_cost``.
    """

    hop_cost: float = 1.0  # every servo subtask (converge on an intermediate node) [hops]
    inlier_weight: float = 1.0  # [hops] at a margin q = 1 above chance (inliers = 2 n0), ~inlier_weight/2
    inlier_softening: float = 0.1  # q0: caps the inlier term at inlier_weight / q0 at the chance level
    flow_weight: float = 2.0  # [hops per image diagonal] of median image motion along the edge
    # An edge with fewer inliers than the chance level (frames that did not verify) is still
    # traversable but is taken only when every verified detour costs more than this [hops].
    unverified_cost: float = 1000.0
    failure_factor: float = 3.0  # Planner.penalize multiplies a failed edge's cost by this
    # A non-sequential edge joining two nodes of one sequence at most this many sequential steps
    # apart costs at least as much as the taught chain between them: consecutive keyframes were
    # chosen so that servoing between them stays feasible, a shortcut across them is a longer
    # baseline. (Real loop closures join nodes further apart and keep their cost.) 0 disables it.
    chain_shortcut_max_skip: int = 8
    # Servoing along a sequential edge against the taught direction means backing towards images
    # that face away from the motion, and at corners turning through views the keyframes barely
    # share: it costs this many times more (still possible where nothing else leads, e.g. dead ends).
    reverse_factor: float = 3.0

    def __post_init__(self) -> None:
        for name in ("hop_cost", "inlier_softening"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"plan {name}={getattr(self, name)} must be positive")
        for name in ("inlier_weight", "flow_weight"):
            if getattr(self, name) < 0:
                raise ConfigError(f"plan {name}={getattr(self, name)} must not be negative")
        if not self.failure_factor >= 1:
            raise ConfigError(f"plan failure_factor={self.failure_factor} must be at least 1")
        if self.chain_shortcut_max_skip < 0:
            raise ConfigError("plan chain_shortcut_max_skip must not be negative")
        if not self.reverse_factor >= 1:
            raise ConfigError(f"plan reverse_factor={self.reverse_factor} must be at least 1")
        # the dearest verified edge (at the chance level, motion of a whole diagonal)
        dearest = self.hop_cost + self.inlier_weight / self.inlier_softening + self.flow_weight
        if not self.unverified_cost > dearest:
            raise ConfigError(
                f"plan unverified_cost={self.unverified_cost} must exceed the dearest verified edge ({dearest:g}); raise it"
            )


PLAN_PRESETS: dict[str, PlanConfig] = {
    # Weigh inliers and image motion: prefer a few more easy servos to one hard one.
    "default": PlanConfig(),
    # Fewest servo subtasks: every verified edge costs one hop; unverified edges still come last.
    "hops": PlanConfig(inlier_weight=0.0, flow_weight=0.0, chain_shortcut_max_skip=0, reverse_factor=1.0),
}


def plan_preset(name: str) -> PlanConfig:
    """The named :class:`PlanConfig`; unknown names list the valid ones."""
    return choose(PLAN_PRESETS, name, "plan preset")


__all__ += ["PlanConfig", "PLAN_PRESETS", "plan_preset"]


@dataclass(frozen=True)
class NavigateConfig:
    """The navigation loop (see :mod:`topomap.navigate`): localize -> plan -> servo -> switch."""

    control_period_s: float = 0.1  # one image and one command per period [s]
    # The camera's height above the floor [m] (None: the robot's ``camera_height_m`` if it has one,
    # else unknown). Known, it makes the goal's distances metric: the goal keyframe's median depth is
    # measured against its graph neighbours' keyframes with the floor points (camera-height scale)
    # — once per goal, a median over neighbours, where per-image floor estimates would jitter.
    camera_height_m: float | None = None
    # An intermediate subgoal is reached when the servo estimates it closer than this [m] ...
    switch_distance_m: float = 0.35
    # Distance and "driven past" count only with the heading within this of the subgoal's: at the
    # teach run's corners consecutive nodes differ by a turn, and the next one is out of view until
    # the robot has turned [deg].
    switch_heading_deg: float = 15.0
    # ... or when the next node of the route verifies with more inliers than the current one
    # (it is the better target now), or the robot has driven past the subgoal.
    switch_min_inliers: int = 30  # the next node must verify with at least this many inliers
    # None of these counts while the floor measures the subgoal farther than this (median of the
    # last periods' readings, with the camera height known) [m]: on a view down a long corridor the
    # subgoal's scale from its neighbours can be several times too small and the nodes behind it
    # match as well as it does, so the estimates say "reached" metres early; on a taught chain walked
    # backwards not before the floor has been read either (for at most a second); None: neither.
    switch_floor_max_m: float | None = 0.7
    settle_steps: int = 5  # the final goal counts as reached after this many converged steps in a row,
    # or when the servo stops making progress close to it: a docked unicycle cannot remove a small
    # lateral offset by turning in place. Then, over settle_window_s (medians, robust to jitter):
    # |heading error| below settle_heading_deg, estimated distance below settle_max_m and changing
    # less than settle_progress_m between the window's halves.
    settle_window_s: float = 3.0
    settle_heading_deg: float = 2.5
    # ... and in both cases the image agrees: the verified matches between the current image and the
    # goal keyframe moved less than this fraction of the image width (median). The pose alone cannot
    # certify arrival: facing a single wall (a plane) the planar relative pose is ambiguous.
    arrive_image_error: float = 0.02
    # ... and the whole image agrees: its thumbnail descriptor is closer to the goal's than this
    # fraction of the goal's distance to its neighbouring keyframes, or (where neighbours look alike)
    # closer than every keyframe more than two hops away. Look-alike textures elsewhere can match part
    # of the view perfectly; the rest of the image then disagrees.
    arrive_descriptor_fraction: float = 0.5
    settle_progress_m: float = 0.01
    settle_max_m: float = 0.08
    # ... and, with the camera height known, the floor agrees: the distance the lowest matched points
    # (taken as floor) measure, median over the settle window, is below this [m]; for a "settled"
    # arrival below settle_patience_max_m. The goal's scale from its neighbours can be several times
    # off on long views (their floor points mismatched), and with it the servo's metric estimate.
    # Refused, the servo takes the scale the floor measures and keeps approaching. Checked when at
    # least arrive_floor_min_fraction of the window's frames, or arrive_floor_min_readings of them,
    # measured the floor, or else on the last arrive_floor_min_readings readings of the patience
    # window (a median of 15 readings is as sure over 20 s as over 3); until then no arrival — unless a
    # whole settle_patience_s at the goal gave fewer: that floor is not matched, image and servo decide.
    arrive_floor_max_m: float = 0.15
    arrive_floor_min_fraction: float = 0.5
    arrive_floor_min_readings: int = 15
    # ... and where the goal's keyframe image is at hand and its near floor textured, the near floor,
    # aligned pixel by pixel (topomap.servo.floor), puts the robot within the same bound: far points
    # cannot tell a sideways step from a turn, the near floor can. An alignment counts when its
    # normalised cross-correlation reaches floor_align_min_ncc and beats the poses a tenth of a camera
    # height aside by floor_align_min_peak. Refused, the servo docks on the floor's pose from then on.
    arrive_floor_align: bool = True
    floor_align_min_ncc: float = 0.9
    floor_align_min_peak: float = 0.015
    # To refuse an arrival (the safe direction) an alignment needs only floor_refuse_min_ncc: the
    # correlation falls with the distance the view moved (docs/navigation.md, "The near floor refuses
    # from further away"), so the steering threshold let the floor refuse only where no refusal was needed.
    floor_refuse_min_ncc: float = 0.8
    # Within the bound, an arrival the near floor puts floor_dock_target_m or more away (the servo's own
    # convergence tolerance, position_tol_m, now measured by the better witness) is held back too: the
    # servo docks on the floor's pose, for at most floor_dock_patience_s, and the next arrival within
    # the bound after that stands. A compensated servo converges on that pose; None: no docking within the bound.
    floor_dock_target_m: float | None = 0.03
    floor_dock_patience_s: float = 15.0
    # An omni vehicle steers its final approach by the near floor as soon as it aligns within this of
    # the goal [m] (tried while the servo or the matched floor put the goal that close), not only after
    # a refusal; None: only after a refusal.
    floor_approach_m: float | None = 0.5
    # ... where the features' pose lies within floor_approach_gate_m of the floor's, the features steer
    # (finer on a good view: the floor's own error reached 0.05 m, 90 % within 0.02 m); beyond it the
    # floor does (features jumping 0.03-1.4 m between frames near a goal under changed light).
    floor_approach_gate_m: float = 0.1
    # A unicycle (only) can also stall further out (heading aligned, no progress, a lateral offset it cannot
    # remove without manoeuvres that lose the view). Aligned within settle_patience_max_m and
    # changing less than settle_patience_progress_m over settle_patience_s (medians of the window's
    # halves), it settles there if the image agrees within settle_patience_image_error (a looser
    # flow bound; the thumbnail test as above): the best docking it can reach.
    settle_patience_s: float = 20.0
    settle_patience_max_m: float = 0.25
    settle_patience_progress_m: float = 0.02
    settle_patience_image_error: float = 0.06
    lost_after_steps: int = 15  # steps without usable geometry before re-localizing
    # A subgoal that gave no usable geometry since the switch, reached from the node before it (the last
    # that verified well) along a straight taught step (keyframe headings within bridge_max_turn_deg,
    # the subgoal within bridge_max_bearing_deg of straight ahead, at most bridge_max_m
    # away by the keyframes' images at the goal's scale; camera height known): before re-localizing,
    # the robot drives that step, disturbances compensated, at bridge_speed_mps, watching for the
    # subgoal or the one after it to verify. A keyframe whose posters were moved or taken down need not
    # break a chain of views the teach run drove straight through. None: never.
    bridge_max_m: float | None = 2.0
    bridge_max_turn_deg: float = 20.0
    bridge_max_bearing_deg: float = 25.0
    bridge_speed_mps: float = 0.2
    # The robot's bumper (a ``collided`` flag on what its ``apply`` returns) reporting contact this
    # many periods in a row while servoing: blocked, re-localize and re-plan as for a lost subgoal;
    # no arrival is taken while in contact. (A unicycle turning while it touches a wall frees itself
    # once it faces away: the window leaves it a turn of ~45 deg at the servo's turn rate.)
    contact_blocked_steps: int = 20
    # ... after reversing the translation it was pushing with for this long [s]: the pushing periods
    # verified well (right view, wrong place), so the trail the back-off inverts may hold none of
    # them, and a unicycle needs room ahead to remove the lateral offset that put it against the wall.
    contact_reverse_s: float = 3.0
    subgoal_timeout_s: float = 40.0  # a subgoal not reached in this time marks its edge as failed
    # The final goal has no such deadline (settling takes what it takes), but a goal servo whose
    # estimated distance came less than goal_no_progress_m closer over goal_no_progress_s without
    # settling is stuck (a wall in the way, a wrong re-localization, a stall the image refuses):
    # re-localize and re-plan as for a lost subgoal instead of pushing until the budget ends.
    goal_no_progress_s: float = 40.0
    goal_no_progress_m: float = 0.05
    # Re-plans that extend the time budget (to the new route's); after them the budget is fixed.
    max_replans: int = 8
    # Never give up while more than this fraction of the time budget is left (and a route exists):
    # recovery goes on until then, re-planning as often as it takes.
    give_up_budget_fraction: float = 0.25
    # After this many legs failed past one loop closure (or one claiming the same revisit), routes avoid
    # those loop closures wherever the map offers another way (Planner.distrust). One failure is
    # often a disturbance; a false loop between look-alike walls fails every time. 0 never distrusts.
    distrust_loop_after: int = 2
    # ... counting only loop closures the failed leg crossed within this many hops before the subgoal
    # it lost: a false claim is exposed where the look-alike stretch it joins ends, a few keyframes on,
    # while a long leg's earlier crossings were passed (blaming them all distrusted 73 true ones on a
    # 67-hop route and sent it around the map).
    distrust_within_hops: int = 6
    # Recovery first drives back along the commands since the last node that verified well (at
    # least switch_min_inliers inliers), at most this long, until that node verifies again [s].
    recover_backoff_s: float = 8.0
    # Re-localizing after a loss prefers nodes within this many hops of that node: a verified
    # answer there beats a look-alike elsewhere (measured: re-localizations 11-18 m off).
    recover_local_hops: int = 3
    # ... and of the near nodes that verify, one showing the scene at the frame's scale within this factor
    # (most inliers first): a keyframe farther down the same view verifies as well (docs/navigation.md;
    # None: the localizer's answer among the near nodes)
    recover_scale_tolerance: float | None = 1.15
    # An answer farther away is taken only if its calibrated confidence reaches this and a second
    # look (after a scan step) answers the same place (within one hop).
    recover_far_confidence: float = 0.9
    # ... and only within reach: at most recover_reach_slack_m plus recover_reach_factor x the distance
    # the robot was commanded to drive (disturbance compensation included) since the track was last
    # confirmed (a node verified with switch_min_inliers), along the map's edges measured on the floor
    # (their keyframes' distance at the camera height). Look-alikes of a whole stretch pass both checks
    # above; the robot's own motion does not (docs/navigation.md). The factor covers slip and a
    # disturbance its compensation missed; None: no reach (nor without a camera height).
    recover_reach_slack_m: float | None = 3.0
    recover_reach_factor: float = 2.0
    # A recovery turn in which nothing verified (neither a near node at switch_min_inliers nor a far
    # answer confirmed): move a step (start_search_step_m) towards the turn's best-verified view, else
    # its most textured one, and turn again, up to this many times before taking a weak answer or the
    # last good node (0: never). A spot from which no view verifies is a bad vantage point (pressed
    # against a wall, past the goal's view); keeping the last good node there loses it again at once.
    recover_search_moves: int = 1
    # The start: an answer below LocalizeConfig.min_confidence is taken when it has at least
    # start_verified_confidence and the servo's geometry confirms it twice: its relative pose has at
    # least switch_min_inliers inliers in the frame, verifies again (the match's min_inliers) after a
    # turn of start_confirm_every_s, and the two headings differ by the turn the two frames measure (within
    # start_confirm_heading_deg; the disturbances make the commanded turn unknown). Chance inliers do
    # not close that loop; a calibrated 0.9 on one frame missed whole turns (held-out world 108).
    start_verified_confidence: float = 0.5
    start_confirm_heading_deg: float = 5.0
    # A full turn that found nothing at start_verified_confidence starts on the best answer of at
    # least start_fallback_confidence that its geometry confirmed in the same way (>= 1 disables):
    # the calibration is cautious on a traversal it never saw, a verified heading loop is not chance.
    start_fallback_confidence: float = 0.3
    # The confirming frame comes after a shorter turn than a scan step: a full step (~20 deg with an
    # uncompensated yaw disturbance) turned the candidate's view out of the image under changed light.
    start_confirm_every_s: float = 0.2
    # A start turn that found nothing: drive up to this far towards the turn's view that verified best
    # (else its most textured) and scan again, while the start has used less than (1 - give_up_budget_fraction) of
    # time_budget_base_s (0 disables: one turn, then fail)
    start_search_step_m: float = 0.6
    start_search_speed_mps: float = 0.15
    # Blind servo periods measure the turn between the last two images (a visual gyro: no goal need
    # be in view) and correct the observer's d_omega with it, so that holding still while blind
    # cancels a turning disturbance the goal's images have not shown yet (e.g. after a re-plan).
    visual_gyro: bool = True
    scan_turn_rps: float = 0.5  # turning rate while scanning for a place to localize [rad/s]
    scan_every_s: float = 0.6  # localize attempts while scanning [s]
    time_budget_base_s: float = 60.0  # the whole navigation may last this [s] ...
    time_budget_s_per_hop: float = 30.0  # ... plus this per route hop [s] (a re-plan restarts the count)

    def __post_init__(self) -> None:
        for name in ("control_period_s", "switch_distance_m", "switch_heading_deg", "settle_heading_deg", "subgoal_timeout_s", "scan_turn_rps", "scan_every_s",
                     "start_confirm_every_s", "goal_no_progress_s", "goal_no_progress_m", "contact_reverse_s",
                     "time_budget_base_s", "time_budget_s_per_hop"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"navigate {name} must be positive")
        if not 0 < self.arrive_descriptor_fraction < 1:
            raise ConfigError("navigate arrive_descriptor_fraction must lie in (0, 1)")
        if not 0 < self.arrive_image_error < 1:
            raise ConfigError("navigate arrive_image_error must lie in (0, 1) (a fraction of the image width)")
        if self.settle_steps < 1 or self.lost_after_steps < 1 or self.contact_blocked_steps < 1 or self.max_replans < 0:
            raise ConfigError("settle_steps, lost_after_steps and contact_blocked_steps must be >= 1, max_replans >= 0")
        if self.distrust_loop_after < 0 or self.distrust_within_hops < 1:
            raise ConfigError("navigate distrust_loop_after must be >= 0 (0: never distrust a loop closure) "
                              "and distrust_within_hops >= 1")
        if not 0 <= self.give_up_budget_fraction < 1 or not 0 <= self.recover_far_confidence <= 1:
            raise ConfigError("navigate give_up_budget_fraction must lie in [0, 1), recover_far_confidence in [0, 1]")
        if not 0 <= self.start_verified_confidence <= 1 or not 0 <= self.arrive_floor_min_fraction <= 1:
            raise ConfigError("navigate start_verified_confidence and arrive_floor_min_fraction must lie in [0, 1]")
        if not self.start_fallback_confidence >= 0:
            raise ConfigError("navigate start_fallback_confidence must be >= 0 (1 or more: never start on a weaker answer)")
        if self.bridge_max_m is not None and not self.bridge_max_m > 0:
            raise ConfigError(f"navigate bridge_max_m={self.bridge_max_m} must be positive or None")
        if not 0 <= self.bridge_max_turn_deg <= 90 or not 0 <= self.bridge_max_bearing_deg <= 90 or not self.bridge_speed_mps > 0:
            raise ConfigError("navigate bridge_max_turn_deg and bridge_max_bearing_deg must lie in [0, 90], "
                              "bridge_speed_mps must be positive")
        if self.switch_floor_max_m is not None and not self.switch_floor_max_m > 0:
            raise ConfigError(f"navigate switch_floor_max_m={self.switch_floor_max_m} must be positive or None")
        if self.arrive_floor_min_readings < 1:
            raise ConfigError("navigate arrive_floor_min_readings must be at least 1")
        if not -1 <= self.floor_align_min_ncc <= 1 or not 0 <= self.floor_align_min_peak <= 2:
            raise ConfigError("navigate floor_align_min_ncc must lie in [-1, 1] and floor_align_min_peak in [0, 2]")
        if not -1 <= self.floor_refuse_min_ncc <= self.floor_align_min_ncc:
            raise ConfigError("navigate floor_refuse_min_ncc must lie in [-1, floor_align_min_ncc]")
        if (self.floor_dock_target_m is not None and not self.floor_dock_target_m > 0) or not self.floor_dock_patience_s >= 0:
            raise ConfigError("navigate floor_dock_target_m must be positive (or None) and floor_dock_patience_s >= 0")
        if not self.floor_approach_gate_m >= 0:
            raise ConfigError("navigate floor_approach_gate_m must be >= 0 (0: the floor always steers)")
        if self.floor_approach_m is not None and not self.floor_approach_m > 0:
            raise ConfigError(f"navigate floor_approach_m={self.floor_approach_m} must be positive or None")
        if not self.arrive_floor_max_m > 0 or not self.start_confirm_heading_deg > 0:
            raise ConfigError("navigate arrive_floor_max_m and start_confirm_heading_deg must be positive")
        if self.start_search_step_m < 0 or not self.start_search_speed_mps > 0:
            raise ConfigError("navigate start_search_step_m must be >= 0 and start_search_speed_mps positive")
        if self.recover_backoff_s < 0 or self.recover_local_hops < 0 or self.recover_search_moves < 0:
            raise ConfigError("navigate recover_backoff_s, recover_local_hops and recover_search_moves must be >= 0")
        if (self.recover_reach_slack_m is not None and not self.recover_reach_slack_m >= 0) or not self.recover_reach_factor > 0:
            raise ConfigError("navigate recover_reach_slack_m must be >= 0 (or None) and recover_reach_factor positive")
        if self.recover_scale_tolerance is not None and not self.recover_scale_tolerance >= 1.0:
            raise ConfigError("navigate recover_scale_tolerance must be >= 1 (a factor of the scene's scale)")


__all__ += ["NavigateConfig"]
