"""Place recognition: a visual vocabulary with a TF-IDF inverted index, and whole-image descriptors.

* :class:`Vocabulary` — a two-level hierarchical k-means tree (DBoW2-style) trained with
  scikit-learn; binary descriptors are unpacked to {0, 1} bit vectors, where squared L2 equals the
  Hamming distance. Quantising a descriptor costs ``k1 + k2`` distance evaluations instead of
  ``k1 * k2`` (sklearn has no hierarchical k-means, hence the small tree written here).
* :class:`BowIndex` — L2-normalised TF-IDF bag-of-words vectors in a sparse node x word matrix;
  :meth:`BowIndex.shortlist` returns the k most similar nodes (cosine similarity).
* :func:`thumbnail_descriptor` — a patch-normalised thumbnail (SeqSLAM), the whole-image
  descriptor for images too small or too blurred for keypoints.

Everything serialises to plain numpy arrays (``to_arrays`` / ``from_arrays``), never pickle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
from sklearn.cluster import MiniBatchKMeans

from topomap.errors import MapFormatError
from topomap.features import Features, detector

__all__ = ["Vocabulary", "BowIndex", "thumbnail_descriptor", "descriptor_space"]


def descriptor_space(descriptors: np.ndarray, binary: bool) -> np.ndarray:
    """Descriptors in the Euclidean space the vocabulary lives in: (N, D) float32.

    Binary descriptors (N, B) uint8 become (N, 8B) bit vectors; float descriptors are L2-normalised.
    """
    if binary:
        return np.unpackbits(np.ascontiguousarray(descriptors, dtype=np.uint8), axis=1).astype(np.float32)
    d = np.asarray(descriptors, dtype=np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _nearest(x: np.ndarray, centers: np.ndarray, centers_sq: np.ndarray) -> np.ndarray:
    """Index of the nearest centre (squared L2) for each row of x."""
    return np.argmin(centers_sq[None, :] - 2.0 * (x @ centers.T), axis=1)


@dataclass(frozen=True)
class Vocabulary:
    """Two-level k-means tree over descriptor space.

    ``top``: (k1, D) float32 level-1 centres; ``leaves``: (k1, k2, D) float32 level-2 centres
    (unused slots hold copies of the parent centre); ``kind``: the feature type it was trained for.
    Word id = ``i1 * k2 + i2``; ``size`` = k1 * k2.
    """

    top: np.ndarray
    leaves: np.ndarray
    kind: str

    @property
    def size(self) -> int:
        return int(self.leaves.shape[0] * self.leaves.shape[1])

    @property
    def binary(self) -> bool:
        return detector(self.kind).binary

    @classmethod
    def train(cls, descriptors: np.ndarray, kind: str, words: int = 1024, seed: int = 0, max_samples: int = 200_000) -> Vocabulary:
        """k-means tree with about ``words`` leaves from (N, D) descriptors (subsampled, seeded)."""
        det = detector(kind)
        rng = np.random.default_rng(seed)
        n = len(descriptors)
        if n == 0:
            raise ValueError("cannot train a vocabulary without descriptors")
        if n > max_samples:
            descriptors = descriptors[np.sort(rng.choice(n, max_samples, replace=False))]
        x = descriptor_space(descriptors, det.binary)
        # enough descriptors per word for the centres to mean something
        words = int(max(4, min(words, len(x) // 8)))
        k1 = int(max(2, round(math.sqrt(words))))
        k2 = int(max(1, math.ceil(words / k1)))
        top = _kmeans(x, k1, seed)
        assign = _nearest(x, top, (top**2).sum(1))
        leaves = np.repeat(top[:, None, :], k2, axis=1).copy()
        for c in range(len(top)):
            members = x[assign == c]
            k = min(k2, len(members))
            if k >= 2:
                leaves[c, :k] = _kmeans(members, k, seed + 1 + c)
        return cls(top.astype(np.float32), leaves.astype(np.float32), det.name)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) descriptors -> (N,) int64 word ids."""
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        x = descriptor_space(descriptors, self.binary)
        i1 = _nearest(x, self.top, (self.top**2).sum(1))
        k2 = self.leaves.shape[1]
        words = np.empty(len(x), np.int64)
        leaves_sq = (self.leaves**2).sum(2)
        for c in np.unique(i1):
            rows = np.nonzero(i1 == c)[0]
            words[rows] = c * k2 + _nearest(x[rows], self.leaves[c], leaves_sq[c])
        return words

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"vocab_top": self.top, "vocab_leaves": self.leaves}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], kind: str) -> Vocabulary:
        try:
            top, leaves = arrays["vocab_top"], arrays["vocab_leaves"]
        except KeyError as e:
            raise MapFormatError(f"map index is incomplete (missing {e.args[0]}); rebuild it with `topomap index`") from None
        if top.ndim != 2 or leaves.ndim != 3 or leaves.shape[0] != top.shape[0] or leaves.shape[2] != top.shape[1]:
            raise MapFormatError("map vocabulary arrays have inconsistent shapes; rebuild it with `topomap index`")
        return cls(top.astype(np.float32), leaves.astype(np.float32), kind)


def _kmeans(x: np.ndarray, k: int, seed: int) -> np.ndarray:
    km = MiniBatchKMeans(n_clusters=k, random_state=seed, n_init=1, batch_size=2048, max_iter=20)
    km.fit(x)
    return km.cluster_centers_.astype(np.float32)


