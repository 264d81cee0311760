"""Place recognition: a vocabulary tree with a TF-IDF inverted file, and whole-image descriptors.

* :class:`Vocabulary` — a hierarchical k-means tree (DBoW2-style, Nister & Stewenius 2006): depth
  ``L``, branching ``k``; quantising a descriptor costs ``k * L`` distance evaluations instead of
  ``k ** L``. Binary descriptors get binary centres (bit-wise majority of their cluster) compared
  with Hamming popcounts; SIFT gets float centres. The clustering itself is OpenCV's ``kmeans``
  (seeded). The tree walk is written here because neither OpenCV nor scikit-learn offers one.
* :class:`BowIndex` — an inverted file: for every visual word, the nodes containing it and how often.
  A query touches only the posting lists of its own words (cosine similarity of TF-IDF vectors), and
  skips *stop words* — words present in a large fraction of a big map's nodes, which carry almost no
  information and dominate the cost (Sivic & Zisserman 2003). The vocabulary grows with the map
  (:func:`vocabulary_size`), which keeps posting lists short: query time grows far slower than the map.
  Past that, a query may be given a postings budget (``max_postings``): it then reads its rarest
  words' lists first and leaves out the commonest words that would overrun it, so a query costs the
  same on a map of a million nodes as on one of a hundred thousand.
* :func:`thumbnail_descriptor` — a patch-normalised thumbnail (SeqSLAM), the whole-image descriptor
  for images too small or too blurred for keypoints.

Everything serialises to plain numpy arrays (``to_arrays`` / ``from_arrays``), never pickle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import scipy.sparse as sp

from topomap.errors import MapFormatError
from topomap.features import Features, detector, hamming

#: Whole-image descriptor: thumbnail ``(w, h)`` [px] of a 4:3 image (maps whose meta omits it) ...
THUMBNAIL_SIZE = (32, 24)
#: ... and the side of its normalisation patches [px].
THUMBNAIL_PATCH = 8
#: Seed offset between vocabulary levels (a prime, so no two clusters' k-means share a seed).
KMEANS_SEED_STRIDE = 7919

__all__ = ["Vocabulary", "BowIndex", "GlobalDescriptors", "vocabulary_size", "thumbnail_descriptor", "sad",
           "hog_descriptor", "hog_size", "make_thumbnail"]

#: Minimum descriptors per visual word when sizing a vocabulary from a map's own descriptors.
DESCRIPTORS_PER_WORD = 8


def vocabulary_size(n_descriptors: int, max_words: int) -> int:
    """Words for a vocabulary trained on ``n_descriptors``: as many as the data supports (8
    descriptors per word), at most ``max_words``."""
    return int(max(16, min(max_words, n_descriptors // DESCRIPTORS_PER_WORD)))


def _hamming(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N, B) uint8 x (N, k, B) uint8 -> (N, k) int32 Hamming distances."""
    return hamming(x[:, None, :], centres)


