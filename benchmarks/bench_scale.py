"""Benchmark: localization latency and memory per node at 1k, 10k and 100k nodes, against exhaustive
matching at the same size (issue 3, "scale benchmark").

The maps are synthetic but made of real data:

* **Vocabulary**: trained like ``topomap build`` trains it for a map of that size — every size here
  asks for the cap of 65536 words, learnt from (at most) 200 000 descriptors — on the real ORB
  descriptors of the corridor (``ref/`` and ``query/`` at topomap's 480 px working size).
* **Word lists**: the 57 corridor keyframes (a real ``build_map`` of ``ref/``) keep their own words
  and features as nodes 0..56; every other node is a *distractor* whose words are drawn from the
  empirical word distribution of those real descriptors (as many as a real keyframe has), and whose
  verification features are a real keyframe's descriptors with shuffled keypoints, so matching costs
  what it costs on real data and RANSAC fails the way it fails on a wrong place.
* **Queries**: the 111 corridor query frames. ``Localizer(descriptor="bow")`` answers them:
  bag-of-words scores over the inverted file -> robust z-scores -> top-k (``shortlist_k`` = 10)
  -> geometric verification of those k nodes (guided: descriptors matched only under the same
  vocabulary-tree node, PROSAC) -> answer. Feature extraction (``prepare``) is timed apart. The row
  "brute" verifies as before guided matching (brute-force Hamming matching, MAGSAC): the baseline
  of that change in the same run. Recall@1 on the real nodes shows how far the distractors push
  the right node out (bag-of-words alone is weak on the corridor: it falls with map size).

Exhaustive matching = ``matching.verify`` of the query against every node: measured in full at 1k
nodes (a few queries), extrapolated linearly from the measured per-pair cost at 10k and 100k.
Memory per node: ``BowIndex.memory_bytes() / N`` (the index) plus, for verification, the node's
features (keypoints + descriptors) if kept in RAM; exhaustive keeps all features in RAM.

Run: ``python benchmarks/bench_scale.py [--sizes 1000,10000,100000] [--queries 111]`` (about 4 min
and 3 GB of RAM at 100k nodes on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from topomap.build import build_map
from topomap.config import LocalizeConfig
from topomap.evaluate import evaluate
from topomap.features import Features, extract
from topomap.graph import Edge, EdgeKind, Node, TopoMap
from topomap.groundtruth import read_correspondences
from topomap.images import open_sequence, to_working_resolution
from topomap.localize import Localizer, _robust_z, _top_rows
from topomap.matching import verify
from topomap.retrieval import BowIndex, Vocabulary, sad

SHARED = Path(os.environ.get("TOPOMAP_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
CORRIDOR = SHARED / "datasets" / "corridor"
WORDS = 65536  # BuildConfig.vocabulary_words: the cap every size here reaches (>= 8 descriptors per word)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def real_data():
    """The corridor map (57 real keyframes), its ground truth, the query frames, the descriptors of
    every reference frame (distractor material) and all real descriptors (vocabulary material)."""
    t0 = time.perf_counter()
    base = build_map(CORRIDOR / "ref")
    truth = read_correspondences(CORRIDOR / "ground_truth.csv", base)
    cfg = base.config.features
    qseq = list(open_sequence(CORRIDOR / "query"))
    ref_desc = [extract(to_working_resolution(f.image, base.working_size), cfg).descriptors
                for f in open_sequence(CORRIDOR / "ref")]
    query_desc = [extract(to_working_resolution(f.image, base.working_size), cfg).descriptors for f in qseq]
    all_desc = np.concatenate(ref_desc + query_desc)
    log(f"real data: {len(base.nodes)} keyframes, {len(all_desc)} descriptors ({time.perf_counter() - t0:.0f} s)")
    return base, truth, qseq, ref_desc, all_desc


def frequency_bands(counts: np.ndarray, band: int) -> tuple[np.ndarray, np.ndarray]:
    """Words ordered by frequency (most frequent first) and each word's rank."""
    by_rank = np.argsort(-counts, kind="stable")
    rank = np.empty_like(by_rank)
    rank[by_rank] = np.arange(len(by_rank))
    return by_rank, rank


