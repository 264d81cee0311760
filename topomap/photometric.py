"""Photometric change of a camera image: exposure, gamma, white balance, vignetting, blur, read noise.

What a different hour, lamp or camera does to the pixels of the same view. The simulator applies it
to its rendered frames (:mod:`topomap.sim.conditions`); localization uses it to see, while a map is
calibrated, how its evidence behaves when the light changes, and the benchmarks to generate the
appearance-change suite (synthetic night, dusk, over- and under-exposure, a noisy camera) from real
images. The order is a real camera's: exposure, white balance and vignetting in linear light, the
tone curve (``gamma``), optical blur, then sensor read noise in the 8-bit domain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from topomap.errors import ConfigError, choose

__all__ = ["Photometric", "PHOTOMETRIC_PRESETS", "photometric_preset", "apply_photometric", "random_photometric"]


@dataclass(frozen=True)
class Photometric:
    """A photometric change. ``exposure_ev``: stops (linear light x ``2**ev``); ``gamma``: tone curve
    exponent on the output (> 1 darkens mid-tones, as a night camera's curve does); ``white_balance_rgb``
    channel gains in linear light; ``vignetting``: brightness lost at the corners (0-1);
    ``blur_sigma_px``: Gaussian blur [px]; ``noise_std``: Gaussian read noise [grey levels of 255];
    ``light_pools``: pools of artificial light (lamps, a headlight) added in linear light, each a
    Gaussian patch as bright as 0.5-2x the unchanged image (so their centres clip), fixed in the
    image and drawn from ``pool_seed`` — night is lit in places, not dimmed evenly."""

    exposure_ev: float = 0.0
    gamma: float = 1.0
    white_balance_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.0
    blur_sigma_px: float = 0.0
    noise_std: float = 0.0
    light_pools: int = 0
    pool_seed: int = 0
    name: str = "custom"

    def __post_init__(self) -> None:
        ranges = {"exposure_ev": (-8.0, 8.0), "gamma": (0.2, 5.0), "vignetting": (0.0, 0.95),
                  "blur_sigma_px": (0.0, 20.0), "noise_std": (0.0, 100.0)}
        for f, (lo, hi) in ranges.items():
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"photometric {f}={v!r} must lie in [{lo}, {hi}]")
        if not (isinstance(self.light_pools, int) and 0 <= self.light_pools <= 16 and isinstance(self.pool_seed, int)):
            raise ConfigError(f"photometric light_pools={self.light_pools!r} must be an integer in [0, 16], pool_seed an integer")
        wb = tuple(float(x) for x in self.white_balance_rgb)
        if len(wb) != 3 or not all(0.0 <= x <= 4.0 for x in wb):
            raise ConfigError(f"photometric white_balance_rgb={self.white_balance_rgb!r} must be three gains in [0, 4]")
        object.__setattr__(self, "white_balance_rgb", wb)

    @property
    def is_identity(self) -> bool:
        return replace(self, name="") == Photometric(name="")


#: The appearance-change suite (docs/localization.md): what each preset stands for is in its name.
PHOTOMETRIC_PRESETS: dict[str, Photometric] = {
    "none": Photometric(name="none"),
    "dusk": Photometric(exposure_ev=-1.5, white_balance_rgb=(1.0, 0.85, 0.7), vignetting=0.3, noise_std=3.0, name="dusk"),
    "night": Photometric(exposure_ev=-3.0, gamma=1.3, vignetting=0.5, blur_sigma_px=0.8, noise_std=5.0, name="night"),
    "deep-night": Photometric(exposure_ev=-4.5, gamma=1.5, vignetting=0.6, blur_sigma_px=1.2, noise_std=8.0,
                              name="deep-night"),
    "lamp-night": Photometric(exposure_ev=-4.5, gamma=1.3, light_pools=3, pool_seed=7, blur_sigma_px=0.8,
                              noise_std=6.0, name="lamp-night"),
    "overexposed": Photometric(exposure_ev=1.5, name="overexposed"),
    "underexposed": Photometric(exposure_ev=-2.0, name="underexposed"),
    "noisy-camera": Photometric(noise_std=8.0, blur_sigma_px=1.2, vignetting=0.3, name="noisy-camera"),
}


def photometric_preset(name: str) -> Photometric:
    """The preset called ``name``; an unknown name lists the valid ones."""
    return choose(PHOTOMETRIC_PRESETS, name, "photometric preset")


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def apply_photometric(image: np.ndarray, change: Photometric, rng: np.random.Generator | None = None) -> np.ndarray:
    """``change`` applied to an ``(H, W, 3)`` or ``(H, W)`` uint8 image: a new image of the same shape.
    ``rng`` is required when ``noise_std > 0`` (seeded by the caller: same seed, same pixels)."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ConfigError(f"expected an (H, W, 3) or (H, W) uint8 image, got {img.dtype} {img.shape}")
    if change.is_identity:
        return img.copy()
    if change.noise_std > 0 and rng is None:
        raise ConfigError("sensor noise needs a numpy Generator (rng)")
    out = img.astype(np.float32) / 255.0
    if (change.exposure_ev != 0 or change.white_balance_rgb != (1.0, 1.0, 1.0) or change.vignetting > 0
            or change.light_pools > 0):
        lin = base = _srgb_to_linear(out)
        gain = np.float32(2.0 ** change.exposure_ev)
        if img.ndim == 3:
            lin = lin * (gain * np.asarray(change.white_balance_rgb, np.float32))[None, None, :]
        else:
            lin = lin * gain * np.float32(np.mean(change.white_balance_rgb))
        if change.vignetting > 0:
            h, w = img.shape[:2]
            yy, xx = np.arange(h, dtype=np.float32)[:, None], np.arange(w, dtype=np.float32)[None, :]  # broadcast, not two full grids
            r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
            fall = 1.0 - np.float32(change.vignetting) * r2  # cos^4-like falloff, 1 at the centre
            lin = lin * (fall[..., None] if img.ndim == 3 else fall)
        if change.light_pools > 0:
            pools = _light_pools(img.shape[0], img.shape[1], change.light_pools, change.pool_seed)
            lin = lin + base * (pools[..., None] if img.ndim == 3 else pools)
        out = _linear_to_srgb(lin).astype(np.float32)
    if change.gamma != 1.0:
        out = np.power(np.clip(out, 0.0, 1.0), np.float32(change.gamma))
    if change.blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), float(change.blur_sigma_px), borderType=cv2.BORDER_REFLECT)
    out = out * 255.0
    if change.noise_std > 0:
        out = out + rng.normal(0.0, change.noise_std, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _light_pools(h: int, w: int, count: int, seed: int) -> np.ndarray:
    """(H, W) float32 gain of ``count`` Gaussian pools of light: centres anywhere, radii 8-20 % of the
    diagonal, peaks 0.5-2 (times the unchanged image's light)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.arange(h, dtype=np.float32)[:, None], np.arange(w, dtype=np.float32)[None, :]
    diag = float(np.hypot(h, w))
    out = np.zeros((h, w), np.float32)
    for _ in range(count):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        sigma = rng.uniform(0.08, 0.2) * diag
        out += np.float32(rng.uniform(0.5, 2.0)) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / np.float32(2 * sigma**2))
    return out


def random_photometric(rng: np.random.Generator, strength: float = 1.0) -> Photometric:
    """A random change from none (``strength`` 0) to about ``deep-night`` (1) or a strong over-exposure."""
    s = float(np.clip(strength, 0.0, 1.0))
    dark = rng.random() < 0.8
    return Photometric(
        exposure_ev=float(-4.5 * s * rng.uniform(0.5, 1.0) if dark else 2.0 * s * rng.uniform(0.5, 1.0)),
        gamma=float(1.0 + 0.5 * s * rng.random()),
        vignetting=float(0.6 * s * rng.random()),
        blur_sigma_px=float(1.2 * s * rng.random()),
        noise_std=float(8.0 * s * rng.uniform(0.3, 1.0)),
        name=f"random-{s:.2f}",
    )
