"""Visual vocabulary: a hierarchical k-majority tree over 256-bit ORB descriptors (DBoW2-like).

The tree has branching factor ``k`` and depth ``L``. Every node holds a 32-byte binary
centre; the leaves are the *words*. Training clusters descriptors level by level with
k-majority (k-medians under the Hamming distance; centres are bitwise majorities) seeded by
k-means++. As in DBoW2, a node with at most ``k`` descriptors gets one child per (distinct)
descriptor, so leaves may sit above depth ``L``.

Words carry tf-idf weights: ``idf(w) = ln(N_images / n_images_containing(w))`` from the
training images. A bag-of-words vector is sparse (sorted word ids, weights), L1-normalised,
and two vectors are compared with DBoW2's L1 score ``1 - 0.5 * |a - b|_1`` in [0, 1].

Lookup descends the tree for many descriptors at once (numpy XOR + ``np.bitwise_count`` on
``uint64`` views), so its result is defined as: at each level take the child with the
smallest Hamming distance, ties to the lowest child slot.

File format: ``numpy.savez_compressed`` with arrays ``node_desc (M, 32) uint8``,
``parent (M,) int32`` (root has -1; children listed in slot order), ``idf (S,) float64``,
``word_count (S,) int64`` (training descriptors per word, used by the feature codec as a
prior), ``residual_ones (256,) int64`` / ``residual_total`` (per-bit-position counts of ones
in training XOR residuals), ``bit_parents (256, P) int16`` / ``bit_p1 (256, 2**P)`` (the
codec's context model of descriptor bits, see :func:`fit_bit_context_model`) and ``meta``
(a JSON string: ``format``, ``k``, ``depth``, ``n_words``, ``n_nodes``, ``trained_on``,
``n_descriptors``, ``n_images``, ``seed``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.errors import RecslamError

log = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32
FORMAT = "recslam-vocabulary-1"
DEFAULT_VOCABULARY_PATH = Path(__file__).resolve().parent / "assets" / "orb_vocabulary.npz"


class VocabularyError(RecslamError):
    """Bad vocabulary file, bad training input or bad descriptors."""


@dataclass(frozen=True)
class VocabularyTrainingConfig:
    """Training options.

    k: branching factor (children per node), default 10.
    depth: number of levels below the root (DBoW2's L), default 5.
    max_iterations: k-majority iterations per node, default 10.
    seed: seed of the random generator (k-means++ seeding), default 0.
    bit_context_parents: parents per bit of the codec's descriptor-bit context model, 10.
    """

    k: int = 10
    depth: int = 5
    max_iterations: int = 10
    seed: int = 0
    bit_context_parents: int = 10


@dataclass(frozen=True)
class BowVector:
    """Sparse bag-of-words vector: ``words (K,) int32`` sorted, ``weights (K,) float64``
    (L1-normalised tf-idf)."""

    words: np.ndarray
    weights: np.ndarray


def _check_descriptors(descriptors: np.ndarray, what: str = "descriptors") -> np.ndarray:
    d = np.asarray(descriptors)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES or d.dtype != np.uint8:
        raise VocabularyError(f"{what} must be (N, 32) uint8, got {d.shape} {d.dtype}")
    return np.ascontiguousarray(d)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances ``(N, M) int64`` between descriptors ``a (N, 32)`` and ``b (M, 32)``."""
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(a64[:, None, :] ^ b64[None, :, :]).sum(axis=2, dtype=np.int64)


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance ``(N,) int64`` between each row of ``a (N, 32)`` and the same row of
    ``b (N, 32)``."""
    a64 = np.ascontiguousarray(a).view(np.uint64)
    b64 = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(a64 ^ b64).sum(axis=1, dtype=np.int64)


def _majority(bits: np.ndarray) -> np.ndarray:
    """Bitwise majority of unpacked bits ``(n, 256)`` -> packed ``(32,) uint8`` (ties -> 1)."""
    return np.packbits(2 * bits.sum(axis=0, dtype=np.int64) >= bits.shape[0])


def _kmajority(
    desc: np.ndarray, bits: np.ndarray, k: int, rng: np.random.Generator, iters: int
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster ``desc (n, 32)`` (n > k) into k clusters; returns (centres (c, 32), labels (n,))."""
    n = desc.shape[0]
    # k-means++ seeding on squared Hamming distance.
    centres = [desc[int(rng.integers(n))]]
    dmin = hamming_matrix(desc, centres[0][None, :])[:, 0].astype(np.float64)
    while len(centres) < k:
        w = dmin**2
        total = w.sum()
        if total <= 0:
            break  # fewer distinct descriptors than k
        idx = int(np.searchsorted(np.cumsum(w), rng.random() * total, side="right"))
        idx = min(idx, n - 1)
        centres.append(desc[idx])
        dmin = np.minimum(dmin, hamming_matrix(desc, desc[idx][None, :])[:, 0])
    c = np.stack(centres)
    labels = np.full(n, -1, dtype=np.int64)
    for _ in range(iters):
        new_labels = np.argmin(hamming_matrix(desc, c), axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
        keep = []
        for j in range(c.shape[0]):
            members = labels == j
            if members.any():
                c[j] = _majority(bits[members])
                keep.append(j)
        if len(keep) < c.shape[0]:  # drop empty clusters and relabel
            c = c[keep]
            labels = np.argmin(hamming_matrix(desc, c), axis=1)
    return c, labels


def fit_bit_context_model(
    descriptors: np.ndarray,
    n_parents: int = 10,
    n_candidates: int = 24,
    max_samples: int = 20000,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Context model of ORB descriptor bits for the feature codec.

    For every bit ``j`` greedily picks ``n_parents`` earlier bits (among the ``n_candidates``
    most correlated) that minimise the conditional entropy ``H(b_j | parents)``.
    Returns ``parents (256, P) int16`` (bit 0 uses bit 0's own index as dummies, always
    zero context) and ``p1 (256, 2**P) float64``: P(b_j = 1 | parent bits), context index
    ``sum(b_parent[q] << (P - 1 - q))``.
    """
    d = _check_descriptors(descriptors)
    rng = np.random.default_rng(seed)
    if d.shape[0] > max_samples:
        d = d[np.sort(rng.choice(d.shape[0], max_samples, replace=False))]
    b = np.unpackbits(d, axis=1).astype(np.int64)
    n = b.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.nan_to_num(np.corrcoef(b.T.astype(np.float64)))
    parents = np.zeros((256, n_parents), dtype=np.int16)
    p1 = np.full((256, 1 << n_parents), 0.5)

    def cond_entropy(bj: np.ndarray, ctx: np.ndarray, size: int) -> float:
        ones = np.bincount(ctx, weights=bj, minlength=size)
        tot = np.bincount(ctx, minlength=size)
        p = (ones + 0.5) / (tot + 1.0)
        return float(-np.log2(np.where(bj == 1, p[ctx], 1.0 - p[ctx])).sum())

    for j in range(256):
        cands = [int(c) for c in np.argsort(-np.abs(corr[j, :j]), kind="stable")[:n_candidates]]
        ctx = np.zeros(n, dtype=np.int64)
        chosen: list[int] = []
        for q in range(n_parents):
            best, best_h = -1, np.inf
            for c in cands:
                if c in chosen:
                    continue
                h = cond_entropy(b[:, j], ctx * 2 + b[:, c], 2 << q)
                if h < best_h:
                    best, best_h = c, h
            if best < 0:  # not enough earlier bits: a dummy parent that is always 0
                best = -1
                ctx = ctx * 2
            else:
                ctx = ctx * 2 + b[:, best]
            chosen.append(best)
        parents[j] = chosen
        ones = np.bincount(ctx, weights=b[:, j], minlength=1 << n_parents)
        tot = np.bincount(ctx, minlength=1 << n_parents)
        p1[j] = (ones + 0.5) / (tot + 1.0)
    return parents, p1


class Vocabulary:
    """A trained vocabulary tree. Build with :meth:`train` or :meth:`load`.

    Attributes: ``k``, ``depth``, ``node_desc (M, 32) uint8``, ``parent (M,) int32``,
    ``children (M, k) int32`` (-1 = none), ``word_of_node (M,) int32`` (-1 for inner nodes),
    ``node_of_word (S,) int32``, ``node_level (M,) int32``, ``idf (S,)``, ``word_count (S,)``,
    ``residual_ones (256,)``, ``residual_total``, ``meta`` (dict).
    """

    def __init__(
        self,
        node_desc: np.ndarray,
        parent: np.ndarray,
        idf: np.ndarray,
        word_count: np.ndarray,
        residual_ones: np.ndarray,
        residual_total: int,
        meta: dict,
        bit_parents: np.ndarray | None = None,
        bit_p1: np.ndarray | None = None,
    ) -> None:
        self.node_desc = _check_descriptors(node_desc, "node descriptors")
        self.parent = np.asarray(parent, dtype=np.int32)
        self.meta = dict(meta)
        self.k = int(meta["k"])
        self.depth = int(meta["depth"])
        m = self.node_desc.shape[0]
        if self.parent.shape != (m,) or m == 0 or self.parent[0] != -1:
            raise VocabularyError("parent array must be (M,) with the root (-1) first")
        if np.any(self.parent[1:] < 0) or np.any(self.parent[1:] >= np.arange(1, m)):
            raise VocabularyError("parent array must point to earlier nodes")
        self.children = np.full((m, self.k), -1, dtype=np.int32)
        par = self.parent[1:].astype(np.int64)
        order = np.argsort(par, kind="stable")  # children in slot order = node order
        sp = par[order]
        rank = np.arange(sp.size) - np.searchsorted(sp, sp, side="left")
        if rank.size and rank.max() >= self.k:
            raise VocabularyError(f"a node has more than k={self.k} children")
        self.children[sp, rank] = order + 1
        slot = np.bincount(par, minlength=m)
        self.node_level = np.zeros(m, dtype=np.int32)
        for _ in range(self.depth + 1):  # parents precede children: converges in depth steps
            self.node_level[1:] = self.node_level[par] + 1
        if m > 1 and self.node_level.max() > self.depth:
            raise VocabularyError(f"tree deeper than depth={self.depth}")
        leaves = np.flatnonzero(slot == 0)
        self.node_of_word = leaves.astype(np.int32)
        self.word_of_node = np.full(m, -1, dtype=np.int32)
        self.word_of_node[leaves] = np.arange(leaves.size, dtype=np.int32)
        self.idf = np.asarray(idf, dtype=np.float64)
        self.word_count = np.asarray(word_count, dtype=np.int64)
        self.residual_ones = np.asarray(residual_ones, dtype=np.int64)
        self.residual_total = int(residual_total)
        if self.idf.shape != (leaves.size,) or self.word_count.shape != (leaves.size,):
            raise VocabularyError("idf / word_count must have one entry per word")
        if self.residual_ones.shape != (256,):
            raise VocabularyError("residual_ones must be (256,)")
        self._desc64 = self.node_desc.view(np.uint64)
        # Lookup tables: for every inner node its children's descriptors (k, 4) uint64 and a
        # distance penalty (k,) for empty slots, so a descent level is one gather per query.
        inner = np.flatnonzero(self.children[:, 0] >= 0)
        self._inner_row = np.full(m, -1, dtype=np.int32)
        self._inner_row[inner] = np.arange(inner.size, dtype=np.int32)
        ch_inner = self.children[inner]
        self._child_desc64 = self._desc64[np.maximum(ch_inner, 0)]  # (I, k, 4)
        self._child_penalty = np.where(ch_inner >= 0, 0, 1 << 20).astype(np.int32)
        self._child_ids = ch_inner
        self._fingerprint: int | None = None
        if bit_parents is None or bit_p1 is None:
            bit_parents = np.full((256, 0), -1, dtype=np.int16)
            bit_p1 = np.full((256, 1), 0.5)
        self.bit_parents = np.asarray(bit_parents, dtype=np.int16)
        # stored as float32 in files: round here too so trained == saved-and-loaded
        self.bit_p1 = np.asarray(bit_p1, dtype=np.float32).astype(np.float64)
        n_par = self.bit_parents.shape[1] if self.bit_parents.ndim == 2 else -1
        if self.bit_parents.shape[0] != 256 or self.bit_p1.shape != (256, 1 << max(n_par, 0)):
            raise VocabularyError("bit_parents must be (256, P) and bit_p1 (256, 2**P)")
        if np.any(self.bit_parents >= np.arange(256)[:, None]) or np.any(self.bit_parents < -1):
            raise VocabularyError("bit_parents must name earlier bits (or -1)")

    # ------------------------------------------------------------------ properties
    @property
    def n_words(self) -> int:
        return int(self.node_of_word.size)

    @property
    def words(self) -> np.ndarray:
        """Word descriptors ``(S, 32) uint8``."""
        return self.node_desc[self.node_of_word]

    # ------------------------------------------------------------------ lookup
    def lookup(self, descriptors: np.ndarray, chunk: int = 16384) -> np.ndarray:
        """Word ids ``(N,) int32`` of ``descriptors (N, 32) uint8`` by vectorised descent."""
        return self.node_of_word_lookup(descriptors, chunk)[1]

    def node_of_word_lookup(
        self, descriptors: np.ndarray, chunk: int = 16384
    ) -> tuple[np.ndarray, np.ndarray]:
        """(leaf node ids (N,), word ids (N,)) of descriptors."""
        d = _check_descriptors(descriptors)
        out = np.empty(d.shape[0], dtype=np.int32)
        for s in range(0, d.shape[0], chunk):
            out[s : s + chunk] = self._descend(d[s : s + chunk].view(np.uint64))
        return out, self.word_of_node[out]

    def _descend(self, d64: np.ndarray) -> np.ndarray:
        cur = np.zeros(d64.shape[0], dtype=np.int32)
        idx = np.arange(d64.shape[0])
        for _ in range(self.depth + 1):
            rows = self._inner_row[cur[idx]]
            keep = rows >= 0
            if not keep.all():
                idx, rows = idx[keep], rows[keep]
            if idx.size == 0:
                break
            c = np.bitwise_count(d64[idx, None, :] ^ self._child_desc64[rows])  # (n, k, 4) u8
            # per-word counts are <= 64, so pairs fit in uint8; the total needs more
            dist = (c[:, :, 0] + c[:, :, 1]).astype(np.int32)
            dist += c[:, :, 2] + c[:, :, 3]
            dist += self._child_penalty[rows]
            cur[idx] = self._child_ids[rows, np.argmin(dist, axis=1)]
        return cur

    def lookup_bruteforce_descent(self, descriptor: np.ndarray) -> int:
        """Reference (slow, per descriptor) descent; equals :meth:`lookup` by definition."""
        node = 0
        while self.children[node, 0] >= 0:
            best, best_d = -1, 1 << 20
            for c in self.children[node]:
                if c < 0:
                    continue
                dd = int(np.unpackbits(self.node_desc[c] ^ descriptor).sum())
                if dd < best_d:
                    best, best_d = int(c), dd
            node = best
        return int(self.word_of_node[node])

    def ancestor_at_level(self, words: np.ndarray | Sequence[int], level: int) -> np.ndarray:
        """Direct index: node id ``(N,)`` of each word's ancestor at ``level`` (0 = root).

        Words shallower than ``level`` map to themselves (their leaf node)."""
        node = self.node_of_word[np.asarray(words, dtype=np.int64)].copy()
        for _ in range(self.depth + 1):
            deeper = self.node_level[node] > level
            if not deeper.any():
                break
            node[deeper] = self.parent[node[deeper]]
        return node

    # ------------------------------------------------------------------ bag of words
    def bow(self, descriptors: np.ndarray) -> BowVector:
        """tf-idf bag-of-words vector of one image's descriptors, L1-normalised."""
        return self.bow_from_words(self.lookup(descriptors))

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        words = np.asarray(words, dtype=np.int64)
        if words.size == 0:
            return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float64))
        uniq, counts = np.unique(words, return_counts=True)
        w = counts / words.size * self.idf[uniq]
        total = w.sum()
        if total > 0:
            w = w / total
        keep = w > 0
        return BowVector(uniq[keep].astype(np.int32), w[keep])

    @staticmethod
    def score(a: BowVector, b: BowVector) -> float:
        """DBoW2 L1 score in [0, 1]: ``1 - 0.5 * |a - b|_1`` for L1-normalised vectors."""
        _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
        va, vb = a.weights[ia], b.weights[ib]
        return float(0.5 * np.sum(np.abs(va) + np.abs(vb) - np.abs(va - vb)))

    # ------------------------------------------------------------------ training
    @classmethod
    def train(
        cls,
        images_descriptors: Sequence[np.ndarray],
        config: VocabularyTrainingConfig = VocabularyTrainingConfig(),
        trained_on: str = "",
    ) -> Vocabulary:
        """Train from per-image descriptor arrays ``[(N_i, 32) uint8, ...]``."""
        if config.k < 2 or config.depth < 1:
            raise VocabularyError(f"need k >= 2 and depth >= 1, got k={config.k}")
        per_image = [
            _check_descriptors(d, f"image {i} descriptors")
            for i, d in enumerate(images_descriptors)
        ]
        desc = np.concatenate(per_image) if per_image else np.zeros((0, 32), np.uint8)
        if desc.shape[0] == 0:
            raise VocabularyError("no training descriptors")
        rng = np.random.default_rng(config.seed)
        bits = np.unpackbits(desc, axis=1)
        node_desc = [np.packbits(bits.sum(0) * 2 >= desc.shape[0])]
        parent = [-1]
        frontier = [(0, np.arange(desc.shape[0]))]  # (node, member indices)
        leaf_members: dict[int, np.ndarray] = {}
        for level in range(config.depth):
            nxt = []
            for node, members in frontier:
                sub = desc[members]
                uniq = np.unique(sub, axis=0)
                if uniq.shape[0] <= config.k:
                    if uniq.shape[0] == 1 and level > 0:
                        leaf_members[node] = members
                        continue
                    centres = uniq
                    labels = np.argmin(hamming_matrix(sub, centres), axis=1)
                else:
                    centres, labels = _kmajority(
                        sub, bits[members], config.k, rng, config.max_iterations
                    )
                for j in range(centres.shape[0]):
                    child = len(node_desc)
                    node_desc.append(centres[j])
                    parent.append(node)
                    nxt.append((child, members[labels == j]))
            frontier = nxt
            log.info("level %d: %d nodes", level + 1, len(frontier))
        for node, members in frontier:
            leaf_members[node] = members
        # Nodes were appended level by level: breadth-first, parents before children.
        node_desc_a = np.stack(node_desc)
        parent_a = np.asarray(parent, dtype=np.int32)
        meta = {
            "format": FORMAT,
            "k": config.k,
            "depth": config.depth,
            "trained_on": trained_on,
            "n_descriptors": int(desc.shape[0]),
            "n_images": len(per_image),
            "seed": config.seed,
        }
        m = node_desc_a.shape[0]
        is_leaf = np.ones(m, dtype=bool)
        is_leaf[parent_a[1:]] = False
        leaves = np.flatnonzero(is_leaf)
        # Training statistics via the same lookup the users will run.
        tmp = cls(
            node_desc_a,
            parent_a,
            np.zeros(leaves.size),
            np.zeros(leaves.size, np.int64),
            np.zeros(256, np.int64),
            0,
            meta,
        )
        words = tmp.lookup(desc)
        word_count = np.bincount(words, minlength=leaves.size)
        n_img = np.zeros(leaves.size, dtype=np.int64)
        for d in per_image:
            if d.shape[0]:
                n_img[np.unique(tmp.lookup(d))] += 1
        idf = np.log(len(per_image) / np.maximum(n_img, 1))
        residual = np.unpackbits(desc ^ tmp.words[words], axis=1)
        meta["n_words"] = int(leaves.size)
        meta["n_nodes"] = int(m)
        parents, p1 = fit_bit_context_model(
            desc, n_parents=config.bit_context_parents, seed=config.seed
        )
        return cls(
            node_desc_a,
            parent_a,
            idf,
            word_count,
            residual.sum(0),
            desc.shape[0],
            meta,
            parents,
            p1,
        )

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Write the vocabulary as a compressed ``.npz`` (see module docstring)."""
        with open(path, "wb") as fh:
            np.savez_compressed(
                fh,
                node_desc=self.node_desc,
                parent=self.parent,
                idf=self.idf,
                word_count=self.word_count,
                residual_ones=self.residual_ones,
                residual_total=np.int64(self.residual_total),
                bit_parents=self.bit_parents,
                bit_p1=self.bit_p1.astype(np.float32),
                meta=np.array(json.dumps(self.meta, sort_keys=True)),
            )

    @classmethod
    def load(cls, path: str | Path = DEFAULT_VOCABULARY_PATH) -> Vocabulary:
        """Read a vocabulary written by :meth:`save`; raises VocabularyError naming the file."""
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                if meta.get("format") != FORMAT:
                    raise VocabularyError(f"{path}: not a {FORMAT} file")
                return cls(
                    z["node_desc"],
                    z["parent"],
                    z["idf"],
                    z["word_count"],
                    z["residual_ones"],
                    int(z["residual_total"]),
                    meta,
                    z["bit_parents"],
                    z["bit_p1"],
                )
        except VocabularyError as exc:
            raise VocabularyError(f"{path}: {exc}") from exc
        except (OSError, KeyError, ValueError) as exc:
            raise VocabularyError(f"{path}: cannot read vocabulary ({exc})") from exc

    def fingerprint(self) -> int:
        """A 32-bit checksum of the tree, so coder and decoder can check they share it."""
        import zlib

        if self._fingerprint is None:  # the tree is immutable: compute once
            self._fingerprint = zlib.crc32(self.node_desc.tobytes() + self.parent.tobytes())
        return self._fingerprint
