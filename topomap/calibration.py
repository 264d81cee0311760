"""Confidence that means a probability: evidence features, a calibrated model, and its scores.

A localizer's raw confidence (the softmax mass on the answer) ranks answers but is not a
probability: on the corridor an answer at 0.9 is right about two times in three. A
:class:`Calibrator` maps an answer's *evidence* — the margin of its score over the best node
outside its neighbourhood, its verified inliers, the raw confidence's log-odds, how noisy and how
flat the query image is compared with the map's keyframes — to the probability that the answered
node is right, with a logistic model (Platt scaling with several inputs). Its weights are
sign-constrained to the direction each piece of evidence must act in (more inliers can only raise
the probability, a noisier image only lower it): a model fitted on the map's own keyframes then
cannot learn a direction that holds there by accident and fails on the queries it has never seen.

The sequence filter's belief mass is a probability by construction, but of the filter's model of
the camera; fitted on labelled queries, a model of its log-odds and of the filter's probability of
being elsewhere, centred on the posterior itself (:data:`POSTERIOR`), maps it to the frequency of
being right.

A map's :class:`Calibration` holds the model, fitted self-supervised (:mod:`topomap.self_supervision`)
and stored in the map's meta as plain numbers. :func:`expected_calibration_error` and :func:`reliability` score a set of answers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import minimize

from topomap.errors import MapFormatError

__all__ = ["SINGLE_FEATURES", "SEQUENCE_FEATURES", "POSTERIOR", "FEATURE_SIGNS", "Calibrator", "Calibration", "ImageQuality",
           "image_quality", "quality_reference", "quality_evidence", "expected_calibration_error", "reliability", "logit", "CALIBRATION_KEY"]

#: Map meta key of the calibration (plain numbers; see :meth:`Calibration.to_dict`).
CALIBRATION_KEY = "calibration"
#: Version of the evidence definitions: a calibration fitted for other definitions is ignored.
EVIDENCE_VERSION = 1

#: Evidence a single-frame answer is judged by (see :meth:`topomap.localize.Localizer.evidence`).
SINGLE_FEATURES = ("margin", "log_inliers", "log_odds", "low_snr", "contrast_loss", "clipping")
#: The direction each feature may act in (+1 raises the probability, -1 lowers it).
FEATURE_SIGNS = {"margin": 1, "log_inliers": 1, "log_odds": 1, "low_snr": -1, "contrast_loss": -1, "clipping": -1,
                 "belief_log_odds": 1, "elsewhere_log_odds": -1}
#: Evidence a sequence answer is judged by: the log-odds of the filter's belief mass on the answer and
#: of its probability that the camera is in no place of the map.
SEQUENCE_FEATURES = ("belief_log_odds", "elsewhere_log_odds")
#: L2 penalty of the fit per sample [1 / weight^2]: a little shrinkage keeps weights finite where
#: the self-supervised samples separate perfectly.
_RIDGE = 1e-2
_EPS = 1e-4


def logit(p: float) -> float:
    p = min(max(float(p), _EPS), 1.0 - _EPS)
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class Calibrator:
    """``P(right | x) = sigmoid(intercept + coef . x)`` over the named ``features``."""

    features: tuple[str, ...]
    coef: tuple[float, ...]
    intercept: float

    def probability(self, evidence: dict[str, float]) -> float:
        z = self.intercept + sum(c * float(evidence.get(f, 0.0)) for f, c in zip(self.features, self.coef))
        return 1.0 / (1.0 + math.exp(-min(max(z, -50.0), 50.0)))

    @classmethod
    def fit(cls, features: tuple[str, ...], x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None, *,
            around: Calibrator | None = None, prior_sd: float = 1.0) -> Calibrator:
        """Maximum-likelihood logistic fit of ``y`` (N,) bool on ``x`` (N, F), each weight bounded to
        its sign in :data:`FEATURE_SIGNS` (scipy L-BFGS-B; scikit-learn's logistic regression has no
        bounds). With ``around`` (a model of the same features) the fit is the posterior mode under a
        Gaussian prior of standard deviation ``prior_sd`` centred on it, intercept included: few
        samples move the model little from a model that is already a probability."""
        x = np.asarray(x, np.float64).reshape(len(y), len(features))
        y = np.asarray(y, np.float64)
        w = np.ones(len(y)) if weights is None else np.asarray(weights, np.float64)
        w = w / w.sum() * len(w)

        if around is not None:
            if around.features != tuple(features):
                raise ValueError(f"the prior model is over {around.features}, not {tuple(features)}")
            centre, k = np.r_[around.intercept, around.coef], 1.0 / (2.0 * prior_sd**2 * len(y))
        else:  # ridge on the weights only
            centre, k = np.zeros(len(features) + 1), _RIDGE
        mask = np.r_[float(around is not None), np.ones(len(features))]

        def loss(theta):
            z = theta[0] + x @ theta[1:]
            # log(1 + e^z) - y z, computed stably
            nll = np.logaddexp(0.0, z) - y * z
            p = 1.0 / (1.0 + np.exp(-z))
            g = w * (p - y)
            d = mask * (theta - centre)
            return float(w @ nll) / len(y) + k * float(d @ d), np.r_[g.sum(), x.T @ g] / len(y) + 2 * k * d

        bounds = [(None, None)] + [(0.0, None) if FEATURE_SIGNS.get(f, 0) > 0 else (None, 0.0) if FEATURE_SIGNS.get(f, 0) < 0
                                   else (None, None) for f in features]
        base = float(np.clip(np.average(y, weights=w), _EPS, 1 - _EPS))
        theta0 = centre.copy() if around is not None else np.r_[math.log(base / (1 - base)), np.zeros(len(features))]
        res = minimize(loss, theta0, jac=True, method="L-BFGS-B", bounds=bounds)
        return cls(tuple(features), tuple(float(c) for c in res.x[1:]), float(res.x[0]))

    def to_dict(self) -> dict:
        return {"features": list(self.features), "coef": list(self.coef), "intercept": self.intercept}

    @classmethod
    def from_dict(cls, d: dict) -> Calibrator:
        try:
            feats = tuple(str(f) for f in d["features"])
            coef = tuple(float(c) for c in d["coef"])
            intercept = float(d["intercept"])
        except (KeyError, TypeError, ValueError):
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`") from None
        if (len(feats) != len(coef) or len(feats) > 64 or not all(math.isfinite(c) for c in (*coef, intercept))
                or not set(feats) <= set(FEATURE_SIGNS)):
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`")
        return cls(feats, coef, intercept)


@dataclass(frozen=True)
class ImageQuality:
    """``noise``: sensor-noise standard deviation [grey levels] (Immerkaer 1996); ``contrast``: the
    standard deviation of the image smoothed at 2 px [grey levels] — the signal the noise competes
    with; ``clipped``: the fraction of pixels at the ends of the range (<= 5 or >= 250), where an
    over- or under-exposed camera has lost the texture."""

    noise: float
    contrast: float
    clipped: float = 0.0

    @property
    def snr(self) -> float:
        return self.contrast / max(self.noise, 0.5)


#: Grey levels counted as clipped (the ends of an 8-bit range, JPEG ringing included).
CLIP_LOW, CLIP_HIGH = 5, 250
#: Added to both clipped fractions before their ratio: a map with no clipped pixel at all does not
#: turn a query's first few into a large loss.
CLIP_FLOOR = 0.02
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def image_quality(image: np.ndarray) -> ImageQuality:
    """Noise and contrast of an ``(H, W)`` uint8 image (fast: two filters)."""
    f = image.astype(np.float32)
    h, w = f.shape
    clipped = float(np.count_nonzero((image <= CLIP_LOW) | (image >= CLIP_HIGH))) / max(1, image.size)
    if h < 3 or w < 3:
        return ImageQuality(0.0, float(f.std()), clipped)
    r = cv2.filter2D(f, -1, _IMMERKAER, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    noise = math.sqrt(math.pi / 2.0) * float(np.abs(r).sum()) / (6.0 * (w - 2) * (h - 2))
    contrast = float(cv2.GaussianBlur(f, (0, 0), 2.0).std())
    return ImageQuality(noise, contrast, clipped)


def quality_reference(qualities: list[ImageQuality]) -> dict:
    """The reference a query's quality is judged against: the median ``snr``, ``contrast`` and
    ``clipped`` of the map keyframes' qualities (empty when there are none)."""
    if not qualities:
        return {}
    return {"snr": float(np.median([q.snr for q in qualities])),
            "contrast": float(np.median([q.contrast for q in qualities])),
            "clipped": float(np.median([q.clipped for q in qualities]))}


