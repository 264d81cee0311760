"""The appearance changes of the benchmark suite (topomap.photometric)."""

import numpy as np
import pytest

from topomap.errors import ConfigError
from topomap.photometric import PHOTOMETRIC_PRESETS, Photometric, apply_photometric, photometric_preset


@pytest.fixture
def image():
    rng = np.random.default_rng(0)
    return rng.integers(60, 200, (48, 64), dtype=np.uint8)


def test_none_is_a_copy(image):
    out = apply_photometric(image, PHOTOMETRIC_PRESETS["none"])
    assert np.array_equal(out, image) and out is not image


def test_every_preset_keeps_shape_and_type_and_is_seeded(image):
    for name, change in PHOTOMETRIC_PRESETS.items():
        a = apply_photometric(image, change, np.random.default_rng(3))
        b = apply_photometric(image, change, np.random.default_rng(3))
        assert a.shape == image.shape and a.dtype == np.uint8, name
        assert np.array_equal(a, b), name
    colour = np.stack([image] * 3, axis=2)
    assert apply_photometric(colour, PHOTOMETRIC_PRESETS["lamp-night"], np.random.default_rng(0)).shape == colour.shape


def test_darker_presets_darken(image):
    mean = image.mean()
    for name in ("dusk", "night", "deep-night", "underexposed", "lamp-night"):
        assert apply_photometric(image, PHOTOMETRIC_PRESETS[name], np.random.default_rng(0)).mean() < mean, name
    assert apply_photometric(image, PHOTOMETRIC_PRESETS["overexposed"]).mean() > mean


def test_light_pools_light_the_night_in_places(image):
    dark = Photometric(exposure_ev=-4.5)
    lit = Photometric(exposure_ev=-4.5, light_pools=3, pool_seed=7)
    d, l1 = apply_photometric(image, dark), apply_photometric(image, lit)
    gain = l1.astype(float) - d
    assert (gain >= 0).all() and gain.max() > 40  # a pool is as bright as daylight, or brighter
    assert np.percentile(gain, 10) < 0.25 * gain.max()  # ... in places, not everywhere
    assert np.array_equal(l1, apply_photometric(image, lit))  # fixed in the image by pool_seed
    assert not np.array_equal(l1, apply_photometric(image, Photometric(exposure_ev=-4.5, light_pools=3, pool_seed=8)))


@pytest.mark.parametrize("kwargs", [dict(light_pools=-1), dict(light_pools=17), dict(light_pools=1.5),
                                    dict(exposure_ev=float("nan")), dict(white_balance_rgb=(1.0, 1.0))])
def test_bad_changes_are_refused(kwargs):
    with pytest.raises(ConfigError):
        Photometric(**kwargs)


def test_noise_needs_a_generator_and_presets_are_named(image):
    with pytest.raises(ConfigError, match="rng"):
        apply_photometric(image, PHOTOMETRIC_PRESETS["noisy-camera"])
    with pytest.raises(ConfigError, match="lamp-night"):
        photometric_preset("no-such-light")
