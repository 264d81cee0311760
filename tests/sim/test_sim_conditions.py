"""Changed conditions between teach and repeat: each one changes the images as intended, seeded."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from topomap.errors import ConfigError
from topomap.sim.conditions import (
    CONDITION_PRESETS,
    Conditions,
    apply_conditions,
    moved_world,
    parse_conditions,
)
from topomap.sim.simulator import Simulator

POSE = (12.0, 8.0, 0.3)  # a corridor view of the default world (walls both sides, floor, ceiling)


def _image(world, conditions=None, seed=0, pose=POSE):
    with Simulator(world, start_pose=pose, conditions=conditions, seed=seed) as sim:
        return sim.robot.render()


@pytest.fixture(scope="module")
def nominal(world):
    return _image(world)


def _sharpness(img: np.ndarray) -> float:
    return float(cv2.Laplacian(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), cv2.CV_64F).var())


def test_nominal_conditions_leave_images_unchanged(world, nominal, renderer):
    assert np.array_equal(_image(world, "none"), nominal)
    assert np.array_equal(renderer.render(POSE), nominal)  # the renderer's own defaults
    assert CONDITION_PRESETS["none"].is_nominal and not CONDITION_PRESETS["lighting"].is_nominal


@pytest.mark.parametrize("name", ["lighting", "evening", "moved", "noisy-camera"])
def test_each_preset_changes_the_image_and_is_deterministic_for_a_seed(world, nominal, name):
    a, b = _image(world, name, seed=3), _image(world, name, seed=3)
    assert np.array_equal(a, b)
    assert a.shape == nominal.shape and a.dtype == np.uint8
    assert np.abs(a.astype(int) - nominal).mean() > 1.0


def test_lighting_relights_walls_differently_and_evening_is_darker_and_warmer(world, nominal):
    lit, eve = _image(world, "lighting"), _image(world, "evening")
    # a directional light from another side: the change is not one global gain over the image
    ratio = (lit.astype(float) + 1) / (nominal.astype(float) + 1)
    left, right = ratio[:, :100].mean(), ratio[:, -100:].mean()
    assert abs(left - right) > 0.02
    assert eve.mean() < 0.75 * nominal.mean()
    r, g, b = eve.reshape(-1, 3).mean(0) / nominal.reshape(-1, 3).mean(0)
    assert r > g > b  # warm light and white balance


def test_light_colour_tints_the_directional_light(world, nominal):
    red = _image(world, Conditions(light_rgb=(1.0, 0.2, 0.2), diffuse=1.0))
    white = _image(world, Conditions(diffuse=1.0))
    assert red[..., 0].mean() == pytest.approx(white[..., 0].mean(), abs=0.5)
    assert red[..., 1].mean() < white[..., 1].mean() - 5


def test_noise_blur_vignetting_and_exposure_act_as_named():
    rng0 = np.random.default_rng(0)
    img = rng0.integers(60, 200, (120, 160, 3)).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    noisy = apply_conditions(img, Conditions(noise_std=8.0), np.random.default_rng(1))
    assert (noisy.astype(float) - img).std() == pytest.approx(8.0, rel=0.1)
    assert np.array_equal(noisy, apply_conditions(img, Conditions(noise_std=8.0), np.random.default_rng(1)))
    assert not np.array_equal(noisy, apply_conditions(img, Conditions(noise_std=8.0), np.random.default_rng(2)))
    blurred = apply_conditions(img, Conditions(blur_sigma_px=1.5))
    assert _sharpness(blurred) < 0.5 * _sharpness(img)
    assert blurred.mean() == pytest.approx(img.mean(), abs=1.0)
    flat = np.full((120, 160, 3), 150, np.uint8)
    vig = apply_conditions(flat, Conditions(vignetting=0.4))
    assert vig[60, 80].mean() > 148 and vig[0, 0].mean() < 120
    dark = apply_conditions(flat, Conditions(exposure_ev=-1.0))
    # one stop halves linear light: sRGB 150 -> linear 0.305 -> 0.153 -> sRGB ~109
    assert dark.mean() == pytest.approx(109, abs=2)
    grey = apply_conditions(flat[..., 0], Conditions(exposure_ev=-1.0))
    assert grey.shape == (120, 160) and grey.mean() == pytest.approx(109, abs=2)


def test_apply_conditions_needs_an_rng_for_noise_and_a_uint8_image():
    img = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ConfigError, match="rng"):
        apply_conditions(img, "noisy-camera")
    with pytest.raises(ConfigError, match="uint8"):
        apply_conditions(img.astype(float), "evening", np.random.default_rng(0))


def test_moved_world_swaps_and_repaints_panels_and_keeps_the_floor_plan(world):
    c = CONDITION_PRESETS["moved"]
    moved = moved_world(world, c)
    assert moved_world(world, c) == moved
    assert np.array_equal(moved.segments, world.segments) and moved.free == world.free and moved.routes == world.routes
    changed = [(a.texture, b.texture) for a, b in zip(world.walls, moved.walls) if a.texture != b.texture]
    n = len(world.walls)
    repainted = [b for _, b in changed if b.startswith("proc:paint:")]
    assert len(repainted) == round(c.remove_fraction * n)
    swapped = [(a, b) for a, b in changed if not b.startswith("proc:paint:")]
    assert len(swapped) >= round(c.swap_fraction * n) - 1  # a panel swapped with an equal texture stays
    assert sorted(b for _, b in swapped) == sorted(a for a, _ in swapped)  # textures moved, none invented
    other = moved_world(world, Conditions(swap_fraction=0.15, remove_fraction=0.1, seed=1))
    assert other.walls != moved.walls


def test_parse_conditions_presets_overrides_and_bad_input():
    assert parse_conditions(None) == CONDITION_PRESETS["none"]
    assert parse_conditions("evening") == CONDITION_PRESETS["evening"]
    c = parse_conditions("lighting,noise_std=3,light_rgb=1:0.8:0.6,seed=4")
    assert c.noise_std == 3.0 and c.light_rgb == (1.0, 0.8, 0.6) and c.seed == 4
    assert c.light_direction == CONDITION_PRESETS["lighting"].light_direction
    assert parse_conditions("exposure_ev=-1").exposure_ev == -1.0
    assert Conditions.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    with pytest.raises(ConfigError, match="choose one of: evening, lighting, moved, noisy-camera, none"):
        parse_conditions("dusk")
    with pytest.raises(ConfigError, match="unknown conditions setting 'glare'"):
        parse_conditions("glare=1")
    with pytest.raises(ConfigError, match="must be three"):
        parse_conditions("light_rgb=1:2")
    with pytest.raises(ConfigError, match=r"noise_std=-1.0 must lie in"):
        parse_conditions("noise_std=-1")
    with pytest.raises(ConfigError, match="must not exceed 1"):
        Conditions(swap_fraction=0.7, remove_fraction=0.5)


def test_a_renderer_given_to_the_simulator_cannot_take_light_or_moved_conditions(world, renderer):
    with pytest.raises(ConfigError, match="renderer"):
        Simulator(world, start_pose=POSE, renderer=renderer, conditions="moved")
    with Simulator(world, start_pose=POSE, renderer=renderer, conditions="noisy-camera", seed=2) as sim:
        a = sim.robot.render()
        assert not np.array_equal(sim.ground_truth.render(), a)  # fresh noise per image