def quality_evidence(q: ImageQuality, reference: dict) -> dict[str, float]:
    """``low_snr``, ``contrast_loss`` and ``clipping``: how much worse (log ratio, 0 when not worse) the
    query's signal-to-noise ratio, contrast and clipped fraction are than the map keyframes' median
    (``reference``; an empty reference gives zeros)."""
    if not reference:
        return {"low_snr": 0.0, "contrast_loss": 0.0, "clipping": 0.0}
    ref_snr = float(reference.get("snr", 0.0) or 0.0)
    ref_contrast = float(reference.get("contrast", 0.0) or 0.0)
    ref_clipped = float(reference.get("clipped", 0.0) or 0.0)
    low_snr = max(0.0, math.log(ref_snr / max(q.snr, 1e-3))) if ref_snr > 0 else 0.0
    contrast_loss = max(0.0, math.log(ref_contrast / max(q.contrast, 1e-3))) if ref_contrast > 0 else 0.0
    clipping = max(0.0, math.log((q.clipped + CLIP_FLOOR) / (ref_clipped + CLIP_FLOOR)))
    return {"low_snr": low_snr, "contrast_loss": contrast_loss, "clipping": clipping}


#: The sequence filter's posterior as it is: ``P(right) = belief mass`` (the prior a labelled sequence
#: calibration is fitted around).
POSTERIOR = Calibrator(SEQUENCE_FEATURES, (1.0, 0.0), 0.0)


