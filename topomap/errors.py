"""One exception family for the whole library.

Every error a user can cause (bad path, corrupt image, foreign map file, unknown option value,
unknown node id, no route) is a :class:`TopomapError`. The CLI prints its message as one line and
exits with code 1; any other exception is a bug and keeps its traceback.

Messages say what is wrong *and* what to do, in one line.
"""

from __future__ import annotations

from collections.abc import Iterable

__all__ = [
    "TopomapError",
    "DatasetError",
    "MapFormatError",
    "MapConflictError",
    "ConfigError",
    "NodeNotFoundError",
    "NoRouteError",
    "IndexMissingError",
    "MissingExtraError",
    "ClusterError",
    "CalibrationError",
    "unknown_choice",
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


def unknown_choice(what: str, value: object, choices: Iterable[str]) -> ConfigError:
    """The standard error for an unknown registry key: lists the valid choices."""
    valid = ", ".join(sorted(choices))
    return ConfigError(f"unknown {what} {value!r}; choose one of: {valid}")
