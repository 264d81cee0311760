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

# The public API, imported on first use: ``import topomap`` stays light (no OpenCV) for the CLI's
# --help and for code that only needs the errors.
_LAZY = {
    "build_map": "topomap.build",
    "load_map": "topomap.store",
    "save_map": "topomap.store",
    "TopoMap": "topomap.graph",
    "EdgeKind": "topomap.graph",
    "CameraIntrinsics": "topomap.camera",
    "load_camera": "topomap.camera",
    "Localizer": "topomap.localize",
    "SequenceLocalizer": "topomap.localize",
    "Localization": "topomap.localize",
    "Planner": "topomap.plan",
    "Route": "topomap.plan",
    "AppearanceServo": "topomap.servo.servo",
    "Navigator": "topomap.navigate",
    "BuildConfig": "topomap.config",
    "FeatureConfig": "topomap.config",
    "LocalizeConfig": "topomap.config",
    "PlanConfig": "topomap.config",
    "ServoConfig": "topomap.config",
    "NavigateConfig": "topomap.config",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'topomap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

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
    *_LAZY,
]