@dataclass(frozen=True)
class Calibration:
    """A map's calibration: the ``single``-frame calibrator; ``reference`` the keyframes' median image
    quality (``snr``, ``contrast``) the query's is compared with; ``fitted_for``: the map it was
    fitted on (``nodes``, ``descriptor``) and its samples (``samples``, ``right``, ``seed``), to tell a
    stale calibration; ``sequence``: the map of the sequence filter's belief mass to a probability
    (fitted on labelled queries only; ``None``: the filter's posterior is the confidence)."""

    single: Calibrator
    reference: dict
    fitted_for: dict
    sequence: Calibrator | None = None

    def to_dict(self) -> dict:
        d = {"version": EVIDENCE_VERSION, "single": self.single.to_dict(), "reference": dict(self.reference),
             "fitted_for": dict(self.fitted_for)}
        if self.sequence is not None:
            d["sequence"] = self.sequence.to_dict()
        return d

    @classmethod
    def from_meta(cls, meta: dict) -> Calibration | None:
        """The map's calibration, or ``None`` when it has none or one of other evidence definitions."""
        d = meta.get(CALIBRATION_KEY)
        if not isinstance(d, dict) or d.get("version") != EVIDENCE_VERSION:
            return None
        try:
            reference = {str(k): float(v) for k, v in dict(d.get("reference") or {}).items()}
            fitted_for = dict(d.get("fitted_for") or {})
        except (TypeError, ValueError):
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`") from None
        if not all(math.isfinite(v) and v >= 0 for v in reference.values()):
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`")
        single, sequence = d.get("single"), d.get("sequence")
        if not isinstance(single, dict) or not (sequence is None or isinstance(sequence, dict)):
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`")
        seq = None if sequence is None else Calibrator.from_dict(sequence)
        if seq is not None and seq.features != SEQUENCE_FEATURES:
            raise MapFormatError("the map's calibration is malformed; refit it with `topomap index MAP`")
        return cls(Calibrator.from_dict(single), reference, fitted_for, seq)


def reliability(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per equal-width confidence bin: mean confidence, fraction right, count (empty bins: NaN, 0)."""
    c = np.asarray(confidence, float)
    ok = np.asarray(correct, bool)
    b = np.clip((c * bins).astype(int), 0, bins - 1)
    counts = np.bincount(b, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_c = np.bincount(b, weights=c, minlength=bins) / counts
        frac = np.bincount(b, weights=ok.astype(float), minlength=bins) / counts
    return mean_c, frac, counts


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """ECE (Guo et al. 2017): the count-weighted mean |fraction right - mean confidence| over bins."""
    mean_c, frac, counts = reliability(confidence, correct, bins)
    if counts.sum() == 0:
        return 0.0
    used = counts > 0
    return float((np.abs(frac[used] - mean_c[used]) * counts[used]).sum() / counts.sum())
