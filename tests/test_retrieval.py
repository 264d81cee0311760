"""topomap.retrieval: vocabulary tree (binary and float), TF-IDF inverted file against a brute-force
cosine, stop words, the per-query postings budget against exact scoring, top-k ties, add(), array
round trips and damaged arrays, the whole-image descriptor."""

from __future__ import annotations

import numpy as np
import pytest
from map_synth import scene, window

from topomap.config import FeatureConfig, LocalizeConfig
from topomap.errors import ConfigError, MapFormatError
from topomap.features import Features, extract
from topomap.retrieval import BowIndex, Vocabulary, sad, thumbnail_descriptor, vocabulary_size


# ----------------------------------------------------------------------------- data
@pytest.fixture(scope="module")
def orb_feats() -> dict[int, Features]:
    """ORB features of 8 views sliding over a synthetic scene (node id -> features)."""
    tex = scene(4)
    cfg = FeatureConfig(max_features=300)
    return {10 + i: extract(window(tex, 150.0 * i, y=40.0), cfg) for i in range(8)}


@pytest.fixture(scope="module")
def sift_feats() -> list[Features]:
    tex = scene(5)
    cfg = FeatureConfig(kind="sift", max_features=200)
    return [extract(window(tex, 200.0 * i, y=40.0), cfg) for i in range(3)]


@pytest.fixture(scope="module")
def orb_vocab(orb_feats) -> Vocabulary:
    desc = np.concatenate([f.descriptors for f in orb_feats.values()])
    return Vocabulary.train(desc, "orb", 200, seed=3)


def greedy_words(voc: Vocabulary, desc: np.ndarray) -> np.ndarray:
    """Oracle for Vocabulary.quantize: walk the tree one descriptor at a time, nearest child first
    (Hamming on unpacked bits for binary kinds, L2 for float ones)."""

    def dist(x, centres):
        if voc.binary:
            return (np.unpackbits(centres, axis=1) != np.unpackbits(x[None, :], axis=1)).sum(axis=1)
        return ((centres.astype(np.float64) - x.astype(np.float64)) ** 2).sum(axis=1)

    out = []
    for x in desc:
        cur = int(np.argmin(dist(x, voc.centres[0])))
        for level in range(1, voc.depth):
            kids = voc.children[level - 1][cur]
            cur = int(kids[np.argmin(dist(x, voc.centres[level][kids]))])
        out.append(cur)
    return np.array(out, np.int64)


def tfidf_cosine(index: BowIndex, words_of: dict[int, np.ndarray], query_words: np.ndarray) -> np.ndarray:
    """Oracle for BowIndex.scores: dense TF-IDF vectors and their cosine, idf = log((N+1)/(df+1)),
    the query's stop words dropped after normalisation (as in the index)."""
    docs, q = tfidf_cosine_terms(index, words_of, query_words)
    return docs @ q


def tfidf_cosine_rows(index: BowIndex, words_of: dict[int, np.ndarray], query_words: np.ndarray,
                      keep: np.ndarray | None = None) -> np.ndarray:
    """:func:`tfidf_cosine` in the index's row order (``words_of`` in any id order), the query
    reduced to the words ``keep`` (after normalisation) when given."""
    ordered = {r: words_of[int(i)] for r, i in enumerate(index.node_ids)}
    q = np.asarray(query_words)
    if keep is None:
        return tfidf_cosine(index, ordered, q)
    docs, weights = tfidf_cosine_terms(index, ordered, q)
    weights[~np.isin(np.arange(len(weights)), keep)] = 0.0
    return docs @ weights


def tfidf_cosine_terms(index: BowIndex, words_of: dict[int, np.ndarray], query_words: np.ndarray):
    """The dense unit TF-IDF node vectors (rows) and the query's unit weights, stop words zeroed."""
    ids = sorted(words_of)
    n, v = len(ids), index.vocabulary.size
    tf = np.zeros((n, v))
    for r, i in enumerate(ids):
        np.add.at(tf[r], words_of[i], 1.0)
    idf = np.log((n + 1.0) / ((tf > 0).sum(axis=0) + 1.0))
    docs = tf * idf
    docs /= np.maximum(np.linalg.norm(docs, axis=1, keepdims=True), 1e-300)
    q = np.bincount(query_words, minlength=v) * idf
    q /= max(np.linalg.norm(q), 1e-300)
    q[index.stop_words] = 0.0
    return docs, q


