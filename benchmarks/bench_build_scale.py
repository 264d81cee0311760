"""Benchmark: building big maps — 1k / 5k / 20k frames of simulator teach runs — and querying a
1M-node index (issue 17, "scale benchmark").

Frames: teach runs (``topomap.sim.teach``, 320x240, an image every 0.25 m or 10 deg) over a large
generated world (6 x 6 junctions, 6 rooms, seed 7), every route of it (the perimeter loop and the
rooms) driven again and again with the ``noisy`` disturbance (a new seed per pass: each pass sees
the world from a slightly different path, as a robot revisiting it would). The frames of the passes
in order make one sequence; a build of N frames takes the first N. Rendered once into ``--cache``.

Per size, in a fresh process (so its peak memory is its own): ``build_map`` with ``--workers``
(default: every core), then ``save_map`` (the map stays in the cache as ``frames_N.topomap``). Printed: wall time, frames/s, peak RSS of the build
process and of its workers (summed), nodes, loop edges, map bytes per node, and the loop-closure time
per new node at the start and at the end of the loop stage (the mean over its first and last 10 %
of nodes, from the stage's progress reports), in wall time and in CPU time of the build process and
its workers (the load-independent one): flat means the candidate sets stay bounded as the map grows. Baseline in the same run: the smallest size (ratios "x 1k").

1M nodes (``--query-nodes``): a synthetic inverted file (``BowIndex``) of that many nodes whose word
lists follow the word statistics of the real keyframes of the largest build (each node the words
of a real keyframe, shifted within frequency bands as ``bench_scale.py`` does), queried with real
keyframes: median / p90 of ``scores`` + ``top_k`` (the bag-of-words shortlist, reading at most
``LocalizeConfig.bow_max_postings`` postings per query) plus the guided verification of the top 10
against real features; the same shortlist reading every posting list (exact) for comparison, timed
apart; and the index's bytes per node (in RAM, and as the map file stores it).

Run: ``python benchmarks/bench_build_scale.py [--sizes 1000,5000,20000] [--workers N]
[--query-nodes 1000000] [--max-postings 1000000,2000000] [--cache DIR]`` (``--query-only`` takes the
map of the largest ``--sizes``). Run time on the 2 shared cores (load 4-9, docs/build.md): rendering
~9 frames/s per process (20k frames ~40 min), the 1k build ~5 min, the 5k build ~18 min, the 10k
build ~32 min, the 20k build over an hour; ``--sizes 1000,5000 --query-nodes 0`` is a run of about half an hour once
the frames are cached. The loop milliseconds are wall time: they follow the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WORLD_SEED = 7
LATTICE = (6, 6)
ROOMS = 6


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- frames
def render_frames(cache: Path, frames: int) -> Path:
    """A list file of at least ``frames`` teach-run images (rendering the passes still missing)."""
    from topomap.errors import DatasetError
    from topomap.sim.teach import teach
    from topomap.sim.world import generate_world

    world = generate_world(WORLD_SEED, lattice=LATTICE, rooms=ROOMS)
    cache.mkdir(parents=True, exist_ok=True)
    paths: list[str] = []
    p = 0
    while len(paths) < frames:
        for route in world.route_names:
            out = cache / f"pass{p:02d}_{route}"
            if not (out / "teach.json").exists():
                t0 = time.perf_counter()
                try:
                    teach(world, route, out, disturbance="noisy", seed=p, overwrite=True)
                except DatasetError as e:  # a pass the driver could not finish: left out
                    log(f"  pass {p} {route}: {e}")
                    continue
                log(f"  rendered pass {p} {route}: {len(list(out.glob('*.png')))} frames ({time.perf_counter() - t0:.0f} s)")
            if (out / "teach.json").exists():
                paths += [str(q) for q in sorted(out.glob("[0-9]*.png"))]
        p += 1
    listing = cache / f"frames_{frames}.txt"
    listing.write_text("\n".join(paths[:frames]) + "\n")
    return listing


# ----------------------------------------------------------------------------- one build (child process)
def build_one(listing: Path, workers: int | None, out_json: Path) -> None:
    sys.path.insert(0, str(HERE))
    from bench_build import cpu_seconds  # the workers' CPU from /proc, as bench_build.py reads it
    from topomap.build import BuildProgress, build_map
    from topomap.parallel import make_executor
    from topomap.store import save_map

    marks: list[tuple[int, float, float]] = []  # (nodes done, wall s, CPU s of this process and its workers)
    pids: list[int] = []

    def cpu_now() -> float:
        return time.process_time() + cpu_seconds(pids)

    def on_progress(p: BuildProgress) -> None:
        if p.stage == "loops":
            marks.append((p.done, time.perf_counter(), cpu_now()))
        elif p.stage == "index" and p.done == 1:
            marks.append((0, time.perf_counter(), cpu_now()))

    t0 = time.perf_counter()
    with make_executor(workers) as ex:
        pids[:] = getattr(ex, "worker_pids", lambda: [])()
        m = build_map(listing, on_progress=on_progress, executor=ex)
        desc = ex.describe()
        worker_peaks = [_peak_rss_mb(pid) for pid in getattr(ex, "worker_pids", lambda: [])()] or [0.0]
    t_build = time.perf_counter() - t0
    path = save_map(m, out_json.with_suffix(".topomap"), overwrite=True)
    size = path.stat().st_size
    self_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def per_node(column: int) -> dict:
        t = np.diff([mk[column] for mk in marks]) * 1e3 if len(marks) > 1 else np.zeros(0)
        tenth = max(1, len(t) // 10)
        return {"start": float(t[:tenth].mean()) if len(t) else 0.0, "end": float(t[-tenth:].mean()) if len(t) else 0.0,
                "mean": float(t.mean()) if len(t) else 0.0}

    wall, cpu = per_node(1), per_node(2)
    out_json.write_text(json.dumps({
        "frames": len(m.frames), "nodes": len(m.nodes), "loops": m.edges_by_kind()["loop"],
        "build_s": t_build, "bytes": size, "rss_mb": self_rss, "worker_rss_mb": max(worker_peaks),
        "workers_rss_mb": sum(worker_peaks),
        "loop_ms_start": wall["start"], "loop_ms_end": wall["end"], "loop_ms_mean": wall["mean"],
        "loop_cpu_ms_start": cpu["start"], "loop_cpu_ms_end": cpu["end"], "loop_cpu_ms_mean": cpu["mean"],
        "executor": desc,
    }))



def _peak_rss_mb(pid: int) -> float:
    """Peak resident memory of a live process (Linux ``VmHWM``) [MB]; 0 where unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def run_build(listing: Path, workers: int | None) -> dict:
    """One build in a fresh process; its map stays beside the listing (``*.topomap``)."""
    out = listing.with_suffix(".json")
    cmd = [sys.executable, __file__, "--child", str(listing), "--child-out", str(out)]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    subprocess.run(cmd, check=True)
    return json.loads(out.read_text())


