"""Place-recognition metrics: Recall@N, precision-recall curve, its area, recall at 100 % precision.

Conventions (as in VPR-Bench): every query gets an answer (the best node) and a confidence. At a
confidence threshold, the *accepted* answers are those at or above it; precision = correct accepted /
accepted, recall = correct accepted / queries that have a true match in the map. So the curve ends at
recall = Recall@1. (scikit-learn's ``precision_recall_curve`` divides by the number of correct
answers instead, which is a different curve — hence the few lines here.)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from topomap.errors import DatasetError
from topomap.graph import TopoMap
from topomap.calibration import expected_calibration_error, reliability
from topomap.groundtruth import GroundTruth, right_nodes
from topomap.localize import Localization

__all__ = ["QueryOutcome", "EvalResult", "evaluate", "pr_curve", "plot_pr"]


@dataclass(frozen=True)
class QueryOutcome:
    """One scored query: ``first_correct_rank`` is 1-based (0 when no ranked node is correct)."""

    query: str
    node: int
    confidence: float
    status: str
    correct: bool
    first_correct_rank: int
    has_match: bool


@dataclass
class EvalResult:
    queries: int
    queries_with_match: int
    recall_at: dict[int, float]
    auc: float
    recall_at_100_precision: float
    declared: float  # fraction of the queries declared `localized`
    declared_right: float  # fraction of the queries with a match declared `localized` and right
    declared_precision: float  # right among the declared (1.0 when none is declared)
    ece: float  # expected calibration error of the confidences (10 bins)
    calibrated: bool  # whether the confidences are the map's calibrated probabilities
    precision: np.ndarray = field(repr=False)
    recall: np.ndarray = field(repr=False)
    thresholds: np.ndarray = field(repr=False)
    outcomes: list[QueryOutcome] = field(repr=False, default_factory=list)

    def to_dict(self, per_query: bool = False) -> dict:
        d = {
            "queries": self.queries,
            "queries_with_match": self.queries_with_match,
            "recall_at_1": self.recall_at.get(1),
            "recall_at_5": self.recall_at.get(5),
            "recall_at_10": self.recall_at.get(10),
            "auc": self.auc,
            "recall_at_100_precision": self.recall_at_100_precision,
            "declared": self.declared,
            "declared_right": self.declared_right,
            "declared_precision": self.declared_precision,
            "ece": self.ece,
            "calibrated": self.calibrated,
        }
        if per_query:
            d["per_query"] = [o.__dict__ for o in self.outcomes]
        return d


def pr_curve(confidence: np.ndarray, correct: np.ndarray, positives: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision and recall at every distinct confidence threshold (descending), plus thresholds."""
    confidence = np.asarray(confidence, float)
    correct = np.asarray(correct, bool)
    if len(confidence) == 0 or positives == 0:
        return np.array([1.0]), np.array([0.0]), np.array([np.inf])
    order = np.argsort(-confidence, kind="stable")
    c, ok = confidence[order], correct[order]
    tp = np.cumsum(ok)
    accepted = np.arange(1, len(c) + 1)
    last = np.r_[c[1:] != c[:-1], True]  # evaluate only after all ties at a threshold
    precision = tp[last] / accepted[last]
    recall = tp[last] / positives
    return np.r_[1.0, precision], np.r_[0.0, recall], np.r_[np.inf, c[last]]


def evaluate(results: Sequence[tuple[str, Localization]], truth: GroundTruth, tmap: TopoMap, ns: Sequence[int] = (1, 5, 10)) -> EvalResult:
    """Score localizations ``[(query file name, Localization), ...]`` against ``truth``."""
    missing = [q for q, _ in results if q not in truth]
    if missing and len(missing) == len(results):
        raise DatasetError(
            f"the ground truth names none of the queries (e.g. {', '.join(q for q, _ in results[:3])}); is it the right file?"
        )
    good_of = right_nodes(truth, tmap)  # a node of another experience joined to a right one counts too
    outcomes = []
    for q, loc in results:
        good = good_of(q)
        ranks = [i + 1 for i, c in enumerate(loc.candidates) if c.node in good]  # candidates[0] is the answer
        outcomes.append(QueryOutcome(q, loc.node, float(loc.confidence), loc.status.value, loc.node in good,
                                     ranks[0] if ranks else 0, bool(good)))
    with_match = sum(o.has_match for o in outcomes)
    denom = max(1, with_match)
    recall_at = {n: sum(1 for o in outcomes if 0 < o.first_correct_rank <= n) / denom for n in ns}
    conf = np.array([o.confidence for o in outcomes])
    ok = np.array([o.correct for o in outcomes])
    precision, recall, thresholds = pr_curve(conf, ok, with_match)
    auc = float(np.trapezoid(precision, recall)) if len(recall) > 1 else 0.0
    at_full = recall[precision >= 1.0 - 1e-12]
    declared = np.array([o.status == "localized" for o in outcomes], bool)
    n_declared = int(declared.sum())
    return EvalResult(len(outcomes), with_match, recall_at, auc, float(at_full.max()) if len(at_full) else 0.0,
                      n_declared / max(1, len(outcomes)), int((declared & ok).sum()) / denom,
                      int((declared & ok).sum()) / n_declared if n_declared else 1.0,
                      expected_calibration_error(conf, ok), bool(results) and all(r.calibrated for _, r in results),
                      precision, recall, thresholds, outcomes)


def plot_pr(result: EvalResult, path: str | Path, label: str = "topomap", title: str | None = None) -> Path:
    """Write the precision-recall curve and, beside it, the reliability diagram as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, rel) = plt.subplots(1, 2, figsize=(10, 4.2), dpi=110)
    conf = np.array([o.confidence for o in result.outcomes])
    ok = np.array([o.correct for o in result.outcomes])
    mean_c, frac, counts = reliability(conf, ok)
    edges = np.linspace(0, 1, len(counts) + 1)
    used = counts > 0
    rel.bar(edges[:-1][used], frac[used], width=1 / len(counts), align="edge", alpha=0.6, edgecolor="k",
            label="fraction right")
    rel.plot([0, 1], [0, 1], "k--", lw=1, label="calibrated")
    rel.plot(mean_c[used], frac[used], "o", color="C3", label="bin: mean confidence, fraction right")
    for x, n in zip(edges[:-1][used], counts[used]):
        rel.annotate(str(int(n)), (x + 0.5 / len(counts), 0.02), ha="center", fontsize=7)
    kind = "calibrated probability" if result.calibrated else "raw confidence (uncalibrated)"
    rel.set_xlabel(kind)
    rel.set_ylabel("fraction of answers right")
    rel.set_xlim(0, 1)
    rel.set_ylim(0, 1.02)
    rel.grid(alpha=0.3)
    rel.legend(loc="upper left", fontsize=8)
    rel.set_title(f"reliability: ECE {result.ece:.3f}; declared {result.declared:.2f}, precision {result.declared_precision:.2f}")
    ax.plot(result.recall, result.precision, "-", lw=2, label=f"{label} (AUC {result.auc:.3f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    r = result.recall_at
    ax.set_title(title or f"R@1 {r.get(1, 0):.2f}  R@5 {r.get(5, 0):.2f}  R@10 {r.get(10, 0):.2f}")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