# ----------------------------------------------------------------------------- vocabulary
def test_vocabulary_size_follows_the_data():
    assert vocabulary_size(80_000, 65536) == 10_000  # 8 descriptors per word
    assert vocabulary_size(10_000_000, 65536) == 65536  # capped
    assert vocabulary_size(10, 65536) == 16  # floor


def test_binary_vocabulary_is_deterministic_for_a_seed(orb_feats, orb_vocab):
    desc = np.concatenate([f.descriptors for f in orb_feats.values()])
    again = Vocabulary.train(desc, "orb", 200, seed=3)
    a, b = orb_vocab.to_arrays(), again.to_arrays()
    assert a.keys() == b.keys() and all(a[k].tobytes() == b[k].tobytes() for k in a)
    np.testing.assert_array_equal(orb_vocab.quantize(desc), again.quantize(desc))
    other = Vocabulary.train(desc, "orb", 200, seed=4)
    assert any(x.tobytes() != y.tobytes() for x, y in zip(orb_vocab.centres, other.centres))
    # shape contract: binary centres are packed bits, 2 levels for 65..4096 words, ~200 leaves
    assert orb_vocab.binary and orb_vocab.depth == 2 and 100 <= orb_vocab.size <= 225
    assert all(c.dtype == np.uint8 and c.shape[1] == 32 for c in orb_vocab.centres)
    w = orb_vocab.quantize(desc)
    assert w.dtype == np.int64 and w.min() >= 0 and w.max() < orb_vocab.size
    assert len(np.unique(w)) > 0.5 * orb_vocab.size  # words are used, not collapsed onto a few


class _Counted:
    """An array-like chunk that counts how often it is read (as build_index's lazy descriptors)."""

    def __init__(self, a):
        self.a, self.reads = a, 0

    def __len__(self):
        return len(self.a)

    def __array__(self, dtype=None, copy=None):
        self.reads += 1
        return self.a


@pytest.mark.parametrize("max_samples", [500, 10**6])
def test_a_vocabulary_trained_from_chunks_is_the_one_of_their_concatenation(orb_feats, max_samples):
    chunks = [f.descriptors for f in orb_feats.values()]
    whole = Vocabulary.train(np.concatenate(chunks), "orb", 100, seed=5, max_samples=max_samples)
    lazy = [_Counted(c) for c in chunks]
    parts = Vocabulary.train(lazy, "orb", 100, seed=5, max_samples=max_samples)
    a, b = whole.to_arrays(), parts.to_arrays()
    assert a.keys() == b.keys() and all(a[k].tobytes() == b[k].tobytes() for k in a)
    assert all(c.reads <= 1 for c in lazy)  # each chunk read once at most, lengths need no read


def test_binary_quantize_is_the_greedy_tree_walk(orb_feats, orb_vocab):
    desc = orb_feats[12].descriptors[:120]
    np.testing.assert_array_equal(orb_vocab.quantize(desc), greedy_words(orb_vocab, desc))
    flat = Vocabulary.train(np.concatenate([f.descriptors for f in orb_feats.values()]), "orb", 48, seed=0)
    assert flat.depth == 1  # one level: quantize is the exact nearest centre
    np.testing.assert_array_equal(flat.quantize(desc), greedy_words(flat, desc))
    assert orb_vocab.quantize(desc[:0]).shape == (0,)


def test_akaze_descriptors_of_61_bytes():
    rng = np.random.default_rng(2)
    desc = rng.integers(0, 256, (600, 61), dtype=np.uint8)
    voc = Vocabulary.train(desc, "akaze", 100, seed=0)
    assert voc.binary and voc.centres[0].shape[1] == 61
    np.testing.assert_array_equal(voc.quantize(desc[:100]), greedy_words(voc, desc[:100]))


