"""Run every benchmark, one after the other: ``python benchmarks/run_all.py [--quick] [--only NAME ...]``.

Each benchmark prints its own table with a ratio against a baseline measured in the same run (these
machines are noisy). ``--quick`` shrinks the long ones (scale: 1k and 10k nodes; build scale: 1k
frames and a 100k-node index; navigation: 8 episodes; held-out navigation: 4) for a smoke run; the
figures quoted in the docs come from the full run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: name -> (full arguments, quick arguments)
BENCHMARKS = {
    "build": ([], []),
    "build_scale": ([], ["--sizes", "1000", "--query-nodes", "100000"]),
    "localize": ([], ["--dataset", "corridor", "--no-exhaustive-480"]),
    "scale": ([], ["--sizes", "1000,10000"]),
    "servo": ([], ["--trials", "100"]),
    "render": ([], []),
    "observability": ([], []),
    "navigate": (["--episodes", "40", "--worlds", "0,1"],
                 ["--episodes", "8", "--worlds", "0,1", "--max-hops", "10"]),
    "fuzz": ([], ["--quick"]),
    # held-out worlds and photographs (docs/navigation.md); hours on 2 shared cores in full
    "navigate_unseen": (["--episodes", "100", "--worlds", "100-109"],
                        ["--episodes", "4", "--worlds", "100,101", "--max-hops", "6", "--methods", "topomap,blind replay"]),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller runs of the long benchmarks")
    ap.add_argument("--only", nargs="+", choices=sorted(BENCHMARKS), help="run only these")
    args = ap.parse_args(argv)
    failed = []
    for name, (full, quick) in BENCHMARKS.items():
        if args.only and name not in args.only:
            continue
        cmd = [sys.executable, str(HERE / f"bench_{name}.py"), *(quick if args.quick else full)]
        print(f"\n===== {name}: {' '.join(cmd[1:])}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd)
        print(f"===== {name}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
