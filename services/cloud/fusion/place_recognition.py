"""Place recognition: bag-of-words keyframe database and loop-candidate detection.

Bag-of-words vectors come straight from the visual word ids that arrive inside the coded
keyframes (no second descriptor pass): ``tf = count / N`` times the vocabulary's ``idf``,
L1-normalised (DBoW2's TF_IDF weighting with L1 norm). Two vectors are compared with DBoW2's
L1 score ``1 - 0.5 |a - b|_1`` which for non-negative L1-normalised vectors equals
``sum_w min(a_w, b_w)`` — the form the inverted index accumulates.

The inverted index is an append-only word-sorted structure of ``(word, keyframe, weight)``
entries (a CSR matrix words × keyframes held as three arrays) plus a small unsorted tail of at
most ``merge_min`` entries (scanned with ``np.isin``) that is merged into the sorted arrays
when full (one O(n) ``np.insert``); a query gathers the posting lists of its words with one
vectorised range expansion and accumulates with ``np.bincount``.

Detection follows ORB-SLAM's ``LoopClosing::DetectLoop`` / ``KeyFrameDatabase::
DetectLoopCandidates`` (Mur-Artal & Tardós 2017, after Gálvez-López & Tardós 2012, DBoW2):
the lowest score between the query and its covisible keyframes is the acceptance threshold;
candidates must share ≥ 80 % of the best candidate's common words; scores are accumulated
over each candidate's covisible group; groups below 75 % of the best are dropped; a candidate
is accepted once its covisibility group has overlapped the candidates of ``min_consistency``
consecutive keyframes of the query's agent. Like ORB-SLAM3, the best candidates that are not
consistent yet are verified at once too (``early_candidates``), and accepted when the query's
covisible keyframes see the candidate's map points where the verified pose puts them.
Intra- and inter-robot candidates are treated alike; the query's own covisible and recent
keyframes are excluded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from common.errors import RecslamError
from services.cloud.atlas.atlas import Atlas
from services.cloud.config import PlaceRecognitionConfig

log = logging.getLogger(__name__)


class PlaceRecognitionError(RecslamError):
    """Bad word ids, unknown keyframe or bad idf table."""


@dataclass(frozen=True, eq=False)
class BowVec:
    """Sparse bag-of-words vector: ``words (K,) int32`` sorted, ``weights (K,) float64``."""

    words: np.ndarray
    weights: np.ndarray


def bow_vector(word_ids: np.ndarray, idf: np.ndarray) -> BowVec:
    """tf-idf vector (L1-normalised) of one keyframe's word ids ``(N,)`` against ``idf (S,)``."""
    w = np.asarray(word_ids, dtype=np.int64).ravel()
    w = w[w >= 0]
    if w.size and int(w.max()) >= idf.shape[0]:
        raise PlaceRecognitionError(f"word id {int(w.max())} outside vocabulary of {idf.size}")
    if w.size == 0:
        return BowVec(np.zeros(0, np.int32), np.zeros(0))
    uniq, counts = np.unique(w, return_counts=True)
    weights = counts / w.size * idf[uniq]
    total = weights.sum()
    keep = weights > 0
    if total > 0:
        weights = weights / total
    return BowVec(uniq[keep].astype(np.int32), weights[keep])


def l1_score(a: BowVec, b: BowVec) -> float:
    """DBoW2 L1 score in [0, 1] of two L1-normalised vectors."""
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


@dataclass(frozen=True, eq=False)
class QueryResult:
    """Keyframes sharing at least one word with a query: ``keys (M,)``, ``scores (M,)`` (L1
    score), ``common_words (M,)``, plus ``agents (M,)`` and ``timestamps (M,)``."""

    keys: np.ndarray
    scores: np.ndarray
    common_words: np.ndarray
    agents: np.ndarray
    timestamps: np.ndarray


