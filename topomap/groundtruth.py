"""Ground-truth files — used only for plots and scoring, never by localization or navigation.

* :func:`read_poses` reads a poses CSV keyed by image file name: either planar ``image,x,z,theta``
  (what ``topomap sim teach`` writes) or 3-D camera centres ``image,cx,cy,cz[,r11..r33]``
  (castle-p30's ``poses_camera_to_world.csv``).
  :meth:`PoseTable.positions_2d` turns them into floor-plan positions.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topomap.errors import DatasetError

__all__ = ["PoseTable", "read_poses"]


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        raise DatasetError(f"poses file {path} does not exist")
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DatasetError(f"cannot read CSV {path}: {e}") from None
    if not rows:
        raise DatasetError(f"CSV {path} has no rows")
    return rows


@dataclass(frozen=True)
class PoseTable:
    """Ground-truth poses by image file name.

    ``values``: (N, 3) float64 — ``(x, z, theta)`` [m, m, rad] when ``planar``, camera centres
    ``(cx, cy, cz)`` [m] otherwise (a missing theta is stored as 0).
    """

    names: tuple[str, ...]
    values: np.ndarray
    planar: bool

    def __contains__(self, name: str) -> bool:
        return name in self._row

    def __getitem__(self, name: str) -> np.ndarray:
        return self.values[self._row[name]]

    @property
    def _row(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.names)}

    def positions_2d(self) -> dict[str, np.ndarray]:
        """Floor-plan positions: planar poses keep ``(x, z)``; 3-D camera centres are projected on
        their two principal axes (the ground plane of a walk at roughly constant height)."""
        P = self.values
        if self.planar or len(P) < 3:
            xy = P[:, :2]
        else:
            centred = P - P.mean(axis=0)
            _, _, vt = np.linalg.svd(centred, full_matrices=False)
            xy = centred @ vt[:2].T
        return {n: xy[i] for i, n in enumerate(self.names)}


def read_poses(path: str | Path) -> PoseTable:
    """Read a poses CSV: ``image,x,z[,theta]`` (planar) or ``image,cx,cy,cz[,...]`` (3-D centres)."""
    path = Path(path)
    rows = _rows(path)
    cols = set(rows[0])
    key = next((k for k in ("image", "frame", "file", "name") if k in cols), None)
    if key is None:
        raise DatasetError(f"poses CSV {path} needs an 'image' column with file names")
    if {"x", "z"} <= cols:
        fields, planar = ["x", "z", "theta"] if "theta" in cols else ["x", "z"], True
    elif {"cx", "cy", "cz"} <= cols:
        fields, planar = ["cx", "cy", "cz"], False
    else:
        raise DatasetError(f"poses CSV {path} needs columns x,z[,theta] or cx,cy,cz; it has {', '.join(sorted(cols))}")
    names, values = [], []
    for i, r in enumerate(rows, start=2):
        try:
            v = [float(r[f]) for f in fields]
        except (TypeError, ValueError):
            raise DatasetError(f"poses CSV {path}, line {i}: a value is not a number") from None
        names.append(Path(r[key]).name)
        values.append(v + [0.0] * (3 - len(v)))
    return PoseTable(tuple(names), np.array(values, dtype=float), planar)