def test_float_sift_vocabulary(sift_feats):
    desc = np.concatenate([f.descriptors for f in sift_feats])
    voc = Vocabulary.train(desc, "sift", 100, seed=1)
    assert not voc.binary and voc.kind == "sift" and voc.depth == 2
    assert all(c.dtype == np.float32 and c.shape[1] == 128 for c in voc.centres)
    again = Vocabulary.train(desc, "sift", 100, seed=1)
    assert all(x.tobytes() == y.tobytes() for x, y in zip(voc.centres, again.centres))
    np.testing.assert_array_equal(voc.quantize(desc[:150]), greedy_words(voc, desc[:150]))
    # the index works the same on float descriptors: a view is its own best match
    feats = {i: f for i, f in enumerate(sift_feats)}
    index = BowIndex.build(voc, feats)
    for i, f in feats.items():
        assert index.shortlist(f, 1)[0][0] == i
    back = BowIndex.from_arrays(index.to_arrays(), "sift")
    np.testing.assert_array_equal(back.scores(sift_feats[1]), index.scores(sift_feats[1]))


def test_train_rejects_too_few_descriptors():
    with pytest.raises(ValueError, match="at least two"):
        Vocabulary.train(np.zeros((1, 32), np.uint8), "orb", 16)


# ----------------------------------------------------------------------------- inverted file
def test_scores_equal_brute_force_tfidf_cosine(orb_feats, orb_vocab):
    index = BowIndex.build(orb_vocab, orb_feats)
    words_of = {i: orb_vocab.quantize(f.descriptors) for i, f in orb_feats.items()}
    assert not index.stop_words.any()  # a small map has no stop words
    tex = scene(4)
    query = extract(window(tex, 160.0, y=45.0), FeatureConfig(max_features=300))  # near node 11
    got = index.scores(query)
    want = tfidf_cosine(index, words_of, orb_vocab.quantize(query.descriptors))
    assert got.dtype == np.float32 and got.shape == (8,)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert index.shortlist(query, 1)[0][0] == 11
    # a node queried with its own features scores 1 (unit vectors) and beats the others
    own = index.scores(orb_feats[14])
    assert own[index.row_of(14)] == pytest.approx(1.0, abs=1e-5) and int(np.argmax(own)) == index.row_of(14)
    assert index.scores(Features.empty("orb", (480, 360))).tolist() == [0.0] * 8


def test_top_k_ties_exclusion_and_bounds(orb_feats, orb_vocab):
    index = BowIndex.build(orb_vocab, orb_feats)
    scores = np.array([0.5, 0.9, 0.5, 0.1, 0.9, 0.0, 0.5, 0.2], np.float32)  # rows of ids 10..17
    assert index.top_k(scores, 4) == [(11, pytest.approx(0.9)), (14, pytest.approx(0.9)), (10, 0.5), (12, 0.5)]
    assert [n for n, _ in index.top_k(scores, 3, exclude={11, 10, 99})] == [14, 12, 16]
    assert len(index.top_k(scores, 50)) == 8 and index.top_k(scores, 0) == []


