"""Fuzz and fault run over map files and inputs: ``python benchmarks/bench_fuzz.py [--quick] [--workers N]``.

Regenerates the cases of ``tests/fuzz_cases.py`` (byte flips and truncations of a map, tampered rows
with and without recomputed checksums, views/triggers/extra tables, image bombs as files, bytes and
map BLOBs, SIGKILL during a commit, concurrent writers, hostile worlds and input folders) from seeds
other than the tests' (they start at 10000), runs each in a forked child under a memory limit and a
deadline, and prints the counts by outcome:

* clean error — one ``TopomapError`` line; success — worked, nothing lost or changed;
* data loss — a lost or partial update, or a map that opened with content other than it holds
  (``silent``); hang — past the deadline; traceback — any other exception; memory — peak RSS over
  500 MB (or killed by the limit).

The ratio printed is the mean case time against the baseline of opening and using the intact map.
Exit code 1 when any case ends in data loss, hang, traceback or memory.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import select
import signal
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

import cv2  # noqa: E402
import fuzz_cases as fc  # noqa: E402

from topomap.errors import TopomapError  # noqa: E402
from topomap.store import load_map  # noqa: E402

#: kind -> cases in the full run (>= 2000 in all); --quick takes a tenth.
FULL = {
    "flip": 900, "truncate": 150, "tamper": 4 * len(fc.TAMPERS), "schema": 4 * len(fc.SCHEMA_ATTACKS),
    "image_bomb": 140, "map_bomb": 140, "kill_commit": 200, "concurrent": 80, "world": 85, "inputs": 100,
}
SEED0 = 10_000  # the tests use seeds 0..n
DEADLINE_S = 30.0
MEMORY_HEADROOM = 1536 << 20  # address space a case child may add: a decoded bomb dies here, not the machine
PEAK_LIMIT_MB = 500.0
OUTCOMES = ("clean error", "success", "data loss", "hang", "traceback", "memory")


def classify(outcome: str) -> str:
    outcome = outcome.split(": ")[0] if outcome.startswith((fc.ERROR, fc.OK)) else outcome
    if outcome in (fc.ERROR, fc.OK):
        return outcome
    if outcome.startswith(("data loss", "silent")):
        return "data loss"
    return "traceback"


def start(ctx: fc.FuzzContext, kind: str, seed: int) -> tuple[int, int]:
    """Fork a child that runs one case and writes its JSON result to a pipe: (pid, read fd)."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child
        os.close(r)
        result = {"outcome": "traceback", "detail": ""}
        try:
            os.setpgid(0, 0)
            limit = _address_space() + MEMORY_HEADROOM
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            work = ctx.work / f"{kind}-{seed}"
            work.mkdir()
            out = fc.CASE_KINDS[kind](fc.FuzzContext(ctx.base, ctx.query, work, ctx.signature, ctx.grow_from), seed)
            result = {"outcome": out, "detail": out}
        except MemoryError:
            result = {"outcome": "memory", "detail": "MemoryError"}
        except TopomapError as e:  # a case that lets a clean error escape is still a clean error
            result = {"outcome": fc.ERROR, "detail": str(e)[:200]}
        except BaseException as e:  # noqa: BLE001 - everything else is what we count
            result = {"outcome": "traceback", "detail": f"{type(e).__name__}: {str(e)[:200]}"}
        finally:
            os.write(w, json.dumps(result).encode())
            os._exit(0)
    os.close(w)
    return pid, r


