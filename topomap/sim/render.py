"""Rendering the camera image of a world: a small :class:`Renderer` protocol and its PyBullet backend.

Any backend (PyBullet's TinyRenderer here; MuJoCo, an OpenGL context or a real robot's camera in
another implementation) only has to turn a camera pose into an ``(H, W, 3) uint8`` RGB image that
agrees with the camera intrinsics ``K`` (OpenCV pixel-centre convention, see :mod:`topomap.camera`):
a world point ``P`` must appear at the pixel ``K [R|t] P`` of :func:`topomap.sim.geometry.camera_from_world`.

:class:`PyBulletRenderer` builds each wall panel, floor tile and ceiling tile as a textured quad in a
headless ``p.DIRECT`` PyBullet client and renders with TinyRenderer (CPU, deterministic). TinyRenderer
visits every pixel of each triangle's bounding box, so before each frame the panels that cannot be
seen are hidden (zero alpha): walls are full height, hence a panel is visible in pixel column ``u``
only if it is the first wall hit by the floor-plan ray through that column (exact visibility: images
are identical with and without it). The cost of a frame is dominated by TinyRenderer shading each
covered pixel (about 0.2 us per pixel here), so culling only saves 5-10 %.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from topomap.camera import CameraIntrinsics
from topomap.errors import ConfigError, unknown_choice
from topomap.sim import textures as tx
from topomap.sim.geometry import CAMERA_HEIGHT_M, Pose
from topomap.sim.world import World

__all__ = ["Renderer", "PyBulletRenderer", "RENDERERS", "make_renderer", "gl_projection", "gl_view"]

log = logging.getLogger(__name__)

_NEAR_M = 0.05  # near clipping plane [m]
# Added to the clip-space w = depth: TinyRenderer clips only triangles with a vertex at w < 0 and divides
# by w, so a vertex exactly on the camera plane (w = 0, common when poses and tiles share a grid) gave
# inf/NaN bounding boxes and frames of seconds. The image error is eps/depth relative: < 1e-3 px.
_W_EPS = 1.234567e-6


@runtime_checkable
class Renderer(Protocol):
    """Turns a camera pose into an image; ``camera`` says which intrinsics the image obeys."""

    camera: CameraIntrinsics

    def render(self, camera_pose: Pose) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB image seen from ``camera_pose = (x, z, theta)``."""
        ...

    def close(self) -> None:
        """Release the backend's resources."""
        ...


def _import_pybullet():
    """Import pybullet without its 'build time' banner on stderr (the library never prints)."""
    import sys

    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    fd = 2
    try:
        saved = os.dup(fd)
    except OSError:  # no usable stderr
        import pybullet

        return pybullet
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), fd)
            import pybullet
    finally:
        os.dup2(saved, fd)
        os.close(saved)
    return pybullet


def gl_projection(camera: CameraIntrinsics, near_m: float, far_m: float) -> np.ndarray:
    """(4, 4) OpenGL projection reproducing ``K`` in TinyRenderer's pixel grid (row-major).

    TinyRenderer samples pixel column ``i`` at window coordinate ``x = i`` (not ``i + 0.5``), which is
    the OpenCV convention, and PyBullet returns rows top-down, so with ``X = x_gl, Y = -y_gl,
    Z = -z_gl``: ``ndc_x = 2u/W - 1`` and ``ndc_y = 1 - 2(v + 1)/H``. Clip ``w`` is ``Z + _W_EPS``.
    """
    W, H = camera.width, camera.height
    n, f = near_m, far_m
    return np.array([
        [2 * camera.fx / W, -2 * camera.skew / W, 1 - 2 * camera.cx / W, 0.0],
        [0.0, 2 * camera.fy / H, 2 * (camera.cy + 1) / H - 1, 0.0],
        [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
        [0.0, 0.0, -1.0, _W_EPS],
    ])


def gl_view(pose: Pose | tuple[float, float, float], height_m: float) -> np.ndarray:
    """(4, 4) OpenGL view matrix (row-major) of the camera at ``pose``; PyBullet world = ``(x, z, h)``."""
    x, z, theta = (float(v) for v in pose)
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[s, -c, 0.0], [0.0, 0.0, 1.0], [-c, -s, 0.0]])  # rows: right, up, backward
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ np.array([x, z, float(height_m)])
    return V