def synthetic_map(base: TopoMap, voc: Vocabulary, ref_words: list[np.ndarray], counts: np.ndarray, n: int,
                  seed: int = 0, band: int = 64):
    """``n`` nodes: the real keyframes (ids 0..K-1) then distractors. Returns (map, features_of, seconds
    to build the index).

    A distractor is "another place with the same statistics": the words of a real reference frame,
    each replaced by another word of about the same frequency (a per-distractor cyclic shift of the
    frequency rank within bands of ``band`` ranks: never the word itself), 10 % of them dropped.
    Frequent words stay frequent, so posting-list lengths and stop words behave as on real data,
    but a distractor shares words with a query only by chance."""
    rng = np.random.default_rng(seed)
    real = [base.nodes[i] for i in sorted(base.nodes)]
    k = len(real)
    shuffled = []  # distractor features: real descriptors, keypoints shuffled (no consistent geometry)
    for r in real:
        perm = rng.permutation(len(r.features))
        shuffled.append(Features(r.features.keypoints[perm], r.features.descriptors, r.features.kind, r.features.image_size))
    by_rank, rank = frequency_bands(counts, band)
    v = len(rank)
    word_lists = [voc.quantize(r.features.descriptors) for r in real]
    for i in range(k, n):
        src = ref_words[int(rng.integers(len(ref_words)))]
        src = src[rng.random(len(src)) >= 0.1]
        r = rank[src]
        shifted = (r // band) * band + (r % band + int(rng.integers(1, band))) % band
        word_lists.append(by_rank[np.minimum(shifted, v - 1)])
    # each feature's word (guided matching): a distractor's descriptors are its source keyframe's
    feature_words = word_lists[:k] + [word_lists[i % k] for i in range(k, n)]
    t0 = time.perf_counter()
    index = BowIndex.from_word_lists(voc, np.arange(n), word_lists, feature_words)
    build_s = time.perf_counter() - t0
    thumb = np.zeros((4, 4), np.uint8)
    tmap = TopoMap(camera=base.camera, config=base.config, meta=dict(base.meta))
    for i in range(n):
        f = real[i].features if i < k else shuffled[i % k]
        tmap.nodes[i] = Node(i, 0, i, real[i].source if i < k else f"synthetic{i}.png", f, thumb)
    for i in range(n - 1):  # a chain of sequential edges, as a build makes
        tmap.edges[(i, i + 1)] = Edge(i, i + 1, EdgeKind.SEQUENTIAL, 100, 0.1)
    tmap.frames = list(base.frames)
    tmap.index = index

    def features_of(node: int) -> Features:
        return tmap.nodes[node].features

    return tmap, features_of, build_s


def features_bytes(f: Features) -> int:
    return int(f.keypoints.nbytes + f.descriptors.nbytes)


def time_queries(loc: Localizer, prepared: list) -> dict[str, np.ndarray]:
    """Per query: ms in BoW appearance, verification of the top k, the rest (softmax, answer), total."""
    out = {"appearance": [], "verify": [], "answer": [], "total": []}
    results = []
    for q in prepared:
        t0 = time.perf_counter()
        score = loc.appearance(q)
        t1 = time.perf_counter()
        checks = loc.verify_candidates(q, score)
        t2 = time.perf_counter()
        chance = loc.map.config.match.min_inliers
        for r, v in checks.items():
            score[r] += loc.config.inlier_weight * max(0, v.inliers - chance)
        p = loc.likelihood(score)
        p /= p.sum()
        res = loc.answer(p, score, checks, score)
        t3 = time.perf_counter()
        results.append(res)
        for k, v in (("appearance", t1 - t0), ("verify", t2 - t1), ("answer", t3 - t2), ("total", t3 - t0)):
            out[k].append(v * 1e3)
    return {k: np.array(v) for k, v in out.items()}, results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1000,10000,100000")
    ap.add_argument("--queries", type=int, default=111, help="corridor query frames used per size")
    ap.add_argument("--top-k", default="10,3", help="shortlist sizes to time (10 = LocalizeConfig default)")
    ap.add_argument("--no-brute-force", action="store_true", help="skip the brute-force-verification rows")
    ap.add_argument("--exhaustive-queries", type=int, default=3, help="queries matched exhaustively at the smallest size")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    # (label, config): guided verification (the default) at each k, and the previous verification
    # (brute-force matching, MAGSAC with 2000 hypotheses) at the first k for comparison
    ks = [int(k) for k in args.top_k.split(",")]
    variants = [(f"top-{k}", LocalizeConfig(descriptor="bow", shortlist_k=k)) for k in ks]
    if not args.no_brute_force:
        variants.append((f"top-{ks[0]} brute", LocalizeConfig(descriptor="bow", shortlist_k=ks[0], guided_matching=False,
                                                             verify_ransac_method="magsac", verify_max_iters=2000)))
    if not CORRIDOR.exists():
        sys.exit(f"corridor dataset not found under {CORRIDOR}; set TOPOMAP_SHARED")
    load_before = os.getloadavg()[0]

    base, truth, qseq, ref_desc, all_desc = real_data()
    t0 = time.perf_counter()
    voc = Vocabulary.train(all_desc, "orb", WORDS, seed=0)
    log(f"vocabulary: {voc.size} words, depth {voc.depth} ({time.perf_counter() - t0:.0f} s)")
    counts = np.bincount(voc.quantize(all_desc), minlength=voc.size)
    ref_words = [voc.quantize(d) for d in ref_desc]

    qseq = qseq[: args.queries]
    probe = Localizer(base, LocalizeConfig(descriptor="bow"))
    t0 = time.perf_counter()
    prepared = [probe.prepare(f.image) for f in qseq]
    extract_ms = (time.perf_counter() - t0) / len(qseq) * 1e3
    names = [f.name for f in qseq]
    feat_node_bytes = float(np.mean([features_bytes(n.features) for n in base.nodes.values()]))

    rows = []  # (n, k, times, recall, exhaustive ms, how, index bytes/node, stop words)
    pair_ms = None
    for n in sizes:
        t0 = time.perf_counter()
        tmap, features_of, index_s = synthetic_map(base, voc, ref_words, counts, n)
        log(f"{n} nodes: map ready ({time.perf_counter() - t0:.0f} s, index from word lists {index_s:.1f} s)")
        if pair_ms is None:  # exhaustive, measured in full at the first size
            t0 = time.perf_counter()
            nq = min(args.exhaustive_queries, len(prepared))
            for q in prepared[:nq]:
                for node in range(n):
                    verify(q.features, features_of(node), tmap.config.match)
            pair_ms = (time.perf_counter() - t0) / (nq * n) * 1e3
            how = f"measured in full ({nq} queries x {n} nodes)"
        else:
            how = "extrapolated from the per-pair cost"
        for k, cfg in variants:
            loc = Localizer(tmap, cfg, features_of=features_of)
            loc.localize_query(prepared[0])  # warm-up
            times, results = time_queries(loc, prepared)
            recall = evaluate(list(zip(names, results)), truth, tmap).recall_at[1]
            rows.append((n, k, times, recall, pair_ms * n, how, tmap.index.memory_bytes() / n,
                         int(tmap.index.stop_words.sum())))
            log(f"{n} nodes, {k}: median {np.median(times['total']):.1f} ms, Recall@1 {recall:.3f}")
        del tmap, loc, features_of

    # fused mode (the default on keypoint maps) adds thumbnail distances to the bag of words' best
    # LocalizeConfig.thumbnail_candidates nodes (all of them on smaller maps): their cost at each size
    rng = np.random.default_rng(0)
    q_desc = rng.standard_normal(768).astype(np.float32)
    m_thumb = LocalizeConfig().thumbnail_candidates
    fused_ms, fused_all_ms = {}, {}
    for n in sizes:
        descs = rng.standard_normal((n, 768)).astype(np.float32)
        bow = rng.standard_normal(n)
        t0 = time.perf_counter()
        for _ in range(5):
            best = _top_rows(bow, m_thumb) if n > m_thumb else slice(None)
            _robust_z(-sad(q_desc, descs[best]).astype(np.float64))
        fused_ms[n] = (time.perf_counter() - t0) / 5 * 1e3
        t0 = time.perf_counter()
        for _ in range(5):
            _robust_z(-sad(q_desc, descs).astype(np.float64))
        fused_all_ms[n] = (time.perf_counter() - t0) / 5 * 1e3
        del descs

    print(f"\nquery latency (BoW shortlist + verification of the top k + answer) and memory per node, "
          f"{len(prepared)} corridor queries per row")
    print(f"feature extraction (prepare) {extract_ms:.1f} ms per query, not included; vocabulary {voc.size} words "
          f"(depth {voc.depth}); real keyframe features {feat_node_bytes / 1024:.1f} KiB per node; exhaustive "
          f"per-pair verification {pair_ms:.2f} ms; load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after (2 cores)")
    head = (f"{'nodes':>8}{'verify':>15}{'median ms':>10}{'p90 ms':>8}{'BoW ms':>8}{'verify':>8}{'answer':>8}{'exh. ms':>10}"
            f"{'exh./tm':>9}{'R@1':>6}{'stop w.':>8}{'index B/node':>13}{'+feats B/node':>14}{'exh. B/node':>12}{'mem ratio':>10}")
    print(head)
    print("-" * len(head))
    for n, k, t, recall, exh, how, index_b, stop in rows:
        med = float(np.median(t["total"]))
        with_feats = index_b + feat_node_bytes
        print(f"{n:>8}{k:>15}{med:10.1f}{np.percentile(t['total'], 90):8.1f}{np.median(t['appearance']):8.1f}"
              f"{np.median(t['verify']):8.1f}{np.median(t['answer']):8.1f}{exh:10.0f}{exh / med:9.0f}{recall:6.2f}{stop:8d}"
              f"{index_b:13.0f}{with_feats:14.0f}{feat_node_bytes:12.0f}{with_feats / feat_node_bytes:10.2f}")
    print("  exh. ms: verification against every node, " + "; ".join(dict.fromkeys(f"{r[0]}: {r[5]}" for r in rows)))
    print("  R@1: corridor queries whose answer is a right real node among the distractors (node level)")
    print("  mem ratio: (index + features kept in RAM for verification) / exhaustive (features of every node); with "
          "features read from the map file on demand (Localizer(features_of=...)) the index alone is "
          + ", ".join(dict.fromkeys(f"{r[6] / feat_node_bytes:.3f}" for r in rows)) + " of exhaustive")
    for k, _ in variants:
        mine = [r for r in rows if r[1] == k]
        first, last = mine[0], mine[-1]
        growth = np.median(last[2]["total"]) / np.median(first[2]["total"])
        bow = np.median(last[2]["appearance"]) / np.median(first[2]["appearance"])
        goal = "met" if np.median(last[2]["total"]) < 30 else "MISSED"
        print(f"  {k}: {last[0] // first[0]}x the nodes -> {growth:.2f}x the median latency (BoW part {bow:.1f}x); "
              f"goal median < 30 ms at {last[0]} nodes: {goal}")
    print(f"  fused mode (--descriptor fused/auto) adds thumbnail distances to the bag of words' best {m_thumb} nodes: "
          + ", ".join(f"{n}: {ms:.1f} ms" for n, ms in fused_ms.items())
          + " (to every node: " + ", ".join(f"{n}: {ms:.1f} ms" for n, ms in fused_all_ms.items()) + ")")


if __name__ == "__main__":
    main()