def test_stop_words_only_on_big_maps():
    """Words held by > 5 % of the nodes are skipped by queries once the map has >= 2000 nodes."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (64, 32), dtype=np.uint8)
    voc = Vocabulary.train(np.repeat(base, 4, axis=0), "orb", 64, seed=0)
    assert voc.depth == 1 and voc.size == 64
    common = 0  # in every 10th node (10 % of the map); any other word in ~3 % (2 of 63 per node)

    def node_words(i: int) -> np.ndarray:
        w = rng.choice(np.arange(1, 64), 2, replace=False)
        return np.r_[w, common] if i % 10 == 0 else w

    def index_of(n: int) -> tuple[BowIndex, dict[int, np.ndarray]]:
        words = {i: node_words(i) for i in range(n)}
        # descriptors equal to the leaf centres quantise to those leaves (one level: exact nearest)
        feats = {i: Features(np.zeros((len(w), 2), np.float32), voc.centres[-1][w], "orb", (10, 10)) for i, w in words.items()}
        index = BowIndex.build(voc, feats)
        assert all(np.array_equal(voc.quantize(f.descriptors), words[i]) for i, f in list(feats.items())[:20])
        return index, words

    query = Features(np.zeros((2, 2), np.float32), voc.centres[-1][[common, 5]], "orb", (10, 10))
    small, small_words = index_of(BowIndex.STOP_MIN_NODES - 1)
    big, big_words = index_of(BowIndex.STOP_MIN_NODES)
    assert not small.stop_words.any()
    assert big.stop_words[common] and big.stop_words.sum() == 1
    s_small, s_big = small.scores(query), big.scores(query)
    np.testing.assert_allclose(s_small, tfidf_cosine(small, small_words, np.array([common, 5])), atol=1e-5)
    np.testing.assert_allclose(s_big, tfidf_cosine(big, big_words, np.array([common, 5])), atol=1e-5)
    def only_common(words: dict[int, np.ndarray]) -> np.ndarray:
        return np.array([common in words[i] and 5 not in words[i] for i in range(len(words))])

    assert only_common(small_words).any() and (s_small[only_common(small_words)] > 0).all()  # counts on a small map ...
    assert (s_big[only_common(big_words)] == 0).all()  # ... and is ignored on a big one
    holds_5 = np.array([5 in big_words[i] for i in range(len(big))])
    assert (s_big[holds_5] > 0).all()


def random_index(n: int, v: int = 2000, per_node: int = 60, seed: int = 0) -> tuple[BowIndex, dict[int, np.ndarray]]:
    """An index of ``n`` nodes over a flat ``v``-word vocabulary, words drawn from a skewed (Zipf-like)
    distribution as real ones are, so posting-list lengths spread over two orders of magnitude."""
    rng = np.random.default_rng(seed)
    voc = Vocabulary((np.zeros((v, 32), np.uint8),), (), "orb")
    p = 1.0 / np.arange(1, v + 1) ** 0.8
    words = {i: rng.choice(v, per_node, p=p / p.sum()) for i in range(n)}
    ids = rng.permutation(np.arange(100, 100 + 3 * n, 3))  # node ids not in row order
    words = {int(ids[r]): w for r, w in enumerate(words.values())}
    return BowIndex.from_word_lists(voc, list(words), list(words.values())), words


def query_of(words: np.ndarray) -> Features:
    """A query whose features' words are given (passed as ``words=``): only its length matters."""
    return Features(np.zeros((len(words), 2), np.float32), np.zeros((len(words), 32), np.uint8), "orb", (10, 10))