# ----------------------------------------------------------------------------- 1M-node query
def _synthetic_chunks(uniq: list[np.ndarray], by_rank: np.ndarray, rank: np.ndarray, n_nodes: int, seed: int,
                      band: int, chunk: int = 20000):
    """Yield (first node, source keyframe per node, words (int32), node of each word) chunk by chunk:
    each synthetic node is a real keyframe's distinct words, each moved to another word of about the
    same frequency (a cyclic shift within frequency bands, as bench_scale.py does). Seeded: the same
    chunks every time they are generated."""
    rng = np.random.default_rng(seed)
    v = len(rank)
    flat = np.concatenate(uniq)
    length = np.array([len(u) for u in uniq])
    offset = np.concatenate(([0], np.cumsum(length)[:-1]))
    for start in range(0, n_nodes, chunk):
        n = min(chunk, n_nodes - start)
        src = rng.integers(len(uniq), size=n)
        lens = length[src]
        first = np.cumsum(lens) - lens  # each node's first slot in the chunk
        r = rank[flat[np.repeat(offset[src] - first, lens) + np.arange(int(lens.sum()))]]
        shift = np.repeat(rng.integers(1, band, size=n), lens)
        words = by_rank[np.minimum((r // band) * band + (r % band + shift) % band, v - 1)].astype(np.int32)
        yield start, src, words, np.repeat(np.arange(start, start + n, dtype=np.int32), lens)


def query_at_scale(listing: Path, n_nodes: int, queries: int = 50, band: int = 64, seed: int = 0,
                   budgets: list | None = None) -> dict:
    """Latency of the bag-of-words shortlist + guided verification at ``n_nodes`` synthetic nodes,
    reading at most ``LocalizeConfig.bow_max_postings`` postings per query; ``budgets``: other
    values of it measured on the same index (the results' ``others``)."""
    from dataclasses import replace

    from topomap.config import LocalizeConfig
    from topomap.matching import match_descriptors_grouped, verify
    from topomap.retrieval import BowIndex
    from topomap.store import load_map

    real = load_map(listing.with_suffix(".topomap"))  # the largest build: its vocabulary and real keyframes
    voc = real.index.vocabulary
    ids = sorted(real.nodes)
    feats = [real.nodes[i].features for i in ids]
    words = [real.index.words_of_features(i) for i in ids]
    counts = np.bincount(np.concatenate(words), minlength=voc.size)
    by_rank = np.argsort(-counts, kind="stable")
    rank = np.empty_like(by_rank)
    rank[by_rank] = np.arange(len(by_rank))
    uniq = [np.unique(w) for w in words]
    t0 = time.perf_counter()
    # word-major postings by a counting sort in two passes over the seeded chunks: no per-posting
    # 8-byte temporaries (a million nodes hold ~10^9 postings)
    per_word = np.zeros(voc.size, np.int64)
    for _, _, w, _ in _synthetic_chunks(uniq, by_rank, rank, n_nodes, seed, band):
        per_word += np.bincount(w, minlength=voc.size)
    indptr = np.concatenate(([0], np.cumsum(per_word)))
    rows = np.empty(int(indptr[-1]), np.int32)
    fill = indptr[:-1].copy()
    source = np.empty(n_nodes, np.int32)
    for start, src, w, r in _synthetic_chunks(uniq, by_rank, rank, n_nodes, seed, band):
        source[start : start + len(src)] = src
        order = np.argsort(w, kind="stable")
        ws, rs = w[order], r[order]
        first = np.flatnonzero(np.r_[True, ws[1:] != ws[:-1]])
        within = np.arange(len(ws)) - np.repeat(first, np.diff(np.r_[first, len(ws)]))
        rows[fill[ws] + within] = rs
        fill += np.bincount(w, minlength=voc.size)
    del fill
    index = BowIndex(voc, np.arange(n_nodes), indptr, rows, np.ones(len(rows), np.float32))
    build_s = time.perf_counter() - t0
    log(f"  {n_nodes} synthetic nodes: {len(rows)} postings ({build_s:.0f} s)")
    # queries: real keyframes (their own words are in no synthetic node: a place the index must rank
    # among a million look-alikes); the top 10 verified as Localizer does it (guided matching under
    # vocabulary-tree nodes, PROSAC), the candidates' features and words those of their source keyframe
    cfg = LocalizeConfig(descriptor="bow")
    vcfg = replace(real.config.match, ransac_method=cfg.verify_ransac_method, ransac_max_iters=cfg.verify_max_iters)
    level = voc.group_level(cfg.match_groups)
    groups = [voc.ancestors(w, level) for w in words]
    qrows = list(range(0, len(ids), max(1, len(ids) // queries)))[:queries]
    lengths = np.diff(index.indptr)

    def measure(budget: int | None) -> dict:
        times, bow_times, verify_times, exact_times, read, overlap = [], [], [], [], [], []
        for qr in qrows:
            qf, qwords = feats[qr], words[qr]
            t0 = time.perf_counter()
            scores = index.scores(qf, words=qwords, max_postings=budget)
            top = index.top_k(scores, cfg.shortlist_k)
            t1 = time.perf_counter()
            for node, _ in top:
                c = int(source[node])
                m = match_descriptors_grouped(qf, feats[c], groups[qr], groups[c], vcfg, float(cfg.guided_max_hamming))
                verify(qf, feats[c], vcfg, matches=m)
            t2 = time.perf_counter()
            if budget is None:  # the shortlist is the exact one
                exact, t3 = top, t2 + (t1 - t0)
            else:
                exact = index.top_k(index.scores(qf, words=qwords), cfg.shortlist_k)  # every non-stop word
                t3 = time.perf_counter()
            times.append((t2 - t0) * 1e3)
            bow_times.append((t1 - t0) * 1e3)
            verify_times.append((t2 - t1) * 1e3)
            exact_times.append((t3 - t2) * 1e3)
            kept, _ = index.query_terms(qf, qwords, budget)
            every, _ = index.query_terms(qf, qwords)
            read.append((int(lengths[kept].sum()), int(lengths[every].sum())))
            overlap.append(len({n for n, _ in top} & {n for n, _ in exact}) / max(1, len(exact)))
        read = np.array(read)
        return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
                "bow_median_ms": float(np.median(bow_times)), "verify_median_ms": float(np.median(verify_times)),
                "exact_bow_median_ms": float(np.median(exact_times)), "exact_bow_p90_ms": float(np.percentile(exact_times, 90)),
                "max_postings": budget, "read_median": float(np.median(read[:, 0])), "all_median": float(np.median(read[:, 1])),
                "overlap": float(np.mean(overlap))}

    result = measure(cfg.bow_max_postings)
    others = [measure(b) for b in (budgets or []) if b != cfg.bow_max_postings]
    stored = sum(a.nbytes for k, a in index.to_arrays().items() if k.startswith("bow_"))
    words_per_node = float(np.mean([len(w) for w in words])) * (2 if voc.size <= 1 << 16 else 4)
    return {**result, "others": others, "nodes": n_nodes, "ram_bytes_per_node": index.memory_bytes() / n_nodes,
            "stored_bytes_per_node": stored / n_nodes + words_per_node, "postings_per_node": len(rows) / n_nodes,
            "stop_words": int(index.stop_words.sum()), "words": voc.size, "build_s": build_s}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,5000,20000", help="frames per build, comma-separated")
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: every core)")
    ap.add_argument("--query-nodes", type=int, default=1_000_000, help="synthetic index size for the query latency (0: skip)")
    ap.add_argument("--max-postings", default="",
                    help="other LocalizeConfig.bow_max_postings values to time on the 1M index, comma-separated ('none': all)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "topomap-scale-frames",
                    help="folder for the rendered teach runs (kept between runs)")
    ap.add_argument("--render-only", action="store_true", help="render the frames of the largest size and stop")
    ap.add_argument("--query-only", action="store_true",
                    help="only the query part, on the map an earlier run built for the largest --sizes")
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--child-out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        build_one(args.child, args.workers, args.child_out)
        return 0
    try:
        sizes = sorted({int(s) for s in args.sizes.split(",") if s.strip()})
    except ValueError:
        print(f"Error: --sizes takes comma-separated frame counts, got {args.sizes!r}", file=sys.stderr)
        return 1
    if not sizes or sizes[0] < 10:
        print("Error: --sizes needs frame counts of at least 10", file=sys.stderr)
        return 1
    if args.workers is not None and args.workers < 1:
        print(f"Error: --workers must be at least 1, got {args.workers}", file=sys.stderr)
        return 1
    try:
        budgets = [None if b.strip().lower() == "none" else int(b) for b in args.max_postings.split(",") if b.strip()]
    except ValueError:
        budgets = [0]
    if any(b is not None and b < 1 for b in budgets):
        print(f"Error: --max-postings takes comma-separated positive integers or 'none', got {args.max_postings!r}", file=sys.stderr)
        return 1
    load0 = os.getloadavg()
    if args.query_only:
        listing = args.cache / f"frames_{sizes[-1]}.txt"
        if not listing.with_suffix(".topomap").exists():
            print(f"Error: no map of {sizes[-1]} frames in {args.cache}; run without --query-only first", file=sys.stderr)
            return 1
        print_query(query_at_scale(listing, args.query_nodes, budgets=budgets), load0, os.getloadavg())
        return 0
    log(f"rendering / reading {sizes[-1]} frames in {args.cache} ...")
    t0 = time.perf_counter()
    listings = {n: render_frames(args.cache, n) for n in sizes}
    log(f"frames ready ({time.perf_counter() - t0:.0f} s)")
    if args.render_only:
        return 0
    rows = []
    for n in sizes:
        log(f"building {n} frames ...")
        r = run_build(listings[n], args.workers)
        rows.append(r)
        log(f"  {r['build_s']:.0f} s, {r['nodes']} nodes, peak RSS {r['rss_mb']:.0f} MB")
    q = query_at_scale(listings[sizes[-1]], args.query_nodes, budgets=budgets) if args.query_nodes else None
    load1 = os.getloadavg()

    base = rows[0]
    print(f"\nBuild at scale: simulator teach runs, world seed {WORLD_SEED} ({LATTICE[0]}x{LATTICE[1]} junctions, {ROOMS} rooms), "
          f"320x240, {base['executor']}; load average {load0[0]:.1f} before, {load1[0]:.1f} after")
    head = (f"{'frames':>7}{'nodes':>7}{'loops':>7}{'wall s':>8}{'frames/s':>9}{'x 1st':>7}{'RSS MB':>8}{'workers MB':>11}"
            f"{'KB/node':>9}{'loop ms/node start':>20}{'end':>7}{'mean x 1st':>11}{'loop CPU ms start':>19}{'end':>7}{'mean':>7}{'x 1st':>7}")
    print(head)
    print("-" * len(head))
    for r in rows:
        fps = r["frames"] / r["build_s"]
        print(f"{r['frames']:>7}{r['nodes']:>7}{r['loops']:>7}{r['build_s']:>8.0f}{fps:>9.1f}"
              f"{fps / (base['frames'] / base['build_s']):>7.2f}{r['rss_mb']:>8.0f}{r.get('workers_rss_mb', r['worker_rss_mb']):>11.0f}"
              f"{r['bytes'] / r['nodes'] / 1024:>9.1f}{r['loop_ms_start']:>20.1f}{r['loop_ms_end']:>7.1f}"
              f"{r['loop_ms_mean'] / max(base['loop_ms_mean'], 1e-9):>11.2f}"
              f"{r.get('loop_cpu_ms_start', 0):>19.1f}{r.get('loop_cpu_ms_end', 0):>7.1f}{r.get('loop_cpu_ms_mean', 0):>7.1f}"
              f"{r.get('loop_cpu_ms_mean', 0) / max(base.get('loop_cpu_ms_mean', 0), 1e-9):>7.2f}")
    print("  RSS: peak of the build process; workers MB: the peaks of its worker processes, summed; x 1st: over the "
          "smallest build; loop ms/node: loop-closure stage wall time per new node, mean over its first / last 10 % of "
          "nodes (follows the machine's load); loop CPU ms: the same in CPU time of the build process and its workers")
    last = rows[-1]
    total = last["rss_mb"] + last.get("workers_rss_mb", last["worker_rss_mb"])
    cpu_ratio = last.get("loop_cpu_ms_mean", 0) / max(base.get("loop_cpu_ms_mean", 0), 1e-9)
    print(f"  goals: peak RSS <= 2048 MB at {last['frames']} frames: {'met' if total <= 2048 else 'MISSED'}"
          f" ({total:.0f} MB, the build process and every worker); loop CPU ms per node at "
          f"{last['frames']} within 1.5x of {base['frames']}: {cpu_ratio:.2f}x ({'met' if cpu_ratio <= 1.5 else 'MISSED'}; "
          f"wall time {last['loop_ms_mean'] / max(base['loop_ms_mean'], 1e-9):.2f}x)")
    if q:
        print_query(q, load0, load1)
    return 0


def print_query(q: dict, load0, load1) -> None:
    """The 1M-node query table."""
    if q:
        print(f"\nQuery at {q['nodes']} synthetic nodes ({q['words']} words, {q['postings_per_node']:.0f} postings per node, "
              f"{q['stop_words']} stop words): median {q['median_ms']:.1f} ms, p90 {q['p90_ms']:.1f} ms "
              f"(bag-of-words shortlist {q['bow_median_ms']:.1f} ms + verification of the top 10 {q['verify_median_ms']:.1f} ms); "
              f"goal median < 30 ms: {'met' if q['median_ms'] < 30 else 'MISSED'}")
        print(f"  postings read per query (LocalizeConfig.bow_max_postings = {q['max_postings']}): median {q['read_median']:.0f} "
              f"of the {q['all_median']:.0f} its non-stop words hold; reading them all (exact shortlist): "
              f"{q['exact_bow_median_ms']:.1f} ms median, p90 {q['exact_bow_p90_ms']:.1f} ms; top 10 shared with the "
              f"exact shortlist: {q['overlap']:.2f} (synthetic look-alikes: a measure of difference, not of quality)")
        for o in q["others"]:
            print(f"  with bow_max_postings = {o['max_postings']}: median {o['median_ms']:.1f} ms, p90 {o['p90_ms']:.1f} ms "
                  f"(shortlist {o['bow_median_ms']:.1f} + verification {o['verify_median_ms']:.1f}), {o['read_median']:.0f} "
                  f"postings read, exact shortlist {o['exact_bow_median_ms']:.1f} ms, top 10 shared {o['overlap']:.2f}")
        print(f"  index bytes per node: {q['ram_bytes_per_node']:.0f} in RAM (postings, weights; the per-feature words "
              f"of a real map are not held here), {q['stored_bytes_per_node']:.0f} in the map file (postings + each feature's word)")
        print(f"  synthetic index built in {q['build_s']:.0f} s; load average {load0[0]:.1f} before, {load1[0]:.1f} after")


if __name__ == "__main__":
    sys.exit(main())