class PyBulletRenderer:
    """TinyRenderer images of ``world`` through ``camera`` at ``camera_height_m`` (headless, CPU).

    ``cull`` hides panels that cannot be seen before each frame (same image, 5-10 % faster);
    ``lighting``: TinyRenderer's ``(ambient, diffuse)`` coefficients; ``light_direction``: towards
    its one directional light, world axes ``(x, z, up)``; ``light_rgb``: that light's colour (it
    tints the diffuse term only; see :mod:`topomap.sim.conditions`); ``cell_m``: wall strips and
    floor/ceiling cells are at most this wide [m]. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        world: World,
        camera: CameraIntrinsics,
        camera_height_m: float = CAMERA_HEIGHT_M,
        *,
        cull: bool = True,
        lighting: tuple[float, float] = (0.75, 0.35),
        light_direction: tuple[float, float, float] = (0.4, 0.7, 1.0),
        light_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0),
        far_m: float | None = None,
        cell_m: float = 1.0,
    ) -> None:
        if not camera.width or not camera.height:
            raise ConfigError("the simulated camera needs an image size (width, height)")
        if camera.has_distortion:
            raise ConfigError("the simulated camera cannot have lens distortion; give a pinhole camera")
        if not 0.0 < camera_height_m < world.wall_height_m:
            raise ConfigError(f"camera height {camera_height_m} m must lie between the floor and the ceiling ({world.wall_height_m} m)")
        self.camera = camera
        self.world = world
        self.camera_height_m = float(camera_height_m)
        self.cull = bool(cull) and camera.skew == 0.0
        self._ambient, self._diffuse = (float(v) for v in lighting)
        self._light_dir = [float(v) for v in light_direction]
        self._light_rgb = [float(v) for v in light_rgb]
        self._cell = float(cell_m)
        x0, z0, x1, z1 = world.bounds()
        self._far = float(far_m or 2.0 * math.hypot(x1 - x0, z1 - z0) + 10.0)
        self._p = _import_pybullet()
        self._cid = self._p.connect(self._p.DIRECT)
        self._proj = gl_projection(camera, _NEAR_M, self._far).T.flatten().tolist()
        try:
            self._build()
        except Exception:
            self.close()
            raise
        # Bearings of the pixel columns, for visibility culling: tan = (u - cx) / fx, positive right.
        self._col_tan = (np.arange(camera.width) - camera.cx) / camera.fx

    # ------------------------------------------------------------------ scene
    def _build(self) -> None:
        p, cid, w = self._p, self._cid, self.world
        H = w.wall_height_m
        keys = sorted({(wl.texture, 0) for wl in w.walls}
                      | {(t, k) for t in (w.floor_texture, w.ceiling_texture) for k in range(w.tile_variants)})
        tex_ids: dict[tuple[str, int], int] = {}
        tex_w: dict[str, float] = {}
        with tempfile.TemporaryDirectory(prefix="topomap-tex-") as tmp:
            for i, (key, k) in enumerate(keys):
                img = tx.texture_variant(key, k, w.texture_dir)
                path = Path(tmp) / f"{i}.png"
                cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
                tex_ids[key, k] = p.loadTexture(str(path), physicsClientId=cid)
                tex_w[key] = H * img.shape[1] / img.shape[0]

        def mesh(vertices, uvs, indices, normal, key, variant: int = 0) -> int:
            vs = p.createVisualShape(
                p.GEOM_MESH, vertices=vertices, indices=indices, uvs=uvs, normals=[normal] * len(vertices),
                physicsClientId=cid,
            )
            body = p.createMultiBody(baseMass=0, baseVisualShapeIndex=vs, physicsClientId=cid)
            p.changeVisualShape(body, -1, textureUniqueId=tex_ids[key, variant], rgbaColor=[1, 1, 1, 1], physicsClientId=cid)
            return body

        # Quads are cut into cells of cell_m: TinyRenderer tests every pixel of a triangle's bounding
        # box, and a long wall seen at a grazing angle has a box far larger than its area. (Measured:
        # a few per cent either way; shading each covered pixel once is the cost that dominates.)
        self._wall_bodies = []
        for wl in w.walls:
            L, tw = wl.length, tex_w[wl.texture]
            nx_, nz_ = -(wl.z1 - wl.z0) / L, (wl.x1 - wl.x0) / L  # the left normal faces the free side
            n = max(1, math.ceil(L / self._cell))
            verts, uvs, idx = [], [], []
            for k in range(n + 1):
                f = k / n
                x, z = wl.x0 + f * (wl.x1 - wl.x0), wl.z0 + f * (wl.z1 - wl.z0)
                # Seen from the free side (x0, z0) is on the right: the texture runs from (x1, z1).
                verts += [[x, z, 0.0], [x, z, H]]
                uvs += [[(1 - f) * L / tw, 0.0], [(1 - f) * L / tw, 1.0]]
            for k in range(n):  # counter-clockwise seen from the free side (back faces are culled)
                b0, t0, b1, t1 = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
                idx += [b0, t0, t1, b0, t1, b1]
            self._wall_bodies.append(mesh(verts, uvs, idx, [nx_, nz_, 0.0], wl.texture))
        ft, ct = tx.FLOOR_TILE_M, tx.CEILING_TILE_M

        def surface(r, period: float, height: float, key: str) -> int:
            """One body of floor (height 0) or ceiling over the rectangle ``r``, texture variant by position."""
            nxc = max(1, math.ceil((r[2] - r[0]) / self._cell))
            nzc = max(1, math.ceil((r[3] - r[1]) / self._cell))
            xs = np.linspace(r[0], r[2], nxc + 1)
            zs = np.linspace(r[1], r[3], nzc + 1)
            grid = [(float(x), float(z)) for z in zs for x in xs]
            tris = []
            for j in range(nzc):
                for i in range(nxc):
                    a, b = j * (nxc + 1) + i, j * (nxc + 1) + i + 1
                    c, d = a + nxc + 1, b + nxc + 1
                    # counter-clockwise seen from above (the floor) or from below (the ceiling)
                    tris += [a, b, d, a, d, c] if height == 0.0 else [a, d, b, a, c, d]
            variant = _tile_variant((r[0] + r[2]) / 2, (r[1] + r[3]) / 2, period, w.tile_variants)
            return mesh([[x, z, height] for x, z in grid], [[x / period, z / period] for x, z in grid], tris,
                        [0, 0, 1 if height == 0.0 else -1], key, variant)

        floor_rects = _tile_cells(w, ft)
        ceiling_rects = _tile_cells(w, ct)
        self._floor_bodies = [surface(r, ft, 0.0, w.floor_texture) for r in floor_rects]
        self._ceiling_bodies = [surface(r, ct, H, w.ceiling_texture) for r in ceiling_rects]
        for m in w.markers:
            vs = p.createVisualShape(p.GEOM_SPHERE, radius=m.radius_m, rgbaColor=[c / 255.0 for c in m.color] + [1.0], physicsClientId=cid)
            p.createMultiBody(baseMass=0, baseVisualShapeIndex=vs, basePosition=[m.x, m.z, m.height_m], physicsClientId=cid)
        self._bodies = np.array(self._wall_bodies + self._floor_bodies + self._ceiling_bodies)
        self._shown = np.ones(len(self._bodies), dtype=bool)
        seg = w.segments
        self._seg_a = seg[:, 0:2]
        self._seg_d = seg[:, 2:4] - seg[:, 0:2]
        self._floor_rects = np.array(floor_rects)
        self._ceiling_rects = self._floor_rects if ceiling_rects == floor_rects else np.array(ceiling_rects)
        log.debug("PyBullet scene: %d wall panels, %d floor and %d ceiling cells, %d textures", len(self._wall_bodies),
                  len(self._floor_bodies), len(self._ceiling_bodies), len(keys))

    # ------------------------------------------------------------------ visibility
    def visible(self, camera_pose: Pose) -> np.ndarray:
        """Boolean mask over walls + floor tiles + ceiling tiles that pixel columns can see from ``camera_pose``."""
        x, z, theta = (float(v) for v in camera_pose)
        c, s = math.cos(theta), math.sin(theta)
        # Floor-plan ray of each pixel column: forward + tan * right, right = (s, -c).
        d = np.stack([c + self._col_tan * s, s - self._col_tan * c], axis=1)  # (W, 2)
        a = self._seg_a - (x, z)  # (S, 2)
        e = self._seg_d
        # Solve t d = a + q e for (t, q) with Cramer's rule; cross(u, v) = u0 v1 - u1 v0.
        den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (W, S)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (a[None, :, 0] * e[None, :, 1] - a[None, :, 1] * e[None, :, 0]) / den
            q = (a[None, :, 0] * d[:, None, 1] - a[None, :, 1] * d[:, None, 0]) / den
        # The first wall along each ray, with the panels as they are ...
        ahead = np.isfinite(t) & (t > 0)
        t_first = np.where(ahead & (q >= 0) & (q <= 1), t, np.inf).min(axis=1)  # (W,) in units of |d| >= 1
        # ... and every panel within 2 px + 2 cm of that hit, so rounding in the rasteriser (a ray
        # grazing a corner, a joint between two panels) never uncovers a hidden panel.
        seg_len = np.maximum(np.hypot(e[:, 0], e[:, 1]), 1e-9)
        slack = (0.02 + 2.0 * np.where(np.isfinite(t_first), t_first, 0.0) / self.camera.fx)[:, None]
        q_tol = slack / seg_len[None, :]
        with np.errstate(invalid="ignore"):
            near = ahead & (q >= -q_tol) & (q <= 1 + q_tol) & (t <= t_first[:, None] + slack + 0.05)
        walls = near.any(axis=0)
        # Floor/ceiling tiles crossed by a ray before its first wall (slab test, rays x rects).
        reach = np.where(np.isfinite(t_first), t_first + 0.05, self._far)[:, None]
        floor = self._crossed(self._floor_rects, x, z, d, reach)
        ceiling = floor if self._ceiling_rects is self._floor_rects else self._crossed(self._ceiling_rects, x, z, d, reach)
        return np.concatenate([walls, floor, ceiling])

    @staticmethod
    def _crossed(r: np.ndarray, x: float, z: float, d: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """Which rectangles ``r`` (R, 4) the rays ``d`` (W, 2) from ``(x, z)`` cross before ``reach`` (W, 1)."""
        dx, dz = d[:, 0:1], d[:, 1:2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx0, tx1 = (r[None, :, 0] - x) / dx, (r[None, :, 2] - x) / dx
            tz0, tz1 = (r[None, :, 1] - z) / dz, (r[None, :, 3] - z) / dz
        # A zero direction component leaves 0/0 = NaN (on the slab edge) or +-inf: both handled below.
        in_x = np.where(dx != 0, True, (r[None, :, 0] <= x) & (x <= r[None, :, 2]))
        in_z = np.where(dz != 0, True, (r[None, :, 1] <= z) & (z <= r[None, :, 3]))
        tmin = np.maximum(np.nan_to_num(np.minimum(tx0, tx1), nan=-np.inf), np.nan_to_num(np.minimum(tz0, tz1), nan=-np.inf))
        tmax = np.minimum(np.nan_to_num(np.maximum(tx0, tx1), nan=np.inf), np.nan_to_num(np.maximum(tz0, tz1), nan=np.inf))
        enter = np.maximum(tmin, 0.0)
        return (in_x & in_z & (tmax >= enter) & (enter <= reach)).any(axis=0)

    def _apply_visibility(self, mask: np.ndarray) -> None:
        p, cid = self._p, self._cid
        for i in np.flatnonzero(mask != self._shown):
            # TinyRenderer skips objects of zero alpha without touching their triangles.
            rgba = [1, 1, 1, 1] if mask[i] else [1, 1, 1, 0]
            p.changeVisualShape(int(self._bodies[i]), -1, rgbaColor=rgba, physicsClientId=cid)
        self._shown = mask.copy()

    # ------------------------------------------------------------------ rendering
    def render(self, camera_pose: Pose) -> np.ndarray:
        """``(H, W, 3) uint8`` RGB image from ``camera_pose = (x, z, theta)`` (a fresh array)."""
        if self._cid is None:
            raise ConfigError("this renderer is closed; create a new one")
        self._apply_visibility(self.visible(camera_pose) if self.cull else np.ones(len(self._bodies), dtype=bool))
        view = gl_view(camera_pose, self.camera_height_m).T.flatten().tolist()
        W, H = self.camera.width, self.camera.height
        _, _, rgba, _, _ = self._p.getCameraImage(
            W, H, view, self._proj,
            renderer=self._p.ER_TINY_RENDERER,
            flags=self._p.ER_NO_SEGMENTATION_MASK,
            shadow=0,
            lightDirection=self._light_dir,
            lightColor=self._light_rgb,
            lightAmbientCoeff=self._ambient,
            lightDiffuseCoeff=self._diffuse,
            lightSpecularCoeff=0.0,
            physicsClientId=self._cid,
        )
        return np.ascontiguousarray(np.asarray(rgba, dtype=np.uint8).reshape(H, W, 4)[:, :, :3])

    def close(self) -> None:
        if getattr(self, "_cid", None) is not None:
            with contextlib.suppress(Exception):
                self._p.disconnect(physicsClientId=self._cid)
            self._cid = None

    def __enter__(self) -> PyBulletRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        self.close()


def _tile_cells(world: World, period: float) -> list[tuple[float, float, float, float]]:
    """The free floor's rectangles ``(x0, z0, x1, z1)``: as they are when the world tiles one texture,
    else cut at every multiple of ``period`` so that each texture tile can show its own variant."""
    if world.tile_variants == 1:
        return [(r.x0, r.z0, r.x1, r.z1) for r in world.free]
    cells = []
    for r in world.free:
        xs = [r.x0] + [k * period for k in range(math.floor(r.x0 / period) + 1, math.ceil(r.x1 / period))] + [r.x1]
        zs = [r.z0] + [k * period for k in range(math.floor(r.z0 / period) + 1, math.ceil(r.z1 / period))] + [r.z1]
        cells += [(x0, z0, x1, z1) for z0, z1 in zip(zs, zs[1:]) for x0, x1 in zip(xs, xs[1:]) if x1 > x0 and z1 > z0]
    return cells


def _tile_variant(x: float, z: float, period: float, variants: int) -> int:
    """Texture variant of the tile holding the point ``(x, z)`` (a cell's centre: never on a tile edge):
    a spatial hash of the tile's index (Teschner et al.'s primes), the same on every machine; 0 when
    the world tiles one texture."""
    if variants == 1:
        return 0
    i, j = math.floor(x / period), math.floor(z / period)
    return ((i * 73856093) ^ (j * 19349663)) % variants


#: Rendering backends: name -> factory ``(world, camera, camera_height_m) -> Renderer``.
RENDERERS: dict[str, Callable[..., Renderer]] = {"pybullet": PyBulletRenderer}


def make_renderer(name: str, world: World, camera: CameraIntrinsics, camera_height_m: float = CAMERA_HEIGHT_M, **options) -> Renderer:
    """The ``name`` backend of :data:`RENDERERS`; an unknown name lists the valid ones."""
    try:
        factory = RENDERERS[name]
    except KeyError:
        raise unknown_choice("renderer", name, RENDERERS) from None
    return factory(world, camera, camera_height_m, **options)