class BowIndex:
    """TF-IDF bag-of-words index over map nodes.

    ``node_ids``: (N,) int64 node id of each row; ``matrix``: (N, V) CSR float32, L2-normalised
    TF-IDF rows; ``idf``: (V,) float32.
    """

    def __init__(self, vocabulary: Vocabulary, node_ids: np.ndarray, counts: sp.csr_matrix):
        self.vocabulary = vocabulary
        self.node_ids = np.asarray(node_ids, np.int64)
        self.counts = counts.tocsr().astype(np.float32)  # raw word counts per node (kept to re-weight on growth)
        self._row_of = {int(n): i for i, n in enumerate(self.node_ids)}
        self._reweight()

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, vocabulary: Vocabulary, features: dict[int, Features]) -> BowIndex:
        """Index the given nodes' features (``{node_id: Features}``)."""
        ids = np.array(sorted(features), np.int64)
        rows = [cls._counts(vocabulary, features[int(i)]) for i in ids]
        counts = sp.vstack(rows, format="csr") if rows else sp.csr_matrix((0, vocabulary.size), dtype=np.float32)
        return cls(vocabulary, ids, counts)

    @staticmethod
    def _counts(vocabulary: Vocabulary, f: Features) -> sp.csr_matrix:
        words = vocabulary.quantize(f.descriptors)
        uniq, cnt = np.unique(words, return_counts=True)
        return sp.csr_matrix((cnt.astype(np.float32), (np.zeros_like(uniq), uniq)), shape=(1, vocabulary.size))

    def add(self, features: dict[int, Features]) -> None:
        """Append nodes (ids must be new); IDF weights are recomputed."""
        clash = [i for i in features if int(i) in self._row_of]
        if clash:
            raise ValueError(f"nodes {clash[:5]} are already indexed")
        ids = np.array(sorted(features), np.int64)
        rows = [self._counts(self.vocabulary, features[int(i)]) for i in ids]
        if not rows:
            return
        self.counts = sp.vstack([self.counts, *rows], format="csr")
        self.node_ids = np.concatenate([self.node_ids, ids])
        self._row_of = {int(n): i for i, n in enumerate(self.node_ids)}
        self._reweight()

    def _reweight(self) -> None:
        n = max(1, self.counts.shape[0])
        df = np.bincount(self.counts.indices, minlength=self.vocabulary.size).astype(np.float32)
        self.idf = np.log((n + 1.0) / (df + 1.0)).astype(np.float32) + 1e-6
        self.matrix = _normalise_rows(self.counts.multiply(self.idf[None, :]).tocsr())
        self._csc = self.matrix.T.tocsr()  # word x node: the inverted file

    def __len__(self) -> int:
        return len(self.node_ids)

    # ------------------------------------------------------------------ queries
    def vector(self, f: Features) -> sp.csr_matrix:
        """The (1, V) L2-normalised TF-IDF vector of a query image."""
        return _normalise_rows(self._counts(self.vocabulary, f).multiply(self.idf[None, :]).tocsr())

    def scores(self, f: Features) -> np.ndarray:
        """Cosine similarity of the query to every indexed node: (N,) float32 in row order."""
        q = self.vector(f)
        if q.nnz == 0 or len(self) == 0:
            return np.zeros(len(self), np.float32)
        # inverted file: only the posting lists of the query's words are touched
        return np.asarray((self._csc[q.indices].T @ q.data)).ravel().astype(np.float32)

    def shortlist(self, f: Features, k: int, exclude: set[int] | None = None) -> list[tuple[int, float]]:
        """The ``k`` most similar nodes as ``(node_id, score)``, best first (ties by node id)."""
        s = self.scores(f)
        return self.top_k(s, k, exclude)

    def top_k(self, scores: np.ndarray, k: int, exclude: set[int] | None = None) -> list[tuple[int, float]]:
        if exclude:
            scores = scores.copy()
            for n in exclude:
                r = self._row_of.get(int(n))
                if r is not None:
                    scores[r] = -np.inf
        k = min(k, len(scores))
        if k <= 0:
            return []
        part = np.argpartition(-scores, k - 1)[:k]
        order = part[np.lexsort((self.node_ids[part], -scores[part]))]
        return [(int(self.node_ids[r]), float(scores[r])) for r in order if np.isfinite(scores[r])]

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        c = self.counts
        return {
            **self.vocabulary.to_arrays(),
            "bow_node_ids": self.node_ids,
            "bow_indptr": c.indptr.astype(np.int64),
            "bow_indices": c.indices.astype(np.int32),
            "bow_counts": c.data.astype(np.float32),
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], kind: str) -> BowIndex:
        voc = Vocabulary.from_arrays(arrays, kind)
        try:
            ids = arrays["bow_node_ids"]
            counts = sp.csr_matrix(
                (arrays["bow_counts"], arrays["bow_indices"], arrays["bow_indptr"]), shape=(len(ids), voc.size)
            )
        except KeyError as e:
            raise MapFormatError(f"map index is incomplete (missing {e.args[0]}); rebuild it with `topomap index`") from None
        except ValueError as e:
            raise MapFormatError(f"map index is damaged ({e}); rebuild it with `topomap index`") from None
        return cls(voc, ids, counts)


def _normalise_rows(m: sp.csr_matrix) -> sp.csr_matrix:
    norms = np.sqrt(np.asarray(m.multiply(m).sum(axis=1)).ravel())
    norms[norms == 0] = 1.0
    return sp.diags(1.0 / norms).dot(m).tocsr().astype(np.float32)


def thumbnail_descriptor(image: np.ndarray, size: tuple[int, int] = (32, 24), patch: int = 8) -> np.ndarray:
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


def sad(query: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """Mean absolute difference between a (D,) descriptor and (N, D) references -> (N,) float32."""
    return np.abs(np.asarray(refs, np.float32) - np.asarray(query, np.float32)[None, :]).mean(axis=1)