def _kmeans(x: np.ndarray, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV k-means++ on float32 rows: (centres (k, D), labels (N,))."""
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 15, 1e-3)
    _, labels, centres = cv2.kmeans(np.ascontiguousarray(x, np.float32), k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    return centres.astype(np.float32), labels.ravel().astype(np.int64)


def _kmeans_job(item: tuple[np.ndarray, int, int, bool]) -> tuple[np.ndarray, np.ndarray]:
    """One cluster's split (a task of :meth:`Vocabulary.train`): ``(rows, k, seed, binary)``, rows
    packed bits when ``binary``."""
    rows, k, seed, binary = item
    x = np.unpackbits(np.ascontiguousarray(rows, np.uint8), axis=1).astype(np.float32) if binary else rows
    return _kmeans(x, k, seed)


def _gather_rows(chunks: Sequence[np.ndarray], rows: np.ndarray) -> np.ndarray:
    """Rows ``rows`` (sorted) of the concatenation of ``chunks``, reading each chunk once (a chunk
    may be read from disk: :class:`topomap.spill.SpilledFeatures`)."""
    ends = np.cumsum([len(c) for c in chunks])
    which = np.searchsorted(ends, rows, side="right")
    parts = []
    for i in np.unique(which):
        chunk = np.asarray(chunks[i])
        parts.append(chunk[rows[which == i] - (ends[i] - len(chunk))])
    return np.concatenate(parts)


@dataclass(frozen=True)
class Vocabulary:
    """A vocabulary tree.

    ``centres[l]``: level-``l`` cluster centres — (n_l, B) uint8 packed bits for binary kinds,
    (n_l, D) float32 otherwise; ``children[l]``: (n_l, k) int32, row ``i`` lists the level-``l+1``
    children of centre ``i`` (padded by repeating the first child). Level 0 holds the root's
    ``k`` children; the leaves (last level) are the words.
    """

    centres: tuple[np.ndarray, ...]
    children: tuple[np.ndarray, ...]
    kind: str

    @property
    def size(self) -> int:
        return int(len(self.centres[-1]))

    @property
    def depth(self) -> int:
        return len(self.centres)

    @property
    def binary(self) -> bool:
        return detector(self.kind).binary

    # ------------------------------------------------------------------ training
    @classmethod
    def train(cls, descriptors: np.ndarray | Sequence, kind: str, words: int = 4096, seed: int = 0,
              max_samples: int = 200_000, mapper=None) -> Vocabulary:
        """Tree with about ``words`` leaves from (N, D) descriptors (subsampled to ``max_samples``),
        or from a sequence of array-likes (``len`` and ``np.asarray``) taken as their concatenation,
        which is never made: a big map's descriptors are read one node at a time and only the
        sampled rows kept (the same rows, the same tree);
        ``mapper(fn, items)``: an ordered parallel map (``Executor.map``) for the independent
        k-means runs of each level's clusters — the same tree with any mapper."""
        det = detector(kind)
        chunks = [descriptors] if isinstance(descriptors, np.ndarray) else descriptors
        n = sum(len(c) for c in chunks)
        if n < 2:
            raise ValueError("a vocabulary needs at least two descriptors")
        rng = np.random.default_rng(seed)
        if n > max_samples:
            descriptors = _gather_rows(chunks, np.sort(rng.choice(n, max_samples, replace=False)))
        elif not isinstance(descriptors, np.ndarray):
            descriptors = np.concatenate([np.asarray(c) for c in chunks])
        words = max(2, min(int(words), len(descriptors)))
        depth = 1 if words <= 64 else (2 if words <= 4096 else 3)
        k = max(2, math.ceil(words ** (1.0 / depth)))
        if det.binary:
            bits = np.unpackbits(np.ascontiguousarray(descriptors, np.uint8), axis=1).astype(np.float32)
        else:
            bits = np.asarray(descriptors, np.float32)

        def make_centre(rows: np.ndarray) -> np.ndarray:
            mean = bits[rows].mean(axis=0)
            return np.packbits(mean >= 0.5) if det.binary else mean  # binary: bit-wise majority

        # breadth-first: groups of sample rows, one per centre of the current level
        groups = [np.arange(len(bits))]
        centres, children = [], []
        for level in range(depth):
            level_centres, level_groups, kids = [], [], []
            jobs = [(g, rows) for g, rows in enumerate(groups) if 2 <= min(k, len(rows)) < len(rows)]
            if mapper is not None and len(jobs) > 1:  # packed descriptors travel, 8x less than bits
                items = [(descriptors[rows] if det.binary else bits[rows], min(k, len(rows)), seed + KMEANS_SEED_STRIDE * level + g, det.binary)
                         for g, rows in jobs]
                split = dict(zip((g for g, _ in jobs), mapper(_kmeans_job, items)))
            else:
                split = {g: _kmeans(bits[rows], min(k, len(rows)), seed + KMEANS_SEED_STRIDE * level + g) for g, rows in jobs}
            for g, rows in enumerate(groups):
                m = len(rows)
                kk = min(k, m)
                first = len(level_centres)
                if g in split:
                    c, lab = split[g]
                    for j in range(kk):
                        sub = rows[lab == j]
                        if len(sub) == 0:
                            continue
                        level_centres.append(make_centre(sub))
                        level_groups.append(sub)
                else:  # too few samples to split: each becomes its own centre (or the group stays whole)
                    parts = [rows[i : i + 1] for i in range(m)] if m <= k else [rows]
                    for sub in parts:
                        level_centres.append(make_centre(sub))
                        level_groups.append(sub)
                kid = list(range(first, len(level_centres)))
                kids.append(kid + [kid[0]] * (k - len(kid)))
            if level > 0:
                children.append(np.array(kids, np.int32))
            centres.append(np.stack(level_centres))
            groups = level_groups
        return cls(tuple(centres), tuple(children), det.name)

    # ------------------------------------------------------------------ quantisation
    def quantize(self, descriptors: np.ndarray, level: int | None = None) -> np.ndarray:
        """(N, D) descriptors -> (N,) int64 word ids (leaf indices), or with ``level`` the index of
        the tree node they pass through at that level (0 = the root's children)."""
        last = self.depth - 1 if level is None else int(level)
        if not 0 <= last < self.depth:
            raise ValueError(f"level {level} outside the tree's 0..{self.depth - 1}")
        n = len(descriptors)
        if n == 0:
            return np.zeros(0, np.int64)
        binary = self.binary
        x = np.ascontiguousarray(descriptors, np.uint8 if binary else np.float32)
        top = self.centres[0]
        if binary:
            cur = _hamming(x, top[None, :, :]).argmin(axis=1)
        else:
            cur = ((top**2).sum(1)[None, :] - 2.0 * x @ top.T).argmin(axis=1)
        rows = np.arange(n)
        for level in range(1, last + 1):
            cand = self.children[level - 1][cur]  # (N, k) candidate children
            c = self.centres[level][cand]
            if binary:
                d = _hamming(x, c)
            else:
                d = (c**2).sum(2) - 2.0 * np.einsum("nd,nkd->nk", x, c)
            cur = cand[rows, d.argmin(axis=1)]
        return cur.astype(np.int64)

    def ancestors(self, words: np.ndarray, level: int) -> np.ndarray:
        """(N,) leaf word ids -> (N,) int64 ids of their tree nodes at ``level`` (what
        ``quantize(descriptors, level)`` gives, without walking the tree again)."""
        if not 0 <= level < self.depth:
            raise ValueError(f"level {level} outside the tree's 0..{self.depth - 1}")
        return self._ancestor_tables[level][np.asarray(words, np.int64)]

    @cached_property
    def _ancestor_tables(self) -> list[np.ndarray]:
        """Per level, (size,) int64: the leaf -> level-node map, from the children tables."""
        tables = [np.arange(self.size, dtype=np.int64)]
        parent_of = np.arange(self.size, dtype=np.int64)  # leaf -> node of the level being built
        for level in range(self.depth - 2, -1, -1):
            up = np.empty(len(self.centres[level + 1]), np.int64)
            kids = self.children[level]
            up[kids.ravel()] = np.repeat(np.arange(len(kids)), kids.shape[1])  # padded repeats agree
            parent_of = up[parent_of]
            tables.insert(0, parent_of)
        return tables

    def group_level(self, max_groups: int) -> int:
        """The deepest tree level with at most ``max_groups`` nodes (at least level 0): the grouping
        for guided matching (ORB-SLAM matches within level-2 nodes of a 10-ary tree, ~100 groups)."""
        level = 0
        while level + 1 < self.depth and len(self.centres[level + 1]) <= max_groups:
            level += 1
        return level

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {f"vocab_centres_{i}": c for i, c in enumerate(self.centres)}
        out.update({f"vocab_children_{i + 1}": c for i, c in enumerate(self.children)})
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], kind: str) -> Vocabulary:
        centres, children = [], []
        while f"vocab_centres_{len(centres)}" in arrays:
            centres.append(arrays[f"vocab_centres_{len(centres)}"])
        for i in range(1, len(centres)):
            ch = arrays.get(f"vocab_children_{i}")
            if (ch is None or ch.ndim != 2 or ch.dtype.kind not in "iu" or len(ch) != len(centres[i - 1])
                    or (ch.size and (ch.min() < 0 or ch.max() >= len(centres[i])))):
                raise MapFormatError("map vocabulary is damaged; rebuild the index with `topomap index MAP`")
            children.append(ch.astype(np.int32))
        if not centres:
            raise MapFormatError("map index has no vocabulary; rebuild it with `topomap index MAP`")
        det = detector(kind)
        want = (np.uint8, det.descriptor_size) if det.binary else (np.float32, det.descriptor_size)
        for c in centres:
            if c.ndim != 2 or c.dtype != want[0] or c.shape[1] != want[1]:
                raise MapFormatError(f"map vocabulary does not fit {kind} descriptors; rebuild it with `topomap index MAP`")
        return cls(tuple(centres), tuple(children), det.name)


