"""Ground-truth files — used only for plots and scoring, never by localization or navigation.

* :func:`read_poses` reads a poses CSV keyed by image file name: either planar ``image,x,z,theta``
  (what ``topomap sim teach`` writes) or 3-D camera centres ``image,cx,cy,cz[,r11..r33]``
  (castle-p30's ``poses_camera_to_world.csv``).
  :meth:`PoseTable.positions_2d` turns them into floor-plan positions.
* :class:`GroundTruth` says, for each query image, which of the map's frames show the same place.
  It is made from a correspondence CSV (:func:`read_correspondences`: corridor-style
  ``query_file,matching_ref_indices`` or ``query_file,matching_ref_files``), from identical file
  names (:func:`same_name`, e.g. Nordland) or from poses and a distance (:func:`from_poses`).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from topomap.errors import DatasetError

__all__ = ["PoseTable", "read_poses", "GroundTruth", "read_correspondences", "same_name", "from_poses", "right_nodes"]


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        raise DatasetError(f"file {path} does not exist")
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

    @cached_property
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


# ---------------------------------------------------------------------- place correspondences
@dataclass(frozen=True)
class GroundTruth:
    """``matches[query file name]`` = the map frames (file names) showing the same place.

    A query whose set is empty has no true match in the map (a correct system answers "unknown").
    """

    matches: dict[str, frozenset[str]]

    def __contains__(self, query: str) -> bool:
        return query in self.matches

    def correct_nodes(self, query: str, node_frames: dict[int, set[str]]) -> set[int]:
        """Nodes representing at least one matching frame (``node_frames``: node -> frame names)."""
        want = self.matches.get(query, frozenset())
        return {n for n, frames in node_frames.items() if frames & want}


def right_nodes(truth: GroundTruth, tmap) -> Callable[[str], set[int]]:
    """Query name -> the map nodes that are right for it: those representing a matching frame, with
    the nodes of other experiences joined to them (one place, :meth:`TopoMap.place_ids`); empty for
    a query ``truth`` does not list (a place not in the map)."""
    node_frames: dict[int, set[str]] = {n: set() for n in tmap.nodes}
    for f in tmap.frames:
        if f.node is not None and f.node in node_frames:
            node_frames[f.node].add(f.source)
    place = tmap.place_ids()
    members: dict[int, set[int]] = {}
    for n, p in place.items():
        members.setdefault(p, set()).add(n)

    def of(query: str) -> set[int]:
        good = truth.correct_nodes(query, node_frames) if query in truth else set()
        return good.union(*(members[place[n]] for n in good if n in place))

    return of


def _map_frames(tmap) -> list:
    return [f for f in tmap.frames if f.node is not None]


def _check_known(refs: set[str], known: set[str], source: str) -> None:
    missing = sorted(refs - known)
    if missing:
        raise DatasetError(
            f"{source} names {len(missing)} frame(s) that are not in the map (e.g. {', '.join(missing[:3])}); "
            "is it the ground truth of this map?"
        )


def read_correspondences(path: str | Path, tmap) -> GroundTruth:
    """Correspondence CSV: ``query_file`` plus ``matching_ref_indices`` (``;``-separated positions of
    frames in the map's first sequence, as in VPR-Bench's corridor) or ``matching_ref_files``
    (``;``-separated file names)."""
    path = Path(path)
    rows = _rows(path)
    cols = set(rows[0])
    qcol = next((c for c in ("query_file", "query", "image") if c in cols), None)
    if qcol is None or not ({"matching_ref_indices", "matching_ref_files"} & cols):
        raise DatasetError(
            f"{path.name} is not a correspondence CSV: it needs a query_file column and matching_ref_indices or "
            f"matching_ref_files (columns found: {', '.join(sorted(cols))})"
        )
    # every input frame counts as known, a skipped (unreadable) one too: it is simply represented
    # by no node, so one bad reference image does not invalidate the whole ground truth
    frames = list(tmap.frames)
    by_index = {f.index: f.source for f in frames if f.sequence == 0}
    known = {f.source for f in frames}
    matches: dict[str, frozenset[str]] = {}
    bad_index: list[str] = []
    bad_files: set[str] = set()
    for i, r in enumerate(rows, start=2):
        q = Path(r[qcol]).name
        if "matching_ref_files" in cols:
            refs = {Path(x).name for x in (r["matching_ref_files"] or "").split(";") if x.strip()}
        else:
            refs = set()
            for tok in (r["matching_ref_indices"] or "").split(";"):
                tok = tok.strip()
                if not tok:
                    continue
                try:
                    idx = int(tok)
                except ValueError:
                    raise DatasetError(f"{path.name}, line {i}: {tok!r} is not a frame index") from None
                if idx not in by_index:
                    bad_index.append(str(idx))
                else:
                    refs.add(by_index[idx])
        bad_files.update(refs - known)
        matches[q] = frozenset(refs)
    _check_known(bad_files, known, path.name)  # after all rows, so the message lists a few of them
    if bad_index:
        raise DatasetError(
            f"{path.name} names frame indices that are not in the map (e.g. {', '.join(sorted(set(bad_index), key=int)[:3])}); "
            f"the map's first sequence has {len(by_index)} frames"
        )
    return GroundTruth(matches)


def same_name(query_names: list[str], tmap, tolerance: int = 0) -> GroundTruth:
    """A query matches the map frame with the same file name (and the ``tolerance`` frames before
    and after it in that frame's sequence)."""
    frames = list(tmap.frames)  # skipped frames too: their neighbours may be in the map (tolerance)
    by_name = {f.source: f for f in frames}
    by_pos = {(f.sequence, f.index): f.source for f in frames}
    missing = [q for q in query_names if q not in by_name]
    if len(missing) == len(query_names):
        raise DatasetError(
            f"no query file name is a frame of the map (e.g. {', '.join(query_names[:3])}); "
            "same-name ground truth needs queries named like the map's images"
        )
    matches = {}
    for q in query_names:
        f = by_name.get(q)
        if f is None:
            matches[q] = frozenset()
            continue
        near = {by_pos.get((f.sequence, f.index + d)) for d in range(-tolerance, tolerance + 1)}
        matches[q] = frozenset(n for n in near if n is not None)
    return GroundTruth(matches)


def from_poses(query_poses: PoseTable, map_poses: PoseTable, tmap, radius_m: float) -> GroundTruth:
    """A query matches every map frame within ``radius_m`` of it: floor-plan distance for planar
    poses, 3-D distance between camera centres otherwise."""
    if radius_m <= 0:
        raise DatasetError(f"--radius must be positive, got {radius_m}")
    if query_poses.planar != map_poses.planar:
        raise DatasetError("query and map poses must both be planar (x,z) or both 3-D (cx,cy,cz)")
    frames = [f.source for f in _map_frames(tmap)]
    missing = [f for f in frames if f not in map_poses]
    if missing:
        raise DatasetError(f"map poses lack {len(missing)} of the map's frames (e.g. {', '.join(missing[:3])})")
    dims = slice(0, 2) if map_poses.planar else slice(0, 3)
    M = np.stack([map_poses[f][dims] for f in frames])
    names = np.array(frames)
    matches = {}
    for q in query_poses.names:
        d = np.linalg.norm(M - query_poses[q][dims][None, :], axis=1)
        matches[q] = frozenset(names[d <= radius_m].tolist())
    return GroundTruth(matches)
