"""Changed conditions between teach and repeat: lighting, camera exposure and noise, moved objects.

A :class:`Conditions` value describes how the world looks on one run; the navigator never sees it,
only the images it produces. Each field acts where it physically belongs:

* **light** (renderer): TinyRenderer has one directional light and an ambient term; the light's
  direction, colour (it tints the directional part only) and the two coefficients are passed to
  :class:`~topomap.sim.render.PyBulletRenderer` (:meth:`Conditions.renderer_options`);
* **camera** (image post-processing, :func:`apply_conditions`): exposure in stops and a white
  balance applied in linear light, vignetting, optical blur, then sensor read noise — the order a
  real camera applies them;
* **moved objects** (world, :func:`moved_world`): a fraction of the wall panels exchange their
  textures (posters moved) and a fraction are repainted plain (posters taken down). The floor plan
  is unchanged, so the vehicle collides with the same walls.

Presets (:data:`CONDITION_PRESETS`): ``none`` (as taught), ``lighting`` (light from another side,
warmer, darker), ``evening`` (dim warm light, underexposed, noisier), ``moved`` (15 % of the panels
swapped, 10 % repainted), ``noisy-camera`` (read noise, blur, vignetting). Specs as for
disturbances: ``"evening"``, ``"noise_std=3,blur_sigma_px=0.8"``, ``"lighting,exposure_ev=-1"``;
vector fields take ``:``-separated numbers (``light_rgb=1:0.8:0.6``).

Everything is seeded: the same conditions, seed and image give the same pixels.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace

import numpy as np

from topomap.config import preset_with_overrides
from topomap.errors import ConfigError, choose, unknown_choice
from topomap.photometric import Photometric, apply_photometric

__all__ = ["Conditions", "CONDITION_PRESETS", "conditions_preset", "parse_conditions", "apply_conditions",
           "moved_world", "PLAIN_PAINT_KIND"]

#: The procedural texture kind a removed panel is repainted with (:mod:`topomap.sim.textures`).
PLAIN_PAINT_KIND = "paint"

_VECTOR_FIELDS = ("light_direction", "light_rgb", "white_balance_rgb")


@dataclass(frozen=True)
class Conditions:
    """How one run looks. The defaults are the simulator's nominal conditions (images unchanged).

    Light (renderer): ``light_direction`` towards the light in world axes ``(x, z, up)``;
    ``light_rgb`` colour of the directional light (0-2 per channel); ``ambient`` / ``diffuse``
    TinyRenderer's coefficients. Camera (post-processing): ``exposure_ev`` exposure change in stops
    (pixel values in linear light times ``2**exposure_ev``); ``white_balance_rgb`` channel gains in
    linear light (a colour cast); ``vignetting`` brightness lost at the image corners (0-1);
    ``blur_sigma_px`` Gaussian blur [px]; ``noise_std`` Gaussian read noise [grey levels of 255].
    World: ``swap_fraction`` of the wall panels exchange textures, ``remove_fraction`` are repainted
    plain. ``seed`` chooses the moved panels (the noise is seeded by the simulator's seed as well).
    """

    light_direction: tuple[float, float, float] = (0.4, 0.7, 1.0)
    light_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.75
    diffuse: float = 0.35
    exposure_ev: float = 0.0
    white_balance_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: float = 0.0
    blur_sigma_px: float = 0.0
    noise_std: float = 0.0
    swap_fraction: float = 0.0
    remove_fraction: float = 0.0
    seed: int = 0
    name: str = "custom"

    def __post_init__(self) -> None:
        for f in _VECTOR_FIELDS:
            v = getattr(self, f)
            try:
                t = tuple(float(x) for x in v)
            except (TypeError, ValueError):
                raise ConfigError(f"conditions {f}={v!r} must be three numbers") from None
            if len(t) != 3 or not all(math.isfinite(x) for x in t):
                raise ConfigError(f"conditions {f}={v!r} must be three finite numbers")
            object.__setattr__(self, f, t)
        if math.hypot(*self.light_direction) < 1e-6:
            raise ConfigError("conditions light_direction must not be the zero vector")
        for f in ("light_rgb", "white_balance_rgb"):
            if not all(0.0 <= x <= 4.0 for x in getattr(self, f)):
                raise ConfigError(f"conditions {f}={getattr(self, f)} must hold gains between 0 and 4")
        ranges = {"ambient": (0.0, 2.0), "diffuse": (0.0, 2.0), "exposure_ev": (-6.0, 6.0), "vignetting": (0.0, 0.95),
                  "blur_sigma_px": (0.0, 20.0), "noise_std": (0.0, 100.0), "swap_fraction": (0.0, 1.0),
                  "remove_fraction": (0.0, 1.0)}
        for f, (lo, hi) in ranges.items():
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"conditions {f}={v!r} must lie in [{lo}, {hi}]")
        if self.swap_fraction + self.remove_fraction > 1.0:
            raise ConfigError("conditions swap_fraction + remove_fraction must not exceed 1")
        object.__setattr__(self, "seed", int(self.seed))

    # ------------------------------------------------------------------ parts
    @property
    def is_nominal(self) -> bool:
        """True when the images are exactly the simulator's nominal ones."""
        return _comparable(self) == _comparable(Conditions())

    @property
    def changes_world(self) -> bool:
        return self.swap_fraction > 0 or self.remove_fraction > 0

    @property
    def changes_light(self) -> bool:
        d = Conditions()
        return (self.light_direction, self.light_rgb, self.ambient, self.diffuse) != (
            d.light_direction, d.light_rgb, d.ambient, d.diffuse)

    @property
    def changes_image(self) -> bool:
        return (self.exposure_ev != 0 or self.white_balance_rgb != (1.0, 1.0, 1.0) or self.vignetting > 0
                or self.blur_sigma_px > 0 or self.noise_std > 0)

    def renderer_options(self) -> dict:
        """Keyword arguments of :class:`~topomap.sim.render.PyBulletRenderer` for this light."""
        return {"lighting": (self.ambient, self.diffuse), "light_direction": self.light_direction,
                "light_rgb": self.light_rgb}

    def to_dict(self) -> dict:
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> Conditions:
        if not isinstance(d, dict):
            raise ConfigError(f"conditions must be a JSON object, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        if unknown := set(d) - names:
            raise unknown_choice("conditions setting", sorted(unknown)[0], names)
        return cls(**d)


def _comparable(c: Conditions) -> dict:
    d = c.to_dict()
    d.pop("name")
    d.pop("seed")
    return d


#: Named conditions (see the module docstring); ``none`` is the teach run's nominal look.
CONDITION_PRESETS: dict[str, Conditions] = {
    "none": Conditions(name="none"),
    # daylight from the other side of the building: other walls lit, warmer, a little darker
    "lighting": Conditions(light_direction=(-0.7, -0.4, 0.6), light_rgb=(1.0, 0.88, 0.7), ambient=0.6,
                           diffuse=0.55, exposure_ev=-0.3, name="lighting"),
    # dim warm lamps, the camera underexposes and its noise shows
    "evening": Conditions(light_direction=(0.2, -0.9, 0.5), light_rgb=(1.0, 0.7, 0.45), ambient=0.5, diffuse=0.3,
                          exposure_ev=-0.8, white_balance_rgb=(1.0, 0.88, 0.7), vignetting=0.35, noise_std=4.0,
                          name="evening"),
    # posters moved between walls, some taken down
    "moved": Conditions(swap_fraction=0.15, remove_fraction=0.10, name="moved"),
    # a cheap camera: read noise, soft optics, dark corners
    "noisy-camera": Conditions(noise_std=8.0, blur_sigma_px=1.2, vignetting=0.3, name="noisy-camera"),
}


def conditions_preset(name: str) -> Conditions:
    """The preset called ``name``; an unknown name lists the valid ones."""
    return choose(CONDITION_PRESETS, name, "conditions preset")


def parse_conditions(spec: str | Conditions | dict | None) -> Conditions:
    """Conditions from ``"PRESET"``, ``"key=value,..."`` or ``"PRESET,key=value,..."`` (or a dict/value).

    Keys are the fields of :class:`Conditions`; vectors as ``x:y:z``. They override the preset
    (``none`` when no preset is named).
    """
    if spec is None:
        return CONDITION_PRESETS["none"]
    if isinstance(spec, Conditions):
        return spec
    if isinstance(spec, dict):
        return Conditions.from_dict(spec)
    base, items = preset_with_overrides(spec, "conditions", CONDITION_PRESETS,
                                        (f.name for f in dataclasses.fields(Conditions) if f.name != "name"))
    if not items:
        return base
    values: dict = {}
    for key, val in items:
        try:
            if key in _VECTOR_FIELDS:
                values[key] = tuple(float(x) for x in val.split(":"))
            elif key == "seed":
                values[key] = int(val)
            else:
                values[key] = float(val)
        except ValueError:
            what = "three numbers like 1:0.8:0.6" if key in _VECTOR_FIELDS else "a number"
            raise ConfigError(f"conditions {key}={val!r} must be {what}") from None
    name = base.name if not values else (f"{base.name}+" if base.name != "none" else "") + ",".join(
        f"{k}={v}" for k, v in values.items())
    return replace(base, **values, name=name)


# ---------------------------------------------------------------------- camera
def apply_conditions(image: np.ndarray, conditions: Conditions | str | None,
                     rng: np.random.Generator | None = None) -> np.ndarray:
    """The camera part of ``conditions`` applied to ``image``: a new ``(H, W, 3)`` or ``(H, W)`` uint8.

    Exposure, white balance and vignetting act in linear light (sRGB decoded), then blur, then read
    noise from ``rng`` (required when ``noise_std > 0``) in the 8-bit domain
    (:func:`topomap.photometric.apply_photometric`). Light and moved panels are not image effects
    (see :meth:`Conditions.renderer_options`, :func:`moved_world`).
    """
    c = parse_conditions(conditions)
    change = Photometric(exposure_ev=c.exposure_ev, white_balance_rgb=c.white_balance_rgb, vignetting=c.vignetting,
                         blur_sigma_px=c.blur_sigma_px, noise_std=c.noise_std, name=c.name)
    return apply_photometric(image, change, rng)


# ---------------------------------------------------------------------- world
def moved_world(world, conditions: Conditions | str | None):
    """``world`` with the moved-object part of ``conditions``: a seeded ``swap_fraction`` of its
    wall panels exchange textures (each moves to another panel of the set) and a disjoint
    ``remove_fraction`` are repainted plain. The floor plan, routes and markers are unchanged."""
    c = parse_conditions(conditions)
    if not c.changes_world:
        return world
    rng = np.random.default_rng([c.seed, int(world.seed or 0), 16])
    walls = list(world.walls)
    n = len(walls)
    order = rng.permutation(n)
    n_swap = int(round(c.swap_fraction * n))
    n_remove = int(round(c.remove_fraction * n))
    swap, remove = order[:n_swap], order[n_swap:n_swap + n_remove]
    if n_swap >= 2:
        textures = [walls[i].texture for i in swap]
        for k, i in enumerate(swap):  # a cyclic shift: every chosen panel gets another one's texture
            walls[i] = replace(walls[i], texture=textures[(k + 1) % n_swap])
    for i in remove:
        walls[i] = replace(walls[i], texture=f"proc:{PLAIN_PAINT_KIND}:{int(rng.integers(0, 1_000_000))}")
    return replace(world, walls=tuple(walls), name=f"{world.name}+moved")