def _check_budget(max_postings: int | None) -> None:
    if max_postings is not None and (isinstance(max_postings, bool) or not isinstance(max_postings, (int, np.integer))
                                     or max_postings < 1):
        raise ValueError(f"max_postings={max_postings!r} must be a positive integer or None")


class BowIndex:
    """TF-IDF inverted file over map nodes.

    Postings are word-major: the nodes containing word ``w`` are ``rows[indptr[w]:indptr[w+1]]``
    (int32 row numbers, ``node_ids[row]`` is the node id) with ``counts`` (float32 term
    frequencies). ``idf``: (V,) float32; ``norms``: (N,) float32 norms of the nodes' TF-IDF vectors.

    ``feature_words`` (optional): the word of every feature of every node, node-row major, in each
    node's feature order — ``feature_words[feature_indptr[r]:feature_indptr[r+1]]`` for row ``r``
    (uint16 when the vocabulary allows, else uint32). DBoW2's "feature vector": it lets verification
    match only descriptors under the same vocabulary-tree node without quantising the node again.
    Maps indexed before it existed simply lack it (verification then quantises on demand).
    """

    #: A query ignores words held by more than this fraction of the nodes (once the map has at
    #: least STOP_MIN_NODES nodes): they are uninformative and own the longest posting lists.
    STOP_FRACTION = 0.05
    STOP_MIN_NODES = 2000

    def __init__(self, vocabulary: Vocabulary, node_ids: np.ndarray, indptr: np.ndarray, rows: np.ndarray, counts: np.ndarray,
                 feature_words: np.ndarray | None = None, feature_indptr: np.ndarray | None = None):
        self.vocabulary = vocabulary
        self.node_ids = np.asarray(node_ids, np.int64)
        self.indptr = np.asarray(indptr, np.int64)
        self.rows = np.asarray(rows, np.int32)
        self.counts = np.asarray(counts, np.float32)
        if (len(self.indptr) != vocabulary.size + 1 or self.indptr[0] != 0 or self.indptr[-1] != len(self.rows)
                or len(self.rows) != len(self.counts) or np.any(np.diff(self.indptr) < 0)):
            raise MapFormatError("map index is damaged (posting lists do not add up); rebuild it with `topomap index MAP`")
        if len(np.unique(self.node_ids)) != len(self.node_ids) or (len(self.counts) and not (self.counts > 0).all()):
            raise MapFormatError("map index is damaged (repeated nodes or empty postings); rebuild it with `topomap index MAP`")
        if len(self.rows) and (self.rows.min() < 0 or self.rows.max() >= len(self.node_ids)):
            raise MapFormatError("map index is damaged (postings name unknown nodes); rebuild it with `topomap index MAP`")
        self._row_of = {int(n): i for i, n in enumerate(self.node_ids)}
        self.feature_words = self.feature_indptr = None
        if feature_words is not None and feature_indptr is not None:
            fw, fp = np.asarray(feature_words), np.asarray(feature_indptr, np.int64)
            if (fw.ndim != 1 or fp.shape != (len(self.node_ids) + 1,) or fp[0] != 0 or fp[-1] != len(fw)
                    or np.any(np.diff(fp) < 0) or (len(fw) and int(fw.max()) >= vocabulary.size)):
                raise MapFormatError("map index is damaged (feature words do not add up); rebuild it with `topomap index MAP`")
            self.feature_words, self.feature_indptr = fw, fp
        self._reweight()

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, vocabulary: Vocabulary, features: dict[int, Features]) -> BowIndex:
        """Index the given nodes' features (``{node_id: Features}``)."""
        ids = np.array(sorted(features), np.int64)
        word_lists = [vocabulary.quantize(features[int(i)].descriptors) for i in ids]
        return cls._from_word_lists(vocabulary, ids, word_lists, word_lists)

    @classmethod
    def from_word_lists(cls, vocabulary: Vocabulary, ids, word_lists: list[np.ndarray],
                        feature_words: list[np.ndarray] | None = None) -> BowIndex:
        """Index nodes given directly as word ids (``word_lists[i]``: (n_i,) ints, the words of node
        ``ids[i]``, repeated by count): for synthetic maps in tests and benchmarks. ``feature_words``
        (optional): per node, the word of each of its features in feature order."""
        ids = np.asarray(ids, np.int64)
        if len(ids) != len(word_lists) or len(np.unique(ids)) != len(ids):
            raise ValueError("ids must be unique and one per word list")
        lists = [np.asarray(w, np.int64) for w in word_lists]
        per_feature = None if feature_words is None else [np.asarray(w, np.int64) for w in feature_words]
        for group in (lists, per_feature or []):
            if any(len(w) and (w.min() < 0 or w.max() >= vocabulary.size) for w in group):
                raise ValueError(f"word ids must lie in [0, {vocabulary.size})")
        if per_feature is not None and len(per_feature) != len(ids):
            raise ValueError("feature_words needs one array per node")
        return cls._from_word_lists(vocabulary, ids, lists, per_feature)

    @classmethod
    def _from_word_lists(cls, vocabulary: Vocabulary, ids: np.ndarray, word_lists: list[np.ndarray],
                         feature_words: list[np.ndarray] | None = None) -> BowIndex:
        words_all, rows_all, counts_all = [], [], []
        for r, words in enumerate(word_lists):
            uniq, cnt = np.unique(words, return_counts=True)
            words_all.append(uniq)
            rows_all.append(np.full(len(uniq), r, np.int32))
            counts_all.append(cnt.astype(np.float32))
        if words_all:
            w = np.concatenate(words_all)
            order = np.argsort(w, kind="stable")
            rows = np.concatenate(rows_all)[order]
            counts = np.concatenate(counts_all)[order]
            indptr = np.searchsorted(w[order], np.arange(vocabulary.size + 1))
        else:
            rows, counts, indptr = np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(vocabulary.size + 1, np.int64)
        fw = fp = None
        if feature_words is not None:
            dtype = np.uint16 if vocabulary.size <= 1 << 16 else np.uint32
            fp = np.concatenate(([0], np.cumsum([len(w) for w in feature_words]))).astype(np.int64)
            fw = np.concatenate([np.asarray(w) for w in feature_words]).astype(dtype) if feature_words else np.zeros(0, dtype)
        return cls(vocabulary, ids, indptr, rows, counts, fw, fp)

    def row_indices(self, node_ids) -> np.ndarray:
        """Rows of the score arrays (:meth:`scores`) that hold the given node ids (all in the index)."""
        return np.array([self._row_of[int(n)] for n in node_ids], np.intp)

    def words_of_features(self, node_id: int) -> np.ndarray | None:
        """The word of each feature of ``node_id`` (feature order), or ``None`` if not stored."""
        if self.feature_words is None:
            return None
        r = self._row_of[int(node_id)]
        return self.feature_words[self.feature_indptr[r] : self.feature_indptr[r + 1]]

    def _word_lists(self) -> list[np.ndarray]:
        """Per node row, its words repeated by count (inverse of ``_from_word_lists``)."""
        words = np.repeat(np.arange(self.vocabulary.size), np.diff(self.indptr))
        order = np.argsort(self.rows, kind="stable")
        per_row = np.split(order, np.searchsorted(self.rows[order], np.arange(1, len(self.node_ids))))
        return [np.repeat(words[o], self.counts[o].astype(np.int64)) for o in per_row]

    def add(self, features: dict[int, Features]) -> None:
        """Append nodes (ids must be new); IDF weights are recomputed."""
        clash = [i for i in features if int(i) in self._row_of]
        if clash:
            raise ValueError(f"nodes {clash[:5]} are already indexed")
        ids = np.array(sorted(features), np.int64)
        new = [self.vocabulary.quantize(features[int(i)].descriptors) for i in ids]
        per_feature = None
        if self.feature_words is not None:
            per_feature = [self.feature_words[a:b] for a, b in zip(self.feature_indptr[:-1], self.feature_indptr[1:])] + new
        fresh = self._from_word_lists(self.vocabulary, np.concatenate([self.node_ids, ids]), self._word_lists() + new, per_feature)
        self.__dict__.update(fresh.__dict__)

    #: Postings handled at once when weighting a very large index (bounds the float64 temporaries).
    REWEIGHT_CHUNK = 1 << 26

    def _reweight(self) -> None:
        n = len(self.node_ids)
        lengths = np.diff(self.indptr)
        self.df = lengths.astype(np.float32)
        self.idf = np.log((n + 1.0) / (self.df + 1.0)).astype(np.float32)
        # per posting: its word's idf times its count (float32, like the counts), then the unit vectors
        w = np.repeat(self.idf, lengths)
        w *= self.counts
        chunk = self.REWEIGHT_CHUNK
        if len(w) <= chunk:  # one pass (every real map): the sums in posting order
            norms = np.bincount(self.rows, weights=w * w, minlength=n)
        else:  # a million nodes: the same sums, chunk by chunk, without 8-byte-per-posting temporaries
            norms = np.zeros(n, np.float64)
            for s in range(0, len(w), chunk):
                part = w[s : s + chunk]
                norms += np.bincount(self.rows[s : s + chunk], weights=part * part, minlength=n)
        self.norms = np.sqrt(norms).astype(np.float32)
        self.norms[self.norms == 0] = 1.0
        for s in range(0, len(w), chunk):
            w[s : s + chunk] /= self.norms[self.rows[s : s + chunk]]
        self._weights = w  # posting weights of unit vectors, float32
        # the same postings as a (V, N) CSR matrix sharing the arrays (int32 row pointers when they fit)
        indptr = self.indptr.astype(np.int32) if len(self.rows) < 2**31 else self.indptr
        self._matrix = sp.csr_matrix((self._weights, self.rows, indptr), shape=(self.vocabulary.size, n), copy=False)
        stop = n >= self.STOP_MIN_NODES
        self.stop_words = self.df > self.STOP_FRACTION * n if stop else np.zeros(self.vocabulary.size, bool)

    def __len__(self) -> int:
        return len(self.node_ids)

    def memory_bytes(self) -> int:
        """Bytes held in RAM by the index (vocabulary + postings + per-word/per-node arrays)."""
        arrays = [*self.vocabulary.centres, *self.vocabulary.children, self.node_ids, self.indptr, self.rows,
                  self.counts, self._weights, self.idf, self.df, self.norms, self.stop_words]
        if self.feature_words is not None:
            arrays += [self.feature_words, self.feature_indptr]
        return int(sum(a.nbytes for a in arrays))

    # ------------------------------------------------------------------ queries
    def query_words(self, f: Features, words: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The query's (word ids, unit TF-IDF weights); ``words``: its features' words if known."""
        words, tf = np.unique(self.vocabulary.quantize(f.descriptors) if words is None else words, return_counts=True)
        q = tf.astype(np.float32) * self.idf[words]
        norm = float(np.sqrt((q * q).sum()))
        return words, (q / norm if norm > 0 else q)

    def query_terms(self, f: Features, words: np.ndarray | None = None,
                    max_postings: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The query's (word ids, unit TF-IDF weights) that :meth:`scores` reads: its stop words
        dropped and, with ``max_postings``, only its rarest words (shortest posting lists first, ties
        by word id) while their lists hold at most that many postings together (at least one list):
        the work per query stays bounded however large the map. Weights stay those of the whole
        query (what is dropped is not renormalised away, as for the stop words)."""
        _check_budget(max_postings)
        words, q = self.query_words(f, words)
        keep = ~self.stop_words[words]
        words, q = words[keep], q[keep]
        if max_postings is not None and len(words) > 1:
            lengths = self.indptr[words + 1] - self.indptr[words]
            if int(lengths.sum()) > max_postings:
                order = np.argsort(lengths, kind="stable")  # words are unique and ascending: ties by id
                read = np.cumsum(lengths[order])
                # at least the rarest word any node holds (words no node holds cost nothing)
                n_keep = max(int(np.searchsorted(read, max_postings, side="right")),
                             int(np.searchsorted(read, 0, side="right")) + 1)
                chosen = np.sort(order[:n_keep])
                words, q = words[chosen], q[chosen]
        return words, q

    def scores(self, f: Features, words: np.ndarray | None = None, max_postings: int | None = None) -> np.ndarray:
        """Cosine similarity of the query to every indexed node: (N,) float32 in row order, over the
        words :meth:`query_terms` keeps (all but the stop words unless ``max_postings`` cuts).
        ``words``: the query features' words (``vocabulary.quantize``) if already computed."""
        n = len(self.node_ids)
        _check_budget(max_postings)
        if n == 0 or len(f) == 0:
            return np.zeros(n, np.float32)
        words, q = self.query_terms(f, words, max_postings)
        if len(words) == 0:
            return np.zeros(n, np.float32)
        # the touched posting lists as a sparse (words x nodes) block, transposed, times the query's
        # weights: scipy's C++ gather and product (~1.6 M postings at 100k nodes: 2 ms; slice-by-slice
        # numpy concatenation and a bincount took 7 ms)
        return np.asarray(self._matrix[words].T @ q, dtype=np.float32).ravel()

    def shortlist(self, f: Features, k: int, exclude: set[int] | None = None, words: np.ndarray | None = None,
                  max_postings: int | None = None) -> list[tuple[int, float]]:
        """The ``k`` most similar nodes as ``(node_id, score)``, best first (ties by node id)."""
        return self.top_k(self.scores(f, words, max_postings), k, exclude)

    def top_k(self, scores: np.ndarray, k: int, exclude: set[int] | None = None) -> list[tuple[int, float]]:
        """Best ``k`` of a row-ordered score array as ``(node_id, score)``, ties by node id;
        ``exclude`` holds node ids (never listed, nor are rows scoring -inf)."""
        if exclude:
            scores = scores.copy()
            rows = [self._row_of[int(n)] for n in exclude if int(n) in self._row_of]
            scores[rows] = -np.inf
        n = len(scores)
        k = min(k, n)
        if k <= 0:
            return []
        # the k-th largest value, then every row above it and, of the rows equal to it, those of the
        # smallest node ids: a partition of the scores (no negated copy), ties decided by node id
        kth = np.partition(scores, n - k)[n - k]
        if kth == -np.inf:  # fewer than k rows left: all of them
            above = np.flatnonzero(scores > -np.inf)
            tied = np.zeros(0, np.intp)
        else:
            above = np.flatnonzero(scores > kth)
            tied = np.flatnonzero(scores == kth)
            need = k - len(above)  # >= 1: fewer than k rows lie above the k-th value
            if len(tied) > need:
                tied = tied[np.argpartition(self.node_ids[tied], need - 1)[:need]]
        part = np.concatenate([above, tied])
        order = part[np.lexsort((self.node_ids[part], -scores[part]))][:k]
        return [(int(self.node_ids[r]), float(scores[r])) for r in order]

    def row_of(self, node_id: int) -> int:
        return self._row_of[int(node_id)]

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        out = {
            **self.vocabulary.to_arrays(),
            "bow_node_ids": self.node_ids,
            "bow_indptr": self.indptr,
            "bow_rows": self.rows,
            "bow_counts": self.counts.astype(np.uint16),
        }
        if self.feature_words is not None:
            out["bow_feature_words"] = self.feature_words
            out["bow_feature_indptr"] = self.feature_indptr
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], kind: str) -> BowIndex:
        voc = Vocabulary.from_arrays(arrays, kind)
        try:
            return cls(voc, arrays["bow_node_ids"], arrays["bow_indptr"], arrays["bow_rows"], arrays["bow_counts"],
                       arrays.get("bow_feature_words"), arrays.get("bow_feature_indptr"))
        except KeyError as e:
            raise MapFormatError(f"map index is incomplete (missing {e.args[0]}); rebuild it with `topomap index MAP`") from None