def test_max_postings_reads_the_rarest_words():
    """A bounded query reads its rarest words while their lists hold at most max_postings, and
    scores them as the exact cosine restricted to those words would."""
    index, words_of = random_index(600)
    rng = np.random.default_rng(1)
    qw = np.r_[words_of[index.node_ids[7]], rng.integers(0, 2000, 40)]
    f = query_of(qw)
    all_w, all_q = index.query_terms(f, qw)
    lengths = np.diff(index.indptr)
    total = int(lengths[all_w].sum())
    for budget in (None, total, 10 * total):  # no cut
        assert np.array_equal(index.query_terms(f, qw, budget)[0], all_w)
        np.testing.assert_array_equal(index.scores(f, qw, budget), index.scores(f, qw))
    np.testing.assert_allclose(index.scores(f, qw), tfidf_cosine_rows(index, words_of, qw), atol=1e-5)
    assert (lengths[index.query_terms(f, qw, 1)[0]] > 0).sum() == 1  # a list is read, however small the budget
    for budget in (total - 1, total // 2, total // 10, 1):
        kept, q = index.query_terms(f, qw, budget)
        assert np.all(np.diff(kept) > 0) and np.isin(kept, all_w).all()
        np.testing.assert_array_equal(q, all_q[np.isin(all_w, kept)])  # weights of the whole query
        dropped = np.setdiff1d(all_w, kept)
        assert len(kept) >= 1 and len(dropped) >= 1 and lengths[kept].max() <= lengths[dropped].min()  # the rarest
        assert lengths[kept].sum() <= budget or (lengths[kept] > 0).sum() == 1  # or the rarest list alone
        assert lengths[kept].sum() + lengths[dropped].min() > budget  # the next rarest would not fit
        want = tfidf_cosine_rows(index, words_of, qw, keep=kept)
        np.testing.assert_allclose(index.scores(f, qw, budget), want, atol=1e-5)
        assert index.shortlist(f, 5, words=qw, max_postings=budget) == index.top_k(index.scores(f, qw, budget), 5)


def test_bounded_top_k_agrees_with_exact_where_the_bound_says_it_must():
    """The words a bounded query leaves out add at most R = sum of (query weight x the largest
    weight in their posting list) to any node's score; a node ahead of the (k+1)-th bounded score by
    more than R is in the exact top k."""
    index, words_of = random_index(BowIndex.STOP_MIN_NODES + 500, seed=2)
    lengths = np.diff(index.indptr)
    k = 10
    certified_total = 0
    for r in range(0, 60, 3):
        qw = words_of[int(index.node_ids[r])]  # a node's own words: it stands out
        f = query_of(qw)
        exact = index.scores(f, qw)
        all_w, all_q = index.query_terms(f, qw)
        total = int(lengths[all_w].sum())
        for share in (0.9, 0.6, 0.3):
            budget = int(share * total)
            bounded = index.scores(f, qw, budget)
            kept, _ = index.query_terms(f, qw, budget)
            gap = np.isin(all_w, kept, invert=True)
            top_w = np.array([index._weights[index.indptr[w]:index.indptr[w + 1]].max() for w in all_w[gap]] or [0.0])
            bound = float((all_q[gap] * top_w).sum())
            diff = exact - bounded
            assert diff.min() >= -1e-6 and diff.max() <= bound + 1e-6
            ranked = index.top_k(bounded, k + 1)
            certified = [n for n, s in ranked[:k] if s > ranked[k][1] + bound]
            assert set(certified) <= {n for n, _ in index.top_k(exact, k)}
            certified_total += len(certified)
    assert certified_total > 0  # the bound did certify answers, so the check above bit


@pytest.mark.parametrize("bad", [0, -5, 2.5, True, "100"])
def test_max_postings_is_validated(bad):
    index, words_of = random_index(50, seed=3)
    qw = words_of[int(index.node_ids[0])]
    with pytest.raises(ValueError, match="max_postings"):
        index.scores(query_of(qw), qw, bad)
    with pytest.raises(ValueError, match="max_postings"):
        index.scores(Features.empty("orb", (10, 10)), None, bad)
    with pytest.raises(ConfigError, match="bow_max_postings"):
        LocalizeConfig(bow_max_postings=bad)


def test_top_k_is_the_stable_full_sort():
    """top_k equals sorting every row by (score descending, node id), on big arrays with many ties
    at the cut, excluded nodes and -inf rows."""
    index, _ = random_index(3000, seed=4)
    rng = np.random.default_rng(5)
    for trial in range(20):
        scores = rng.integers(0, 6, len(index)).astype(np.float32) / 5  # heavy ties
        if trial % 3 == 0:
            scores[rng.random(len(index)) < 0.99] = -np.inf  # fewer finite rows than k at times
        exclude = set(rng.choice(index.node_ids, 50).tolist()) if trial % 2 else None
        s = scores.copy()
        if exclude:
            s[[index.row_of(n) for n in exclude]] = -np.inf
        order = np.lexsort((index.node_ids, -s))
        for k in (1, 10, 40):
            want = [(int(index.node_ids[r]), float(s[r])) for r in order[:k] if np.isfinite(s[r])]
            assert index.top_k(scores, k, exclude) == want


def test_add_equals_building_at_once(orb_feats, orb_vocab):
    ids = sorted(orb_feats)
    whole = BowIndex.build(orb_vocab, orb_feats)
    grown = BowIndex.build(orb_vocab, {i: orb_feats[i] for i in ids[:3]})
    before = grown.memory_bytes()
    grown.add({i: orb_feats[i] for i in ids[3:6]})
    grown.add({i: orb_feats[i] for i in ids[6:]})
    a, b = whole.to_arrays(), grown.to_arrays()
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    for f in orb_feats.values():
        np.testing.assert_array_equal(whole.scores(f), grown.scores(f))
    assert grown.memory_bytes() > before
    with pytest.raises(ValueError, match="already indexed"):
        grown.add({ids[0]: orb_feats[ids[0]]})


def test_index_from_word_lists_equals_build(orb_feats, orb_vocab):
    ids = sorted(orb_feats)
    words = [orb_vocab.quantize(orb_feats[i].descriptors) for i in ids]
    a = BowIndex.build(orb_vocab, orb_feats).to_arrays()
    b = BowIndex.from_word_lists(orb_vocab, ids, words, feature_words=words).to_arrays()
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="unique"):
        BowIndex.from_word_lists(orb_vocab, [1, 1], words[:2])
    with pytest.raises(ValueError, match="word ids must lie in"):
        BowIndex.from_word_lists(orb_vocab, [1], [np.array([orb_vocab.size])])


