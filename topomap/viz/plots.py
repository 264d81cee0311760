"""Plots (matplotlib, Agg backend: no screen needed). Each function writes a PNG and returns its path."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import networkx as nx  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.offsetbox import AnnotationBbox, OffsetImage  # noqa: E402

from topomap.graph import EdgeKind, TopoMap  # noqa: E402

__all__ = ["plot_map", "EDGE_STYLE"]

#: How each edge kind is drawn: loop closures stand out.
EDGE_STYLE = {
    EdgeKind.SEQUENTIAL: {"color": "0.35", "linestyle": "-", "linewidth": 1.6},
    EdgeKind.LOOP: {"color": "tab:red", "linestyle": "--", "linewidth": 1.4},
    EdgeKind.MANUAL: {"color": "tab:blue", "linestyle": ":", "linewidth": 1.4},
}


def _layout(m: TopoMap, positions: dict[str, np.ndarray] | None) -> tuple[dict[int, np.ndarray], bool]:
    """Node positions: ground truth of the keyframe image when given, else a seeded graph layout."""
    if positions:
        pos = {n.id: positions[n.source] for n in m.nodes.values() if n.source in positions}
        if len(pos) == len(m.nodes):
            return pos, True
    g = m.graph
    return {k: np.asarray(v) for k, v in nx.kamada_kawai_layout(g).items()} if len(g) > 1 else {n: np.zeros(2) for n in g}, False


def plot_map(m: TopoMap, path: str | Path, positions: dict[str, np.ndarray] | None = None, max_thumbnails: int = 150,
             title: str | None = None) -> Path:
    """Draw the graph with node thumbnails; ``positions`` maps keyframe file names to 2-D ground
    truth (from :func:`topomap.groundtruth.read_poses`). Loop edges are dashed red."""
    pos, metric = _layout(m, positions)
    fig, ax = plt.subplots(figsize=(10, 8), dpi=110)
    for e in sorted(m.edges.values(), key=lambda e: e.key):
        a, b = pos[e.a], pos[e.b]
        ax.plot([a[0], b[0]], [a[1], b[1]], zorder=1, **EDGE_STYLE[e.kind])
    pts = np.array([pos[n] for n in sorted(m.nodes)]) if m.nodes else np.zeros((0, 2))
    if len(pts):
        ax.scatter(pts[:, 0], pts[:, 1], s=18, c="k", zorder=2)
    span = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 1.0
    if 0 < len(m.nodes) <= max_thumbnails:
        shown_px = min(60.0, 250.0 / np.sqrt(len(m.nodes)))  # thumbnails shrink as the map grows
        for n in m.nodes.values():
            box = AnnotationBbox(OffsetImage(n.thumbnail, cmap="gray", zoom=shown_px / max(n.thumbnail.shape)),
                                 pos[n.id], frameon=True, pad=0.1, zorder=3)
            ax.add_artist(box)
            ax.annotate(str(n.id), pos[n.id], xytext=(0, 0.4 * shown_px + 3), textcoords="offset points",
                        fontsize=7, ha="center", va="bottom", zorder=4, color="tab:blue", weight="bold")
    for kind, style in EDGE_STYLE.items():
        ax.plot([], [], label=f"{kind.value} ({m.edges_by_kind()[kind.value]})", **style)
    ax.legend(loc="best", fontsize=8)
    ax.set_aspect("equal" if metric else "auto")
    if metric:
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    else:
        ax.set_axis_off()
    ax.set_title(title or f"{len(m.nodes)} nodes, {len(m.edges)} edges, {len(m.components())} component(s)")
    if len(pts):
        pad = 0.08 * span + 1e-6
        ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
        ax.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
