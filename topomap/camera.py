"""Pinhole camera intrinsics: K, distortion, pixel <-> normalised coordinates and bearings.

Conventions (docs/theory.md section 1, eq. 1.18): ``lambda [u v 1]^T = K [I|0] P_cam`` with camera axes
X right, Y down, Z forward (OpenCV). Pixel coordinates follow OpenCV: the centre of the top-left
pixel is (0, 0), so the image centre is ``((w - 1) / 2, (h - 1) / 2)``.

Files understood by :func:`load_camera` (``--camera FILE``):

* YAML or JSON with ``fx, fy, cx, cy`` and optionally ``width, height, skew`` and ``distortion``
  (a list ``[k1, k2, p1, p2, k3]`` or a mapping with those keys) — the format
  :meth:`CameraIntrinsics.save` writes;
* OpenCV calibration YAML (``camera_matrix: {data: [...]}``, ``distortion_coefficients``,
  ``image_width``, ``image_height``);
* a plain text 3x3 matrix (``K.txt``), or a KITTI ``calib.txt`` (``P0: 12 numbers``).

Without a file, :meth:`CameraIntrinsics.default` assumes a 60 degree horizontal field of view,
square pixels and the principal point at the image centre; the map records which was used.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

from topomap.errors import DatasetError

__all__ = ["CameraIntrinsics", "load_camera", "DEFAULT_HFOV_DEG"]

#: Horizontal field of view assumed when no calibration is given [deg].
DEFAULT_HFOV_DEG = 60.0


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics with optional radial-tangential distortion.

    ``fx, fy, cx, cy, skew`` in pixels; ``width, height`` the image size they refer to (0 when
    unknown); ``distortion`` OpenCV order ``(k1, k2, p1, p2, k3)``; ``source`` says where they came
    from (a file name, ``"default"`` or ``"simulator"``).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 0
    height: int = 0
    skew: float = 0.0
    distortion: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))
    source: str = "given"

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise DatasetError(f"camera focal length {name}={v} must be a positive number")
        for name in ("cx", "cy", "skew"):
            if not math.isfinite(getattr(self, name)):
                raise DatasetError(f"camera parameter {name} is not a finite number")
        object.__setattr__(self, "distortion", tuple(float(d) for d in self.distortion))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def default(cls, width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> CameraIntrinsics:
        """Square pixels, principal point at the centre, ``hfov_deg`` horizontal field of view."""
        if width <= 0 or height <= 0:
            raise DatasetError(f"cannot derive a default camera for a {width}x{height} image")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, int(width), int(height), source="default")

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int = 0, height: int = 0, distortion=(), source: str = "given") -> CameraIntrinsics:
        """From a 3x3 matrix ``K``."""
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise DatasetError(f"camera matrix must be 3x3, got shape {K.shape}")
        dist = tuple(distortion) + (0.0,) * max(0, 5 - len(tuple(distortion)))
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height), K[0, 1], dist[:5], source)

    @classmethod
    def from_dict(cls, d: dict) -> CameraIntrinsics:
        """Inverse of :meth:`to_dict` (also accepts the plain ``fx, fy, cx, cy`` files)."""
        try:
            dist = d.get("distortion", d.get("dist", ()))
            if isinstance(dist, dict):
                dist = [dist.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")]
            dist = [float(x) for x in (dist or [])]
            dist = (dist + [0.0] * 5)[:5] if len(dist) <= 5 else dist
            return cls(
                float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                int(d.get("width", 0) or 0), int(d.get("height", 0) or 0),
                float(d.get("skew", 0.0)), tuple(dist), str(d.get("source", "given")),
            )
        except KeyError as e:
            raise DatasetError(f"camera description lacks {e.args[0]!r}; give fx, fy, cx, cy") from None
        except (TypeError, ValueError) as e:
            raise DatasetError(f"camera description has a non-numeric value ({e})") from None

    # ------------------------------------------------------------------ views
    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """(5,) float64 distortion coefficients, OpenCV order."""
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view [deg] (needs ``width``)."""
        return math.degrees(2 * math.atan2(self.width / 2.0, self.fx)) if self.width else float("nan")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["distortion"] = list(self.distortion)
        return d

    # ------------------------------------------------------------------ geometry
    def scaled(self, sx: float, sy: float | None = None, width: int | None = None, height: int | None = None) -> CameraIntrinsics:
        """Intrinsics of the image resized by ``(sx, sy)`` (OpenCV pixel-centre convention)."""
        sy = sx if sy is None else sy
        return replace(
            self,
            fx=self.fx * sx, fy=self.fy * sy, skew=self.skew * sx,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width if width is not None else round(self.width * sx)),
            height=int(height if height is not None else round(self.height * sy)),
        )

    def fitted_to(self, width: int, height: int) -> CameraIntrinsics:
        """These intrinsics for images of ``width x height``: rescaled if they refer to another size.

        Intrinsics with unknown size (0) are taken to describe images of the given size.
        """
        if not self.width or not self.height:
            return replace(self, width=int(width), height=int(height))
        if (self.width, self.height) == (width, height):
            return self
        return self.scaled(width / self.width, height / self.height, width, height)

    def normalize(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> normalised image coordinates (N, 2) ``(X/Z, Y/Z)``, undistorted."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(pts) == 0:
            return np.zeros((0, 2))
        if self.has_distortion:
            return cv2.undistortPoints(pts, self.K, self.dist).reshape(-1, 2)
        x = (pts[:, 0, 0] - self.cx - self.skew * (pts[:, 0, 1] - self.cy) / self.fy) / self.fx
        y = (pts[:, 0, 1] - self.cy) / self.fy
        return np.stack([x, y], axis=1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> pixels (N, 2) (no distortion applied)."""
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        uvw = P @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit viewing rays (N, 3) in the camera frame of pixels (N, 2), undistorted."""
        xy = self.normalize(pixels)
        rays = np.column_stack([xy, np.ones(len(xy))])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def bearing(self, pixels: np.ndarray) -> np.ndarray:
        """Horizontal bearing ``atan2(X, Z)`` [rad] of each pixel (N, 2) -> (N,); positive to the right."""
        return np.arctan(self.normalize(pixels)[:, 0])

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write YAML (``.yaml``/``.yml``) or JSON that :func:`load_camera` reads back."""
        path = Path(path)
        d = self.to_dict()
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps(d, indent=2) + "\n")
        else:
            path.write_text(yaml.safe_dump(d, sort_keys=False))
        return path


def _parse_matrix_text(text: str) -> np.ndarray | None:
    rows = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            rows.append([float(x) for x in line.replace(",", " ").split()])
        except ValueError:
            return None
    flat = [x for r in rows for x in r]
    return np.array(flat).reshape(3, 3) if len(flat) == 9 else None


def load_camera(path: str | Path) -> CameraIntrinsics:
    """Read intrinsics from a YAML / JSON / OpenCV YAML / 3x3 text / KITTI calib file."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"camera file {path} does not exist; give a YAML/JSON file with fx, fy, cx, cy")
    if path.is_dir():
        raise DatasetError(f"--camera {path} is a folder; give a YAML/JSON file with fx, fy, cx, cy")
    from topomap.images import read_file_bytes

    data = read_file_bytes(path, max_bytes=1 << 20, what="camera file")  # a FIFO or /dev/zero never ends
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise DatasetError(f"cannot read camera file {path}: {e}") from None
    # KITTI calib.txt: "P0: fx 0 cx tx 0 fy cy ty 0 0 1 tz"
    for line in text.splitlines():
        if line.startswith(("P0:", "P_rect_00:")):
            vals = [float(x) for x in line.split(":", 1)[1].split()]
            if len(vals) == 12:
                return CameraIntrinsics.from_matrix(np.array(vals).reshape(3, 4)[:, :3], source=path.name)
    K = _parse_matrix_text(text)
    if K is not None:
        return CameraIntrinsics.from_matrix(K, source=path.name)
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text.replace("%YAML:1.0", ""))
    except (json.JSONDecodeError, yaml.YAMLError) as e:
        raise DatasetError(f"camera file {path} is not valid YAML/JSON: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"camera file {path} must hold a mapping with fx, fy, cx, cy")
    if "camera_matrix" in data:  # OpenCV calibration YAML
        cm = data["camera_matrix"]
        K = np.array(cm["data"] if isinstance(cm, dict) else cm, dtype=float).reshape(3, 3)
        dc = data.get("distortion_coefficients", {})
        dist = dc.get("data", []) if isinstance(dc, dict) else (dc or [])
        return CameraIntrinsics.from_matrix(
            K, int(data.get("image_width", 0)), int(data.get("image_height", 0)), dist, source=path.name
        )
    cam = CameraIntrinsics.from_dict(data)
    return cam if cam.source != "given" else replace(cam, source=path.name)
