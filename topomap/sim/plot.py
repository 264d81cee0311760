"""Floor-plan drawings of a world, its routes and driven trajectories (matplotlib, Agg backend)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from topomap.errors import DatasetError
from topomap.sim.world import World

__all__ = ["plot_world"]


def _texture_colour(key: str) -> str:
    kind = key.split(":", 1)[0]
    if kind in ("photo", "user"):
        return "#8c564b"
    return "#1f77b4"


def plot_world(
    world: World,
    out: str | Path | None = None,
    *,
    route: str | None = None,
    trajectories: Mapping[str, np.ndarray] | None = None,
    title: str | None = None,
    dpi: int = 120,
):
    """Draw the floor plan (free floor grey, walls coloured by texture source: brown photographs,
    blue procedural), route ``route`` (arrow at its start) and ``trajectories`` (label -> (N, >=2)
    array of ``x, z[, theta]`` [m]). Saves a PNG to ``out`` if given; returns the matplotlib Figure.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    r = world.route(route) if route is not None else None
    x0, z0, x1, z1 = world.bounds()
    w, h = x1 - x0, z1 - z0
    fig = Figure(figsize=(max(4.0, 8.0 * w / max(w, h)) + 1.0, max(4.0, 8.0 * h / max(w, h))), dpi=dpi)
    ax = fig.add_subplot(1, 1, 1)
    for f in world.free:
        ax.add_patch(Rectangle((f.x0, f.z0), f.x1 - f.x0, f.z1 - f.z0, facecolor="#e8e8e8", edgecolor="none"))
    seg = world.segments
    ax.add_collection(LineCollection(seg.reshape(-1, 2, 2), colors=[_texture_colour(wl.texture) for wl in world.walls], linewidths=2.0))
    for m in world.markers:
        ax.plot(m.x, m.z, "o", color=np.array(m.color) / 255.0, markersize=5)
    if r is not None:
        p = r.points
        ax.plot(p[:, 0], p[:, 1], "--", color="#2ca02c", lw=1.5, label=f"route {r.name}")
        ax.plot(p[0, 0], p[0, 1], "o", color="#2ca02c", markersize=7)
        d = p[1] - p[0]
        d = 0.8 * d / max(np.linalg.norm(d), 1e-9)
        ax.annotate("", xy=(p[0, 0] + d[0], p[0, 1] + d[1]), xytext=(p[0, 0], p[0, 1]),
                    arrowprops=dict(arrowstyle="->", color="#2ca02c", lw=2))
    for label, traj in (trajectories or {}).items():
        t = np.asarray(traj, dtype=float)
        if t.ndim != 2 or t.shape[1] < 2:
            raise DatasetError(f"trajectory {label!r} must be an (N, 2) or (N, 3) array of x, z[, theta]")
        ax.plot(t[:, 0], t[:, 1], "-", lw=1.2, label=label)
    ax.set_aspect("equal")
    ax.set_xlim(x0 - 1, x1 + 1)
    ax.set_ylim(z0 - 1, z1 + 1)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.set_title(title or f"{world.name}: {len(world.walls)} wall panels, routes: {', '.join(world.route_names)}", fontsize=9)
    if r is not None or trajectories:
        ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    if out is not None:
        out = Path(out)
        try:
            fig.savefig(out)
        except OSError as e:
            raise DatasetError(f"cannot write plot {out}: {e.strerror or e}") from None
    return fig