class KeyframeDatabase:
    """Inverted-index BoW database, vocabulary-agnostic: give it the ``idf (S,)`` weights."""

    def __init__(self, idf: np.ndarray, merge_min: int = 1 << 16) -> None:
        idf = np.asarray(idf, dtype=np.float64).ravel()
        if idf.size == 0 or not np.all(np.isfinite(idf)) or np.any(idf < 0):
            raise PlaceRecognitionError("idf must be a non-empty finite non-negative vector")
        self.idf = idf
        self._merge_min = merge_min
        self._index_of: dict[int, int] = {}
        self._keys = np.zeros(0, np.int64)
        self._agents = np.zeros(0, np.int64)
        self._times = np.zeros(0, np.float64)
        self._active = np.zeros(0, bool)
        self._n = 0
        self._vectors: list[BowVec] = []
        # Sorted main index (CSR over words).
        self._m_kf = np.zeros(0, np.int32)
        self._m_w = np.zeros(0, np.float32)
        self._m_words = np.zeros(0, np.int32)
        self._indptr = np.zeros(idf.size + 1, np.int64)
        # Unsorted tail.
        self._t_words: list[np.ndarray] = []
        self._t_kf: list[np.ndarray] = []
        self._t_w: list[np.ndarray] = []
        self._t_size = 0

    def __len__(self) -> int:
        return int(self._active[: self._n].sum())

    def __contains__(self, key: int) -> bool:
        i = self._index_of.get(int(key))
        return i is not None and bool(self._active[i])

    def _grow(self) -> None:
        cap = max(1024, 2 * self._keys.size)
        for name in ("_keys", "_agents", "_times", "_active"):
            old = getattr(self, name)
            new = np.zeros(cap, old.dtype)
            new[: old.size] = old
            setattr(self, name, new)

    def add(self, key: int, word_ids: np.ndarray, agent_id: int, timestamp: float) -> BowVec:
        """Insert keyframe ``key`` (word ids ``(N,)``); returns its vector."""
        key = int(key)
        if key in self._index_of:
            raise PlaceRecognitionError(f"keyframe {key} already in the database")
        vec = bow_vector(word_ids, self.idf)
        if self._n == self._keys.size:
            self._grow()
        i = self._n
        self._n += 1
        self._index_of[key] = i
        self._keys[i], self._agents[i], self._times[i] = key, agent_id, timestamp
        self._active[i] = True
        self._vectors.append(vec)
        self._t_words.append(vec.words)
        self._t_kf.append(np.full(vec.words.size, i, np.int32))
        self._t_w.append(vec.weights.astype(np.float32))
        self._t_size += vec.words.size
        if self._t_size >= self._merge_min:
            self._merge_tail()
        return vec

    def remove(self, key: int) -> None:
        """Deactivate a keyframe (it is never returned again)."""
        i = self._index_of.get(int(key))
        if i is not None:
            self._active[i] = False

    def vector(self, key: int) -> BowVec:
        i = self._index_of.get(int(key))
        if i is None:
            raise PlaceRecognitionError(f"keyframe {key} is not in the database")
        return self._vectors[i]

    def _merge_tail(self) -> None:
        if not self._t_size:
            return
        tw = np.concatenate(self._t_words)
        tk = np.concatenate(self._t_kf)
        tv = np.concatenate(self._t_w)
        order = np.argsort(tw, kind="stable")
        tw, tk, tv = tw[order], tk[order], tv[order]
        pos = np.searchsorted(self._m_words, tw, side="right")
        self._m_words = np.insert(self._m_words, pos, tw)
        self._m_kf = np.insert(self._m_kf, pos, tk)
        self._m_w = np.insert(self._m_w, pos, tv)
        counts = np.bincount(self._m_words, minlength=self.idf.size)
        self._indptr = np.concatenate([[0], np.cumsum(counts)])
        self._t_words, self._t_kf, self._t_w, self._t_size = [], [], [], 0

    def query(self, vec: BowVec) -> QueryResult:
        """Every active keyframe sharing a word with ``vec``, with its L1 score."""
        n = self._n
        score = np.zeros(n)
        common = np.zeros(n, np.int64)
        if vec.words.size:
            starts = self._indptr[vec.words]
            lens = self._indptr[vec.words + 1] - starts
            total = int(lens.sum())
            if total:
                offs = np.cumsum(lens) - lens
                idx = np.arange(total) + np.repeat(starts - offs, lens)
                kf = self._m_kf[idx]
                contrib = np.minimum(np.repeat(vec.weights, lens), self._m_w[idx])
                score += np.bincount(kf, contrib, minlength=n)
                common += np.bincount(kf, minlength=n)
            if self._t_size:
                tw = np.concatenate(self._t_words)
                hit = np.flatnonzero(np.isin(tw, vec.words))
                if hit.size:
                    tk = np.concatenate(self._t_kf)[hit]
                    tv = np.concatenate(self._t_w)[hit]
                    qw = vec.weights[np.searchsorted(vec.words, tw[hit])]
                    score += np.bincount(tk, np.minimum(qw, tv), minlength=n)
                    common += np.bincount(tk, minlength=n)
        sel = np.flatnonzero((common > 0) & self._active[:n])
        return QueryResult(
            keys=self._keys[sel].copy(),
            scores=score[sel],
            common_words=common[sel],
            agents=self._agents[sel].copy(),
            timestamps=self._times[sel].copy(),
        )


@dataclass(frozen=True)
class LoopCandidate:
    """A place-recognition candidate for ``query_key`` to verify; ``consistency``: the
    consecutive queries of its agent whose candidates overlapped its group (this one
    included)."""

    query_key: int
    candidate_key: int
    score: float
    group_score: float
    consistency: int
    inter_agent: bool

    def early(self, config: PlaceRecognitionConfig) -> bool:
        """Not yet consistent over ``min_consistency`` queries: accepted only with the
        covisibility check (:func:`services.cloud.fusion.verification.covisible_agreement`)."""
        return self.consistency < config.min_consistency


