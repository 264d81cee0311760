"""Benchmark: the thesis' observability table, exact rank (GF(p), two points) vs a float SVD baseline.

Both methods use the same Lie-derivative rows (Taylor mode, topomap.observability.jets); the
baseline evaluates them in float64 at a random real point and takes ``numpy.linalg.matrix_rank`` of
the row-normalised matrix. Printed: time of each over every cell of the table, the ratio, and how
many cells the baseline gets right, per reading. A third column times the textbook route (symbolic
sympy Lie derivatives, rank over Q) on the cells it can do in reasonable time.

Run: ``python benchmarks/bench_observability.py`` (about a minute on 2 cores).
"""

from __future__ import annotations

import sys
import time
from collections import defaultdict

from topomap.observability import TABLE_CONFIGURATIONS, analyze, float_rank, symbolic_rank, vehicle_landmark_system


def cells(orders: int = 4):
    for vehicle in ("unicycle", "omni"):
        for name, (m, t, h) in TABLE_CONFIGURATIONS.items():
            yield vehicle, name, (m, t, h), "known", "analytic", 0
            for reading in ("analytic", "polynomial"):
                for k in range(orders):
                    yield vehicle, name, (m, t, h), "unknown", reading, k


def main() -> int:
    t_exact = defaultdict(float)
    t_float = defaultdict(float)
    agree = defaultdict(int)
    total = defaultdict(int)
    wrong = []
    for vehicle, name, (m, t, h), inputs, reading, k in cells():
        system = vehicle_landmark_system(vehicle, m, t, h, inputs, reading, k)
        col = "known" if inputs == "known" else reading
        t0 = time.perf_counter()
        rep = analyze(system, directions=False)
        t1 = time.perf_counter()
        fr = float_rank(system)
        t2 = time.perf_counter()
        t_exact[col] += t1 - t0
        t_float[col] += t2 - t1
        total[col] += 1
        if fr == rep.rank:
            agree[col] += 1
        else:
            wrong.append((vehicle, name, col, k, rep.unobservable_dimension, system.dimension - fr))
        if not rep.confirmed:
            print(f"warning: {vehicle} {name} {col} k={k}: the two exact points disagree", file=sys.stderr)

    # textbook symbolic route on the cells it finishes quickly (known inputs, reading A with k <= 1)
    t_sym = t_jets = 0.0
    sym_agree = sym_total = 0
    for vehicle, name, (m, t, h), inputs, reading, k in cells(orders=2):
        if inputs == "unknown" and reading == "polynomial":
            continue
        system = vehicle_landmark_system(vehicle, m, t, h, inputs, reading, k)
        depth = system.max_derivative if system.max_derivative is not None else system.dimension
        t0 = time.perf_counter()
        rs = symbolic_rank(system, depth)
        t1 = time.perf_counter()
        rj = analyze(system, directions=False).rank
        t2 = time.perf_counter()
        t_sym += t1 - t0
        t_jets += t2 - t1
        sym_total += 1
        sym_agree += rs == rj

    print("Observability table (7 configurations x 2 vehicles): exact GF(p) rank vs float64 SVD baseline")
    print(f"{'column':<12}{'cells':>6}{'exact [s]':>11}{'float [s]':>11}{'exact/float':>13}{'float agrees':>14}")
    for col in ("known", "analytic", "polynomial"):
        print(f"{col:<12}{total[col]:>6}{t_exact[col]:>11.2f}{t_float[col]:>11.2f}"
              f"{t_exact[col] / t_float[col]:>13.2f}{agree[col]:>8}/{total[col]}")
    te, tf = sum(t_exact.values()), sum(t_float.values())
    print(f"{'all':<12}{sum(total.values()):>6}{te:>11.2f}{tf:>11.2f}{te / tf:>13.2f}"
          f"{sum(agree.values()):>8}/{sum(total.values())}")
    if wrong:
        print("cells where the float baseline is wrong (vehicle, configuration, column, k, exact, float):")
        for w in wrong:
            print("  ", w)
    print()
    print("Textbook symbolic route (sympy Lie derivatives, rank over Q) on the known + A k<=1 cells")
    print(f"{'cells':>6}{'symbolic [s]':>14}{'exact jets [s]':>16}{'symbolic/jets':>15}{'agree':>8}")
    print(f"{sym_total:>6}{t_sym:>14.2f}{t_jets:>16.2f}{t_sym / t_jets:>15.1f}{sym_agree:>5}/{sym_total}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
