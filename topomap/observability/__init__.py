"""Observability of bearing-only vehicle/landmark systems with known or unknown inputs, and an
unknown-input observer (docs/theory.md section 2; thesis chapters 2-3).

* :mod:`~topomap.observability.system`: sympy system descriptions, augmentation with the unknown
  inputs (readings A / P), the vehicle/landmark and scalar linear builders;
* :mod:`~topomap.observability.jets`: exact Lie derivatives at a point (Taylor mode over GF(p));
* :mod:`~topomap.observability.analysis`: exact generic rank, unobservable directions, the table;
* :mod:`~topomap.observability.observer`: high-gain differentiator + Jacobian pseudo-inverse observer.
"""

from __future__ import annotations

from topomap.observability.analysis import (
    PRIMES,
    TABLE_CONFIGURATIONS,
    Direction,
    ObservabilityReport,
    TableRow,
    analyze,
    default_cache_dir,
    float_rank,
    symbolic_rank,
    observability_table,
)
from topomap.observability.observer import (
    CONVERGENCE_TIME_S,
    ObserverConfig,
    Simulation,
    plot_simulation,
    simulate,
)
from topomap.observability.system import (
    DirectionKind,
    InputKind,
    Reading,
    Symmetry,
    System,
    augment,
    input_kind,
    linear_system,
    reading_kind,
    vehicle_landmark_system,
)

__all__ = [
    "CONVERGENCE_TIME_S",
    "ObserverConfig",
    "Simulation",
    "plot_simulation",
    "simulate",
    "PRIMES",
    "TABLE_CONFIGURATIONS",
    "Direction",
    "DirectionKind",
    "InputKind",
    "ObservabilityReport",
    "Reading",
    "Symmetry",
    "System",
    "TableRow",
    "analyze",
    "augment",
    "default_cache_dir",
    "float_rank",
    "input_kind",
    "linear_system",
    "observability_table",
    "reading_kind",
    "vehicle_landmark_system",
]
