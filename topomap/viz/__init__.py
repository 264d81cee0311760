"""Drawings and recordings of maps and navigation runs (each imports its heavy library on first use).

* :mod:`topomap.viz.plots` — PNG drawings with matplotlib: the map graph with thumbnails;
* :mod:`topomap.viz.animation` — the camera animation of a run (GIF always, MP4 with the ``viz`` extra);
* :mod:`topomap.viz.rerun` — Rerun recordings of runs and maps (``viz`` extra: ``rerun-sdk``);
* :mod:`topomap.viz.overlay` — what one control step matched, shared by the two above.
"""

from __future__ import annotations

_LAZY = {
    "plot_map": "topomap.viz.plots",
    "EDGE_STYLE": "topomap.viz.plots",
    "CameraAnimation": "topomap.viz.animation",
    "RerunLogger": "topomap.viz.rerun",
    "log_map": "topomap.viz.rerun",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'topomap.viz' has no attribute {name!r}")
