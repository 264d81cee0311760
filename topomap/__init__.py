"""topomap: appearance-based topological maps, localization and servoing from images alone.

Implements the system of F. Belo, *Isn't Appearance Enough?* (University of Pisa, 2011): build a
graph of keyframes from an image sequence, localize a live image in it, plan a route of node
subgoals and servo from image to image while rejecting unknown input disturbances.
"""

from __future__ import annotations

import logging

from topomap.errors import (
    ConfigError,
    DatasetError,
    MapFormatError,
    NodeNotFoundError,
    NoRouteError,
    TopomapError,
)

__version__ = "0.1.0"

# The library never prints: it logs, and only the application decides where logs go.
logging.getLogger("topomap").addHandler(logging.NullHandler())

__all__ = [
    "__version__",
    "TopomapError",
    "DatasetError",
    "MapFormatError",
    "ConfigError",
    "NodeNotFoundError",
    "NoRouteError",
]