class PlaceRecognizer:
    """Loop / merge candidate detection over a :class:`KeyframeDatabase` and an :class:`Atlas`.

    Call :meth:`detect` for each new keyframe (before or after adding it to the database; the
    query itself is never returned), then :meth:`add` it.
    """

    def __init__(self, database: KeyframeDatabase, config: PlaceRecognitionConfig) -> None:
        self.db = database
        self.config = config
        # Per query agent: consistent groups of the previous query, (keys, count).
        self._groups: dict[int, list[tuple[frozenset[int], int]]] = {}
        self.shed_early = False  # True: no early candidates (the cloud is overloaded)

    def add(self, atlas: Atlas, key: int) -> None:
        kf = atlas.keyframe(key)
        self.db.add(key, kf.word_ids[~kf.virtual], kf.agent_id, kf.timestamp)

    def candidates(self, atlas: Atlas, key: int) -> list[tuple[int, float, float]]:
        """Best keyframe of each surviving covisibility group: ``[(key, score, group_score)]``
        before the consistency test, best first."""
        cfg = self.config
        kf = atlas.keyframe(key)
        vec = (
            self.db.vector(key)
            if key in self.db
            else bow_vector(kf.word_ids[~kf.virtual], self.db.idf)
        )
        covis = [c for c, _ in atlas.covisible(key)]
        min_score = cfg.min_score_floor
        scored = [l1_score(vec, self.db.vector(c)) for c in covis if c in self.db]
        if scored:
            min_score = max(min_score, min(scored))
        res = self.db.query(vec)
        ok = res.keys != key
        if cfg.exclude_covisible and covis:
            ok &= ~np.isin(res.keys, np.asarray(covis, np.int64))
        ok &= ~(
            (res.agents == kf.agent_id)
            & (np.abs(res.timestamps - kf.timestamp) < cfg.recent_window_s)
        )
        if not ok.any():
            return []
        max_common = int(res.common_words[ok].max())
        ok &= res.common_words >= cfg.min_common_words_ratio * max_common
        ok &= res.scores >= min_score
        if not ok.any():
            return []
        cand = dict(zip(res.keys[ok].tolist(), res.scores[ok].tolist(), strict=True))
        groups = []
        for c, s in cand.items():
            best_key, best_s, acc = c, s, s
            for nb in atlas.best_covisible(c, cfg.group_size):
                sn = cand.get(nb)
                if sn is not None:
                    acc += sn
                    if sn > best_s:
                        best_key, best_s = nb, sn
            groups.append((acc, best_s, best_key))
        best_acc = max(g[0] for g in groups)
        out: dict[int, tuple[float, float]] = {}
        for acc, s, k in sorted(groups, reverse=True):
            if acc >= cfg.group_score_ratio * best_acc and k not in out:
                out[k] = (s, acc)
        return [(k, s, acc) for k, (s, acc) in out.items()]

    def detect(self, atlas: Atlas, key: int) -> list[LoopCandidate]:
        """Candidates for keyframe ``key`` to verify: first those consistent over
        ``min_consistency`` consecutive queries (at most ``max_candidates``), then up to
        ``early_candidates`` of the best others (:meth:`LoopCandidate.early`), which need the
        covisibility check after verification; none while :attr:`shed_early` (an overloaded
        cloud, :class:`services.cloud.core.CloudCore`)."""
        cfg = self.config
        n_early = 0 if self.shed_early else cfg.early_candidates
        agent = atlas.keyframe(key).agent_id
        found = self.candidates(atlas, key)
        previous = self._groups.get(agent, [])
        current: list[tuple[frozenset[int], int]] = []
        accepted: list[LoopCandidate] = []
        early: list[LoopCandidate] = []
        for ckey, score, acc in found:
            group = frozenset([ckey, *atlas.best_covisible(ckey, 2 * cfg.group_size)])
            count = 1 + max((n for g, n in previous if g & group), default=0)
            current.append((group, count))
            inter = atlas.keyframe(ckey).agent_id != agent
            cand = LoopCandidate(key, ckey, score, acc, count, inter)
            if count >= cfg.min_consistency:
                if len(accepted) < cfg.max_candidates:
                    accepted.append(cand)
            elif len(early) < n_early:
                early.append(cand)
        self._groups[agent] = current
        accepted += early
        if accepted:
            log.debug("query %d: %d candidates (%d early)", key, len(accepted), len(early))
        return accepted

    def reset_consistency(self, agent_id: int) -> None:
        """Forget the consistent groups of an agent (after a loop was closed for it)."""
        self._groups.pop(agent_id, None)