def run(ctx: fc.FuzzContext, plan: dict[str, int], workers: int) -> list[dict]:
    todo = [(k, SEED0 + i) for k, n in plan.items() for i in range(n)]
    todo.reverse()
    running: dict[int, tuple] = {}
    results = []
    while todo or running:
        while todo and len(running) < workers:
            kind, seed = todo.pop()
            pid, fd = start(ctx, kind, seed)
            running[pid] = (kind, seed, fd, time.monotonic(), bytearray())
        fds = {v[2]: pid for pid, v in running.items()}
        ready, _, _ = select.select(list(fds), [], [], 0.2)
        for fd in ready:
            chunk = os.read(fd, 65536)
            running[fds[fd]][4].extend(chunk)
        for pid, (kind, seed, fd, t0, buf) in list(running.items()):
            hung = time.monotonic() - t0 > DEADLINE_S
            if hung:
                try:
                    os.killpg(pid, signal.SIGKILL)  # the case and any writer it forked
                except ProcessLookupError:
                    pass
            done, status, usage = os.wait4(pid, os.WNOHANG)
            if done == 0:
                continue
            while True:  # drain what the child wrote before it exited
                more = os.read(fd, 65536)
                if not more:
                    break
                buf.extend(more)
            os.close(fd)
            seconds = time.monotonic() - t0
            peak_mb = usage.ru_maxrss / 1024
            try:
                res = json.loads(buf.decode())
                detail, outcome = res["detail"], res["outcome"]
                outcome = outcome if outcome == "memory" else classify(outcome)
            except ValueError:
                detail = f"the case process died (status {status})"
                outcome = "hang" if hung else "memory" if os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL else "traceback"
            if outcome not in ("hang",) and peak_mb > PEAK_LIMIT_MB:
                outcome, detail = "memory", f"peak {peak_mb:.0f} MB; {detail}"
            results.append({"kind": kind, "seed": seed, "outcome": outcome, "detail": detail,
                            "seconds": round(seconds, 3), "peak_mb": round(peak_mb, 1)})
            del running[pid]
    return results


def _address_space() -> int:
    """This process's virtual size [bytes] (the forked child starts from it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 1 << 30


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a tenth of the cases")
    ap.add_argument("--workers", type=int, default=2, help="cases run at once (each in its own process)")
    ap.add_argument("--only", nargs="+", choices=sorted(FULL), help="only these kinds")
    ap.add_argument("--json", type=Path, help="also write every case's result to this file")
    args = ap.parse_args(argv)
    plan = {k: max(1, n // 10) if args.quick else n for k, n in FULL.items() if not args.only or k in args.only}

    with tempfile.TemporaryDirectory(prefix="topomap-fuzz-") as tmp:
        root = Path(tmp)
        base = fc.make_base_map(root)
        m = load_map(base, images=True)
        query = cv2.imread(str(sorted((root / "frames").iterdir())[2]), cv2.IMREAD_GRAYSCALE)
        (root / "cases").mkdir()
        fc.world_attack_set()  # made once here, inherited by every forked case
        ctx = fc.FuzzContext(base, query, root / "cases", fc.map_signature(m), root / "grow")
        t0 = time.perf_counter()
        for _ in range(5):
            fc.exercise(base, query)
        baseline_ms = (time.perf_counter() - t0) / 5 * 1000
        t0 = time.perf_counter()
        results = run(ctx, plan, max(1, args.workers))
        wall = time.perf_counter() - t0

    by_kind: dict[str, Counter] = defaultdict(Counter)
    for r in results:
        by_kind[r["kind"]][r["outcome"]] += 1
    total = Counter(r["outcome"] for r in results)
    width = max(len(k) for k in plan) + 2
    print(f"fuzz run: {len(results)} cases (seeds from {SEED0}), {args.workers} workers, {wall:.0f} s")
    print("kind".ljust(width) + "".join(f"{o:>13}" for o in OUTCOMES) + "      mean s   max MB")
    for kind in plan:
        rs = [r for r in results if r["kind"] == kind]
        print(kind.ljust(width) + "".join(f"{by_kind[kind][o]:>13}" for o in OUTCOMES)
              + f"  {sum(r['seconds'] for r in rs) / len(rs):10.3f} {max(r['peak_mb'] for r in rs):8.0f}")
    print("total".ljust(width) + "".join(f"{total[o]:>13}" for o in OUTCOMES))
    mean_ms = 1000 * sum(r["seconds"] for r in results) / len(results)
    print(f"baseline: opening and using the intact map {baseline_ms:.1f} ms; a case {mean_ms:.1f} ms "
          f"(ratio {mean_ms / baseline_ms:.1f}: a copy, the damage, the same use, in a fresh process)")
    bad = [r for r in results if r["outcome"] in ("data loss", "hang", "traceback", "memory")]
    for r in bad[:20]:
        print(f"  {r['outcome']}: {r['kind']} seed {r['seed']}: {r['detail']}")
    killed = [r for r in results if r["kind"] == "kill_commit"]
    if killed and not [r for r in bad if r["kind"] == "kill_commit"]:
        states = Counter(r["detail"].split(": ", 1)[-1] for r in killed)
        print(f"kill -9 during a commit: {len(killed)} writers killed at random moments; every map then opened as "
              "exactly the old or the new map and took the next write: "
              + ", ".join(f"{n} {s}" for s, n in sorted(states.items())))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