def make_thumbnail(image: np.ndarray, longest_px: int) -> np.ndarray:
    """``(H, W)`` image reduced (area averaging) so that its longest side is ``longest_px``; smaller ones copied."""
    h, w = image.shape
    s = longest_px / max(h, w)
    if s >= 1:
        return image.copy()
    return cv2.resize(image, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def thumbnail_descriptor(image: np.ndarray, size: tuple[int, int] = THUMBNAIL_SIZE, patch: int = THUMBNAIL_PATCH) -> np.ndarray:
    """Patch-normalised thumbnail (SeqSLAM): ``(H, W) uint8`` image -> ``(w*h,)`` float32 descriptor.

    The image is shrunk to ``size = (w, h)`` by area averaging; each ``patch x patch`` block is
    then brought to zero mean and unit variance, which removes most illumination change.
    Compare two descriptors with the mean absolute difference (:func:`sad`).
    """
    w, h = size
    t = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    out = np.empty_like(t)
    for y in range(0, h, patch):
        for x in range(0, w, patch):
            block = t[y : y + patch, x : x + patch]
            sd = block.std()
            out[y : y + patch, x : x + patch] = (block - block.mean()) / (sd if sd > 1e-6 else 1.0)
    return out.ravel()


def sad(query: np.ndarray, refs: np.ndarray, block: int = 1024) -> np.ndarray:
    """Mean absolute difference between a (D,) descriptor and (N, D) references -> (N,) float32.

    Computed ``block`` rows at a time in one reused buffer: the same numbers as the one-line numpy
    expression, twice as fast on big maps (no N x D temporaries; 100k nodes: ~70 ms instead of ~150).
    """
    refs = np.asarray(refs, np.float32)
    query = np.asarray(query, np.float32)[None, :]
    out = np.empty(len(refs), np.float32)
    buf = np.empty((min(block, len(refs)), refs.shape[1] if refs.ndim == 2 else 0), np.float32)
    for start in range(0, len(refs), block):
        rows = refs[start : start + block]
        t = buf[: len(rows)]
        np.subtract(rows, query, out=t)
        np.abs(t, out=t)
        out[start : start + len(rows)] = t.mean(axis=1)
    return out


# ---------------------------------------------------------------------- gradient-orientation descriptor
#: Whole-image HOG (Dalal & Triggs 2005): the thumbnail resized to HOG_WIDTH px wide, cells of HOG_CELL
#: px, blocks of 2x2 cells normalised on their own. Gradient orientations survive illumination and
#: exposure changes that move every intensity (each block is contrast-normalised), which the bag of
#: words' keypoints do not; the coarse grid tolerates the few pixels of shift between neighbouring
#: views. See docs/localization.md for what it adds on the corridor and Nordland.
HOG_WIDTH = 128
HOG_CELL = 16
HOG_BINS = 9
#: Gaussian blur before the gradients [px]: sensor noise otherwise fills every orientation bin.
HOG_BLUR_SIGMA = 1.0


def hog_size(width: int, height: int) -> tuple[int, int]:
    """``(w, h)`` the HOG is computed at for images of this aspect: whole cells, at least 2x2 of them."""
    h = max(2 * HOG_CELL, int(round(HOG_WIDTH * height / max(width, 1) / HOG_CELL)) * HOG_CELL)
    return HOG_WIDTH, h


def hog_descriptor(image: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """Whole-image gradient-orientation descriptor: ``(H, W) uint8`` image -> ``(D,)`` float32, unit L2.

    Compare two descriptors by their dot product (cosine similarity). ``size`` defaults to
    :func:`hog_size` of the image; every image compared must use the same size.
    """
    w, h = size or hog_size(image.shape[1], image.shape[0])
    t = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if image.shape[1] >= w else cv2.INTER_LINEAR)
    t = cv2.GaussianBlur(t, (0, 0), HOG_BLUR_SIGMA)
    hog = cv2.HOGDescriptor((w, h), (2 * HOG_CELL, 2 * HOG_CELL), (HOG_CELL, HOG_CELL), (HOG_CELL, HOG_CELL), HOG_BINS)
    d = hog.compute(t).astype(np.float32).ravel()
    d -= d.mean()  # a flat image (all bins equal after normalisation) then scores ~0 against everything
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-9 else d


@dataclass(frozen=True)
class GlobalDescriptors:
    """Whole-image descriptors of a map's nodes: ``node_ids`` (N,) int64 and ``matrix`` (N, D) float32
    (rows unit L2; D = 1260 for 4:3 images, 5 KB a node in memory, 2.5 KB in the file as float16) of
    ``kind`` ``"hog"`` at ``size = (w, h)``."""

    kind: str
    size: tuple[int, int]
    node_ids: np.ndarray
    matrix: np.ndarray

    @classmethod
    def from_thumbnails(cls, thumbnails: dict[int, np.ndarray]) -> GlobalDescriptors:
        """HOG of each node's stored thumbnail (the map's working images reduced to ``thumbnail_px``)."""
        ids = np.array(sorted(thumbnails), np.int64)
        if len(ids) == 0:
            return cls("hog", (HOG_WIDTH, 2 * HOG_CELL), ids, np.zeros((0, 0), np.float32))
        first = thumbnails[int(ids[0])]
        size = hog_size(first.shape[1], first.shape[0])
        matrix = np.stack([hog_descriptor(thumbnails[int(i)], size) for i in ids])
        return cls("hog", size, ids, matrix)

    def similarity(self, query: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Cosine similarity of a query descriptor to every node (or to ``rows``), (N,) float32."""
        m = self.matrix if rows is None else self.matrix[rows]
        return m @ np.asarray(query, np.float32)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"global_node_ids": self.node_ids, "global_matrix": self.matrix.astype(np.float16)}

    def to_meta(self) -> dict:
        return {"kind": self.kind, "size": list(self.size), "cell": HOG_CELL, "bins": HOG_BINS}

    @classmethod
    def from_map(cls, arrays: dict[str, np.ndarray], meta: dict | None) -> GlobalDescriptors | None:
        """The stored descriptors, or ``None`` when the map has none or they were made another way."""
        if not meta or "global_matrix" not in arrays or "global_node_ids" not in arrays:
            return None
        if meta.get("kind") != "hog" or meta.get("cell") != HOG_CELL or meta.get("bins") != HOG_BINS:
            return None
        ids = np.asarray(arrays["global_node_ids"], np.int64).ravel()
        matrix = np.asarray(arrays["global_matrix"])
        size = meta.get("size")
        ok = (matrix.ndim == 2 and len(matrix) == len(ids) and isinstance(size, list) and len(size) == 2
              and all(isinstance(v, int) and 2 * HOG_CELL <= v <= 64 * HOG_CELL for v in size)
              and matrix.dtype.kind == "f" and bool(np.isfinite(matrix).all()))
        if not ok:
            raise MapFormatError("the map's global descriptors are malformed; rebuild them with `topomap index MAP`")
        # float16 in the file, float32 in memory: numpy casts float16 at ~3 ns an element, which at
        # 2000 candidates would cost more than the comparison itself
        return cls("hog", (int(size[0]), int(size[1])), ids, matrix.astype(np.float32))