# ----------------------------------------------------------------------------- persistence
def test_arrays_round_trip(orb_feats, orb_vocab):
    index = BowIndex.build(orb_vocab, orb_feats)
    arrays = index.to_arrays()
    assert all(isinstance(a, np.ndarray) and a.dtype != object for a in arrays.values())  # no pickle
    back = BowIndex.from_arrays({k: v.copy() for k, v in arrays.items()}, "orb")
    again = back.to_arrays()
    assert arrays.keys() == again.keys()
    assert all(arrays[k].dtype == again[k].dtype and arrays[k].tobytes() == again[k].tobytes() for k in arrays)
    for f in list(orb_feats.values())[:3]:
        np.testing.assert_array_equal(back.scores(f), index.scores(f))
    assert back.memory_bytes() == index.memory_bytes()


def _damage(arrays: dict, how: str) -> dict:
    a = {k: v.copy() for k, v in arrays.items()}
    if how == "missing postings":
        del a["bow_rows"]
    elif how == "short indptr":
        a["bow_indptr"] = a["bow_indptr"][:-1]
    elif how == "counts mismatch":
        a["bow_counts"] = a["bow_counts"][:-1]
    elif how == "unknown node rows":
        a["bow_rows"][0] = len(a["bow_node_ids"]) + 5
    elif how == "negative rows":
        a["bow_rows"][0] = -1
    elif how == "no vocabulary":
        a = {k: v for k, v in a.items() if not k.startswith("vocab_")}
    elif how == "children out of range":
        a["vocab_children_1"][0, 0] = 10**6
    elif how == "children missing":
        del a["vocab_children_1"]
    elif how == "centres wrong width":
        a["vocab_centres_1"] = a["vocab_centres_1"][:, :16]
    elif how == "centres wrong dtype":
        a["vocab_centres_0"] = a["vocab_centres_0"].astype(np.float32)
    return a


@pytest.mark.parametrize("how", ["missing postings", "short indptr", "counts mismatch", "unknown node rows",
                                 "negative rows", "no vocabulary", "children out of range", "children missing",
                                 "centres wrong width", "centres wrong dtype"])
def test_damaged_arrays_raise_map_format_error(orb_feats, orb_vocab, how):
    arrays = BowIndex.build(orb_vocab, orb_feats).to_arrays()
    with pytest.raises(MapFormatError, match="topomap index") as e:
        BowIndex.from_arrays(_damage(arrays, how), "orb")
    assert "\n" not in str(e.value)


def test_index_of_another_feature_kind_is_rejected(orb_feats, orb_vocab):
    arrays = BowIndex.build(orb_vocab, orb_feats).to_arrays()
    with pytest.raises(MapFormatError, match="does not fit sift descriptors"):
        BowIndex.from_arrays(arrays, "sift")


