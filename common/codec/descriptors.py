"""Keyframe descriptor coding: visual word + XOR residual, or XOR against the track's last
descriptor (inter), with an adaptive context model of the residual bits.

Residual model. Bit ``j`` of a residual ``r = b XOR ref`` (``b`` the descriptor, ``ref`` the
word or the previous descriptor) is coded with probability ``P(r_j = 1 | c)`` where the
context ``c = (b_{π_1(j)}, ..., b_{π_P(j)}, ref_j)`` holds ``P`` earlier bits of the same
descriptor (``π`` fitted on training data and stored in the vocabulary, see
``common.vocabulary.fit_bit_context_model``) and the reference bit. ORB's bit tests share
pixels, so these contexts are informative. Bits are coded plane by plane (bit 0 of every
feature of a block, then bit 1, ...) so the decoder knows every context before it needs
it. Probabilities are adaptive: counts start from the vocabulary's prior (weight
``prior_weight`` samples) and are updated after every block of ``descriptor_block``
features and kept across keyframes (per-robot state). Intra and inter residuals have
separate tables.

Mode choice. A feature whose track already carries a descriptor may be coded inter; the
encoder picks the cheaper of intra (word + residual) and inter (residual only) under the
current tables, and sends the choice with an adaptive binary flag. Intra words use an
adaptive categorical that starts from the vocabulary's training word frequencies.

Speed. The tables are addressed through flat indices ``(mode * 256 + j) * 2**(P+1) + ctx``
into 1-D views; the encoder codes a whole block's residual planes with one range-coder
call; the decoder's unavoidable per-plane loop (a plane's contexts need the earlier planes)
does a handful of numpy operations on ``(P, m)`` / ``(m,)`` arrays per plane. Updates are
``np.add.at`` on the flat views (sequential float32 adds, as before) and can be recorded in
an undo journal so callers can roll a failed frame back without copying the 8 MB tables.
The vocabulary-derived prior tables and word descriptors are computed once per vocabulary.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from common.codec.entropy import P_MIN, BitReader, BitWriter
from common.codec.errors import CodecError
from common.vocabulary import Vocabulary

INTRA, INTER = 0, 1
_LO, _HI = np.float32(P_MIN), np.float32(1.0 - P_MIN)  # exact in float32 (2**-12)

# Journal of table updates: (flat indices, old ones, old total) per block, restored in
# reverse order by :func:`rollback`.
UndoLog = list[tuple[np.ndarray, np.ndarray, np.ndarray]]

# Read-only templates derived from a vocabulary (its prior tables, its word descriptors),
# computed once per Vocabulary object and dropped with it.
_VocabCache = dict[tuple, object]
_TEMPLATES: weakref.WeakKeyDictionary[Vocabulary, _VocabCache] = weakref.WeakKeyDictionary()


def _vocab_cache(vocab: Vocabulary) -> _VocabCache:
    cache = _TEMPLATES.get(vocab)
    if cache is None:
        cache = {}
        _TEMPLATES[vocab] = cache
    return cache


@dataclass
class DescriptorModelState:
    """Adaptive counts ``ones/total (2, 256, 2**(P+1)) float32`` (mode, bit, context), the
    mode flag counts ``[inter, total]`` and the word counts ``(S,)`` (the vocabulary's
    training frequencies scaled to ``word_prior_weight`` pseudo-samples, plus every intra
    word coded). float32 keeps the per-robot state at 8 MB for P=10; both ends do the same
    float32 operations, so their probabilities are identical."""

    ones: np.ndarray
    total: np.ndarray
    mode_counts: np.ndarray
    word_counts: np.ndarray

    @classmethod
    def initial(
        cls, vocab: Vocabulary, prior_weight: float, word_prior_weight: float = 5000.0
    ) -> DescriptorModelState:
        cache = _vocab_cache(vocab)
        key = ("initial", float(prior_weight), float(word_prior_weight))
        tpl = cache.get(key)
        if not isinstance(tpl, DescriptorModelState):
            tpl = cls._build_initial(vocab, prior_weight, word_prior_weight)
            cache[key] = tpl
        return tpl.copy()

    @classmethod
    def _build_initial(
        cls, vocab: Vocabulary, prior_weight: float, word_prior_weight: float
    ) -> DescriptorModelState:
        p1 = vocab.bit_p1  # P(b_j = 1 | parents)
        nctx = 2 * p1.shape[1]
        ones = np.zeros((2, 256, nctx), dtype=np.float32)
        total = np.full((2, 256, nctx), prior_weight, dtype=np.float32)
        # intra: P(r=1 | ref=0) = P(b=1), P(r=1 | ref=1) = P(b=0)
        ones[INTRA, :, 0::2] = prior_weight * p1
        ones[INTRA, :, 1::2] = prior_weight * (1.0 - p1)
        ones[INTER] = prior_weight * 0.15  # residuals against a matched descriptor are sparse
        wc = vocab.word_count.astype(np.float64) + 0.5
        word_counts = wc * (word_prior_weight / wc.sum())
        return cls(ones, total, np.array([1.0, 2.0]), word_counts)

    def copy(self) -> DescriptorModelState:
        return DescriptorModelState(
            self.ones.copy(), self.total.copy(), self.mode_counts.copy(), self.word_counts.copy()
        )

    def copy_counts(self) -> DescriptorModelState:
        """A copy that shares the (large) ``ones`` / ``total`` tables and copies the rest;
        pair it with an undo journal (see :func:`rollback`)."""
        return DescriptorModelState(
            self.ones, self.total, self.mode_counts.copy(), self.word_counts.copy()
        )


def rollback(state: DescriptorModelState, undo: UndoLog) -> None:
    """Undo the table updates recorded in ``undo`` (newest first)."""
    ones, total = state.ones.reshape(-1), state.total.reshape(-1)
    for flat, old_ones, old_total in reversed(undo):
        ones[flat] = old_ones
        total[flat] = old_total
    undo.clear()


def _count_words(state: DescriptorModelState, words: np.ndarray) -> None:
    """``word_counts[w] += (number of w in words)``, one addition per distinct word (as a
    full-size bincount would, without touching all S entries)."""
    uniq, counts = np.unique(words, return_counts=True)
    state.word_counts[uniq] += counts


class DescriptorCoder:
    """Stateless helper bound to a vocabulary; the state object is passed in."""

    def __init__(self, vocab: Vocabulary, block: int) -> None:
        self.vocab = vocab
        self.block = int(block)
        par = vocab.bit_parents.astype(np.int64)
        self.n_par = par.shape[1]
        self.parents = np.where(par < 0, 0, par)
        self.parent_valid = (par >= 0).astype(np.int64)
        self.weights = (1 << np.arange(self.n_par - 1, -1, -1)).astype(np.int64)
        # flat-index weights: 2 * context (the reference bit is the low bit), 0 for dummies
        self._w2 = (2 * self.weights[None, :] * self.parent_valid).astype(np.int64)  # (256, P)
        self._parents_z = np.where(par < 0, 256, par)  # dummies read an all-zero row
        # Decoder plane groups: runs of consecutive planes none of which has a parent inside
        # the run, so their contexts are all known once the earlier planes are decoded and
        # the run is decoded with one range-coder call (same symbol order as the encoder's).
        w2f = self._w2.astype(np.float64)
        self._groups: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        last_parent = par.max(axis=1, initial=-1).tolist()  # latest parent of each plane
        start = 0
        for j in range(1, 257):
            if j == 256 or last_parent[j] >= start:
                sel = slice(start, j)
                self._groups.append((start, j, self.parents[sel], w2f[sel, None, :]))
                start = j
        self._nctx = 2 * vocab.bit_p1.shape[1]
        self._plane_off = np.arange(256, dtype=np.int64) * self._nctx
        self._mode_off = 256 * self._nctx
        cache = _vocab_cache(vocab)
        words = cache.get(("words",))
        if not isinstance(words, np.ndarray):
            words = vocab.words
            words.setflags(write=False)
            cache[("words",)] = words
        self._words = words  # (S, 32) uint8, read-only

    # ------------------------------------------------------------------ helpers
    def _contexts_t(self, bits_t: np.ndarray) -> np.ndarray:
        """Parent part of the context, plane-major: ``(256, n) int64`` from bits ``(256, n)``
        (0/1 uint8): ``sum_q b[parent_q(j)] << (P - 1 - q)``, dummy parents count as 0."""
        n = bits_t.shape[1]
        ctx = np.zeros((256, n), dtype=np.uint16)
        if self.n_par == 0:
            return ctx.astype(np.int64)
        padded = np.zeros((257, n), dtype=np.uint16)
        padded[:256] = bits_t
        for q in range(self.n_par):
            g = padded[self._parents_z[:, q]]
            g <<= self.n_par - 1 - q
            ctx |= g
        return ctx.astype(np.int64)

    @staticmethod
    def _p1(ones: np.ndarray, total: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """Clipped float64 P(r = 1) at flat table indices (float32 division, as stored)."""
        p = ones[flat] / total[flat]
        np.maximum(p, _LO, out=p)
        np.minimum(p, _HI, out=p)
        return p.astype(np.float64)

    @staticmethod
    def _update(
        state: DescriptorModelState, flat: np.ndarray, resid: np.ndarray, undo: UndoLog | None
    ) -> None:
        ones, total = state.ones.reshape(-1), state.total.reshape(-1)
        flat = flat.ravel()
        if undo is not None:
            undo.append((flat, ones[flat], total[flat]))
        # np.compress: much faster than boolean indexing here
        np.add.at(ones, np.compress(resid.ravel().astype(bool), flat), np.float32(1.0))
        np.add.at(total, flat, np.float32(1.0))

    def _mode_p(self, state: DescriptorModelState) -> float:
        return float(np.clip(state.mode_counts[0] / state.mode_counts[1], P_MIN, 1 - P_MIN))

    # ------------------------------------------------------------------ encode
    def encode(
        self,
        w: BitWriter,
        state: DescriptorModelState,
        desc: np.ndarray,
        prev_desc: np.ndarray,
        has_prev: np.ndarray,
        undo: UndoLog | None = None,
        standalone: bool = False,
    ) -> None:
        """Code ``desc (N, 32)``; ``prev_desc (N, 32)`` valid where ``has_prev (N,)``.
        ``standalone``: all ``N`` as one block, and ``state`` is left as it was (a payload
        whose tables nothing reads after it: the same bits as one adaptive block)."""
        n = desc.shape[0]
        if n == 0:
            return
        block = max(n, 1) if standalone else self.block
        ones, total = state.ones.reshape(-1), state.total.reshape(-1)
        # plane-major (256, N) arrays: the coding order (bit 0 of every feature, then bit 1)
        bits = np.unpackbits(desc.T, axis=0)
        ctx2 = 2 * self._contexts_t(bits) + self._plane_off[:, None]  # flat index less ref
        words = self.vocab.lookup(desc)
        wbits = np.unpackbits(self._words[words].T, axis=0)
        pbits = np.unpackbits(prev_desc.T, axis=0)
        for s in range(0, n, block):
            sl = slice(s, min(n, s + block))
            b, c2, wb, hp = bits[:, sl], ctx2[:, sl], wbits[:, sl], has_prev[sl]
            wsl = words[sl]
            flat = c2 + wb  # intra
            resid = b ^ wb
            p = self._p1(ones, total, flat)
            pm = self._mode_p(state)
            word_p = state.word_counts / state.word_counts.sum()
            mode = np.zeros(b.shape[1], dtype=np.int64)
            info = None  # information content of the residual bits, if already known
            if hp.any():
                # both alternatives for every feature of the block (no column gathers);
                # per-feature sums over contiguous rows give the same floats as row-major
                pb = pbits[:, sl]
                flat_e = c2 + pb + self._mode_off
                r_inter = b ^ pb
                p_e = self._p1(ones, total, flat_e)
                bits_a = -np.log2(np.where(resid == 1, p, 1 - p))
                bits_e = -np.log2(np.where(r_inter == 1, p_e, 1 - p_e))
                cost_a = np.ascontiguousarray(bits_a.T).sum(1)
                cost_a += -np.log2(word_p[wsl]) - np.log2(1 - pm)
                cost_e = np.ascontiguousarray(bits_e.T).sum(1) - np.log2(pm)
                inter = hp & (cost_e < cost_a)
                mode[inter] = INTER
                flat = np.where(inter, flat_e, flat)
                resid = np.where(inter, r_inter, resid)
                p = np.where(inter, p_e, p)
                info = float(np.where(inter, bits_e, bits_a).sum())
            w.put_bernoulli(mode[hp], np.full(int(hp.sum()), pm), "mode")
            intra = mode == INTRA
            w.put_categorical(wsl[intra], word_p, "word")
            w.put_bernoulli(resid, p, "residual", info)
            if standalone:
                continue
            _count_words(state, wsl[intra])
            self._update(state, flat, resid, undo)
            state.mode_counts += [float((mode[hp] == INTER).sum()), float(hp.sum())]

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        r: BitReader,
        state: DescriptorModelState,
        prev_desc: np.ndarray,
        has_prev: np.ndarray,
        undo: UndoLog | None = None,
        standalone: bool = False,
    ) -> np.ndarray:
        """Inverse of :meth:`encode` (with its ``standalone``); returns descriptors
        ``(N, 32) uint8``."""
        n = prev_desc.shape[0]
        block = max(n, 1) if standalone else self.block
        out = np.zeros((n, 256), dtype=np.uint8)
        ones, total = state.ones.reshape(-1), state.total.reshape(-1)
        pbits = np.unpackbits(prev_desc, axis=1)
        n_par = self.n_par
        get_bits = r.get_bernoulli_fast
        for s in range(0, n, block):
            sl = slice(s, min(n, s + block))
            m = sl.stop - sl.start
            hp = has_prev[sl]
            pm = self._mode_p(state)
            mode = np.zeros(m, dtype=np.int64)
            mode[hp] = r.get_bernoulli(np.full(int(hp.sum()), pm))
            intra = mode == INTRA
            word_p = state.word_counts / state.word_counts.sum()
            words = r.get_categorical(word_p, int(intra.sum()))
            if words.size and (words.min() < 0 or words.max() >= self.vocab.n_words):
                raise CodecError("decoded word index out of range")
            if not standalone:
                _count_words(state, words)
            ref = pbits[sl].copy()
            ref[intra] = np.unpackbits(self._words[words], axis=1)
            ref_t = np.ascontiguousarray(ref.T).astype(np.int32)  # (256, m)
            # flat index of every (plane, feature); the context part is added plane by plane
            off = ref_t + self._plane_off[:, None] + (mode * self._mode_off)[None, :]
            # decoded bits, plane-major, as float64 for a BLAS context product (exact)
            bt = np.zeros((256, m), dtype=np.float64)
            for a, b, par_g, w_g in self._groups:
                f = off[a:b]
                if n_par:
                    f += np.matmul(w_g, bt[par_g])[:, 0, :].astype(np.int64)
                p = ones[f] / total[f]
                np.maximum(p, _LO, out=p)
                np.minimum(p, _HI, out=p)
                # float32 p is exact for constriction (it widens to float64 itself)
                bt[a:b] = get_bits(p.ravel()).reshape(b - a, m) ^ ref_t[a:b]
            bits_t = bt.astype(np.uint8)
            if not standalone:
                self._update(state, off, bits_t ^ ref_t, undo)
                state.mode_counts += [float((mode[hp] == INTER).sum()), float(hp.sum())]
            out[sl] = bits_t.T
        return np.packbits(out, axis=1)
