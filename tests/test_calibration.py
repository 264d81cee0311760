"""Calibration: the sign-constrained model, image quality evidence, ECE and reliability."""

from __future__ import annotations

import numpy as np
import pytest

from topomap.calibration import (
    Calibration,
    Calibrator,
    expected_calibration_error,
    image_quality,
    quality_evidence,
    reliability,
)
from topomap.errors import MapFormatError


def test_fit_learns_the_direction_and_keeps_the_signs():
    rng = np.random.default_rng(0)
    margin = rng.normal(0, 2, 400)
    noise = rng.normal(0, 1, 400)  # carries nothing; its weight may not turn positive
    y = rng.random(400) < 1 / (1 + np.exp(-(1.5 * margin - 0.5)))
    cal = Calibrator.fit(("margin", "low_snr"), np.c_[margin, np.abs(noise)], y)
    assert cal.coef[0] == pytest.approx(1.5, abs=0.4) and cal.coef[1] <= 0.0
    p = [cal.probability({"margin": m, "low_snr": 0.0}) for m in (-3, 0, 3)]
    assert p[0] < p[1] < p[2]
    # a feature whose data says the opposite of its sign gets weight 0, not a wrong direction
    wrong = Calibrator.fit(("log_inliers",), -margin[:, None], y)
    assert wrong.coef == (0.0,)
    assert Calibrator.from_dict(cal.to_dict()) == cal


def test_ece_and_reliability():
    rng = np.random.default_rng(1)
    conf = rng.random(5000)
    calibrated = rng.random(5000) < conf
    assert expected_calibration_error(conf, calibrated) < 0.03
    overconfident = rng.random(5000) < conf * 0.5
    assert expected_calibration_error(conf, overconfident) > 0.2
    mean_c, frac, counts = reliability(conf, calibrated, bins=10)
    assert counts.sum() == 5000 and np.all(np.abs(frac - mean_c) < 0.06)


def test_image_quality_sees_noise_and_clipping():
    rng = np.random.default_rng(2)
    base = np.tile(np.linspace(40, 200, 320, dtype=np.float32), (240, 1))
    clean = base.astype(np.uint8)
    noisy = np.clip(base + rng.normal(0, 8, base.shape), 0, 255).astype(np.uint8)
    assert image_quality(noisy).noise == pytest.approx(8, rel=0.2) and image_quality(clean).noise < 1.5
    bright = np.clip(base * 2.0, 0, 255).astype(np.uint8)
    assert image_quality(bright).clipped > 0.3 and image_quality(clean).clipped == 0.0
    ref = {"snr": image_quality(clean).snr, "contrast": image_quality(clean).contrast, "clipped": 0.0}
    ev = quality_evidence(image_quality(noisy), ref)
    assert ev["low_snr"] > 1.0 and quality_evidence(image_quality(bright), ref)["clipping"] > 1.0
    assert quality_evidence(image_quality(noisy), {}) == {"low_snr": 0.0, "contrast_loss": 0.0, "clipping": 0.0}


def test_calibration_round_trip_and_other_versions():
    cal = Calibration(Calibrator(("margin",), (0.5,), -1.0), {"snr": 10.0}, {"nodes": 3, "descriptor": "fused"})
    assert Calibration.from_meta({"calibration": cal.to_dict()}) == cal
    assert Calibration.from_meta({}) is None
    assert Calibration.from_meta({"calibration": {**cal.to_dict(), "version": 99}}) is None  # other definitions
    with pytest.raises(MapFormatError):
        Calibration.from_meta({"calibration": {**cal.to_dict(), "reference": {"snr": "x"}}})


def test_a_fit_around_a_prior_moves_with_the_evidence():
    prior = Calibrator(("belief_log_odds",), (1.0,), 0.0)
    rng = np.random.default_rng(0)
    # the truth: P(right) = sigmoid(2 + 0.5 x), far from the prior (weight 1, intercept 0)
    x = rng.normal(0.0, 2.0, (4000, 1))
    y = rng.random(4000) < 1.0 / (1.0 + np.exp(-(2.0 + 0.5 * x[:, 0])))
    many = Calibrator.fit(prior.features, x, y, around=prior)
    few = Calibrator.fit(prior.features, x[:8], y[:8], around=prior)
    assert many.intercept == pytest.approx(2.0, abs=0.25) and many.coef[0] == pytest.approx(0.5, abs=0.1)
    # eight samples move the model from the prior by less than they would unconstrained
    assert abs(few.intercept) + abs(few.coef[0] - 1.0) < abs(many.intercept) + abs(many.coef[0] - 1.0)
    with pytest.raises(ValueError, match="prior model"):
        Calibrator.fit(("margin",), x, y, around=prior)


def test_a_sequence_calibration_round_trips_and_a_malformed_one_is_refused():
    from topomap.calibration import POSTERIOR

    cal = Calibration(Calibrator(("margin",), (1.0,), 0.0), {"snr": 3.0}, {"nodes": 5}, POSTERIOR)
    assert Calibration.from_meta({"calibration": cal.to_dict()}) == cal
    assert "sequence" not in Calibration(cal.single, cal.reference, cal.fitted_for).to_dict()
    for bad in ({"features": ["margin"], "coef": [1.0], "intercept": 0.0}, "x", {"coef": [1.0]}):
        with pytest.raises(MapFormatError):
            Calibration.from_meta({"calibration": {**cal.to_dict(), "sequence": bad}})