# ----------------------------------------------------------------------------- whole-image descriptor
def test_thumbnail_descriptor_is_patch_normalised():
    img = window(scene(6), 100.0, y=30.0)
    d = thumbnail_descriptor(img, (32, 24), 8)
    assert d.shape == (32 * 24,) and d.dtype == np.float32
    blocks = d.reshape(3, 8, 4, 8).transpose(0, 2, 1, 3).reshape(12, 64)  # (patch, pixels)
    np.testing.assert_allclose(blocks.mean(axis=1), 0.0, atol=1e-4)
    np.testing.assert_allclose(blocks.std(axis=1), 1.0, atol=1e-3)
    # illumination change (gain and offset) barely moves it; another place moves it a lot
    darker = (0.6 * img.astype(np.float32) + 30.0).astype(np.uint8)
    other = thumbnail_descriptor(window(scene(6), 900.0, y=30.0), (32, 24), 8)
    near = float(sad(d, thumbnail_descriptor(darker, (32, 24), 8)[None])[0])
    far = float(sad(d, other[None])[0])
    assert near < 0.05 and far > 0.5
    # a flat patch stays at zero instead of dividing by zero
    flat = thumbnail_descriptor(np.full((120, 160), 77, np.uint8), (16, 8), 8)
    assert np.isfinite(flat).all() and not flat.any()


def test_sad_is_the_mean_absolute_difference():
    refs = np.array([[0, 0, 0, 0], [1, -1, 2, 0], [4, 4, 4, 4]], np.float32)
    got = sad(np.zeros(4, np.float32), refs)
    assert got.shape == (3,) and got.dtype == np.float32
    np.testing.assert_allclose(got, [0.0, 1.0, 4.0])
    assert sad(np.zeros(4, np.float32), np.zeros((0, 4), np.float32)).shape == (0,)
    # computed in blocks: exactly the plain expression, across block boundaries too
    rng = np.random.default_rng(0)
    many, q = rng.standard_normal((2500, 96)).astype(np.float32), rng.standard_normal(96).astype(np.float32)
    np.testing.assert_array_equal(sad(q, many), np.abs(many - q[None, :]).mean(axis=1))


# ----------------------------------------------------------------------------- feature words (guided matching)
def test_levels_and_ancestors_agree_with_the_tree_walk(orb_feats, orb_vocab):
    desc = np.concatenate([f.descriptors for f in orb_feats.values()])
    leaves = orb_vocab.quantize(desc)
    for level in range(orb_vocab.depth):
        walked = orb_vocab.quantize(desc, level=level)
        np.testing.assert_array_equal(orb_vocab.ancestors(leaves, level), walked)
        assert walked.max() < len(orb_vocab.centres[level])
    np.testing.assert_array_equal(orb_vocab.quantize(desc, level=orb_vocab.depth - 1), leaves)
    with pytest.raises(ValueError, match="level"):
        orb_vocab.quantize(desc, level=orb_vocab.depth)
    # the deepest level with at most that many nodes
    assert orb_vocab.group_level(1) == 0
    assert orb_vocab.group_level(len(orb_vocab.centres[1])) == 1
    assert orb_vocab.group_level(len(orb_vocab.centres[1]) - 1) == 0


def test_index_keeps_each_features_word(orb_feats, orb_vocab):
    ids = sorted(orb_feats)
    index = BowIndex.build(orb_vocab, {i: orb_feats[i] for i in ids[:5]})
    index.add({i: orb_feats[i] for i in ids[5:]})  # add() extends them
    for i in ids:
        np.testing.assert_array_equal(index.words_of_features(i), orb_vocab.quantize(orb_feats[i].descriptors))
    assert index.feature_words.dtype == np.uint16
    back = BowIndex.from_arrays(index.to_arrays(), "orb")
    np.testing.assert_array_equal(back.words_of_features(ids[-1]), index.words_of_features(ids[-1]))
    # an index written before feature words existed still loads, without them
    old = {k: v for k, v in index.to_arrays().items() if not k.startswith("bow_feature")}
    assert BowIndex.from_arrays(old, "orb").words_of_features(ids[0]) is None
    broken = dict(index.to_arrays(), bow_feature_indptr=index.feature_indptr[:-1])
    with pytest.raises(MapFormatError, match="topomap index"):
        BowIndex.from_arrays(broken, "orb")
