"""One exception family for the whole library.

Every error a user can cause (bad path, corrupt image, foreign map file, unknown option value,
unknown node id, no route) is a :class:`TopomapError`. The CLI prints its message as one line and
exits with code 1; any other exception is a bug and keeps its traceback.

Messages say what is wrong *and* what to do, in one line.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping
from typing import TypeVar

import numpy as np

__all__ = [
    "TopomapError",
    "DatasetError",
    "MapFormatError",
    "MapConflictError",
    "ConfigError",
    "ShapeError",
    "NodeNotFoundError",
    "NoRouteError",
    "IndexMissingError",
    "MissingExtraError",
    "ClusterError",
    "CalibrationError",
    "unknown_choice",
    "points_array",
]


class TopomapError(Exception):
    """Base class of every error topomap raises on purpose."""


class DatasetError(TopomapError):
    """Input data is missing, empty, unreadable or of the wrong kind."""


class MapFormatError(TopomapError):
    """A file is not a topomap map, is truncated, or was written by a newer topomap."""


class MapConflictError(TopomapError):
    """Another process is writing the map, or wrote it since it was loaded: nothing was written."""


class ConfigError(TopomapError, ValueError):
    """An option or configuration value is invalid (unknown preset, feature kind, vehicle...)."""


class ShapeError(TopomapError, ValueError):
    """An array handed to a public entry point has the wrong number of dimensions, shape or dtype."""


class NodeNotFoundError(TopomapError, KeyError):
    """A node id that the map does not contain."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class NoRouteError(TopomapError):
    """No path joins two nodes of the map."""


class IndexMissingError(TopomapError):
    """The map has no place-recognition index (built by an older topomap or with --no-index)."""


class MissingExtraError(TopomapError):
    """A feature needs an optional extra that is not installed (``pip install 'appearance-topomap[bags]'``...)."""


class CalibrationError(TopomapError):
    """A map cannot be calibrated (no keyframe images, too few nodes, samples all right or all wrong)."""


class ClusterError(TopomapError):
    """The workers of a build cannot be reached or cannot do their part (Dask scheduler down, a
    worker that cannot read the images)."""


def points_array(a, name: str, rows: int | None = None) -> np.ndarray:
    """``a`` as an (N, 2) float64 array of real coordinates (``rows``: N must equal it), or a
    :class:`ShapeError` naming the expected shape. Empty input of any shape is (0, 2): no matches."""
    arr = np.asarray(a)
    if arr.dtype.kind not in "iuf":
        raise ShapeError(f"{name} must hold real numbers (an (N, 2) array), got dtype {arr.dtype}")
    if arr.size == 0:
        arr = arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ShapeError(f"{name} must be an (N, 2) array of (x, y) points, got shape {arr.shape}")
    if rows is not None and len(arr) != rows:
        raise ShapeError(f"{name} has {len(arr)} rows where {rows} are expected: pass the matches row by row")
    return arr.astype(np.float64, copy=False)


_T = TypeVar("_T")
_E = TypeVar("_E", bound=enum.Enum)


def choose(registry: Mapping[str, _T], name: str, what: str) -> _T:
    """``registry[name]``; an unknown name is :func:`unknown_choice`'s error listing the valid ones."""
    try:
        return registry[name]
    except KeyError:
        raise unknown_choice(what, name, registry) from None


def parse_enum(cls: type[_E], name: str | _E, what: str) -> _E:
    """A member of the string enum ``cls`` from itself or its (case-insensitive) value; an unknown
    value is :func:`unknown_choice`'s error listing the valid ones."""
    if isinstance(name, cls):
        return name
    try:
        return cls(str(name).lower())
    except ValueError:
        raise unknown_choice(what, name, [k.value for k in cls]) from None


def unknown_choice(what: str, value: object, choices: Iterable[str]) -> ConfigError:
    """The standard error for an unknown registry key: lists the valid choices."""
    valid = ", ".join(sorted(choices))
    return ConfigError(f"unknown {what} {value!r}; choose one of: {valid}")
