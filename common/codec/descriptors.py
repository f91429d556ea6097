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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.codec.entropy import P_MIN, BitReader, BitWriter
from common.codec.errors import CodecError
from common.vocabulary import Vocabulary

INTRA, INTER = 0, 1


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

    # ------------------------------------------------------------------ helpers
    def _contexts(self, bits: np.ndarray) -> np.ndarray:
        """Parent part of the context for all planes: (n, 256) from descriptor bits (n, 256)."""
        if self.n_par == 0:
            return np.zeros(bits.shape, dtype=np.int64)
        pb = bits[:, self.parents] * self.parent_valid[None]  # (n, 256, P)
        return pb @ self.weights

    @staticmethod
    def _p1(state: DescriptorModelState, mode: np.ndarray, j, idx: np.ndarray) -> np.ndarray:
        p = (state.ones[mode, j, idx] / state.total[mode, j, idx]).astype(np.float64)
        return np.clip(p, P_MIN, 1.0 - P_MIN)

    def _update(self, state: DescriptorModelState, mode, idx, resid) -> None:
        n = mode.shape[0]
        jj = np.broadcast_to(np.arange(256), (n, 256))
        mm = np.broadcast_to(mode[:, None], (n, 256))
        np.add.at(state.ones, (mm, jj, idx), resid.astype(np.float32))
        np.add.at(state.total, (mm, jj, idx), np.float32(1.0))

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
    ) -> None:
        """Code ``desc (N, 32)``; ``prev_desc (N, 32)`` valid where ``has_prev (N,)``."""
        n = desc.shape[0]
        if n == 0:
            return
        bits = np.unpackbits(desc, axis=1).astype(np.int64)
        ctx = self._contexts(bits)
        words = self.vocab.lookup(desc)
        wbits = np.unpackbits(self.vocab.words[words], axis=1).astype(np.int64)
        pbits = np.unpackbits(prev_desc, axis=1).astype(np.int64)
        for s in range(0, n, self.block):
            sl = slice(s, min(n, s + self.block))
            m = sl.stop - sl.start
            b, c, wb, pb, hp = bits[sl], ctx[sl], wbits[sl], pbits[sl], has_prev[sl]
            jj = np.arange(256)[None, :]
            idx_intra = c * 2 + wb
            idx_inter = c * 2 + pb
            r_intra, r_inter = b ^ wb, b ^ pb
            p_a = self._p1(state, np.zeros((m, 1), np.int64), jj, idx_intra)
            p_e = self._p1(state, np.ones((m, 1), np.int64), jj, idx_inter)
            pm = self._mode_p(state)
            word_p = state.word_counts / state.word_counts.sum()
            cost_a = -np.log2(np.where(r_intra == 1, p_a, 1 - p_a)).sum(1)
            cost_a += -np.log2(word_p[words[sl]]) - np.log2(1 - pm)
            cost_e = -np.log2(np.where(r_inter == 1, p_e, 1 - p_e)).sum(1) - np.log2(pm)
            mode = np.where(hp & (cost_e < cost_a), INTER, INTRA).astype(np.int64)
            w.put_bernoulli(mode[hp], np.full(int(hp.sum()), pm), "mode")
            intra = mode == INTRA
            w.put_categorical(words[sl][intra], word_p, "word")
            state.word_counts += np.bincount(words[sl][intra], minlength=word_p.size)
            resid = np.where(intra[:, None], r_intra, r_inter)
            idx = np.where(intra[:, None], idx_intra, idx_inter)
            p = np.where(intra[:, None], p_a, p_e)
            # plane-major order: bit 0 of every feature, then bit 1, ...
            w.put_bernoulli(resid.T.ravel(), p.T.ravel(), "residual")
            self._update(state, mode, idx, resid)
            state.mode_counts += [float((mode[hp] == INTER).sum()), float(hp.sum())]

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        r: BitReader,
        state: DescriptorModelState,
        prev_desc: np.ndarray,
        has_prev: np.ndarray,
    ) -> np.ndarray:
        """Inverse of :meth:`encode`; returns descriptors ``(N, 32) uint8``."""
        n = prev_desc.shape[0]
        out = np.zeros((n, 256), dtype=np.int64)
        pbits = np.unpackbits(prev_desc, axis=1).astype(np.int64)
        for s in range(0, n, self.block):
            sl = slice(s, min(n, s + self.block))
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
            state.word_counts += np.bincount(words, minlength=word_p.size)
            ref = pbits[sl].copy()
            ref[intra] = np.unpackbits(self.vocab.words[words], axis=1)
            b = np.zeros((m, 256), dtype=np.int64)
            idx = np.zeros((m, 256), dtype=np.int64)
            resid = np.zeros((m, 256), dtype=np.int64)
            for j in range(256):
                if self.n_par:
                    pb = b[:, self.parents[j]] * self.parent_valid[j][None]
                    cj = pb @ self.weights
                else:
                    cj = np.zeros(m, dtype=np.int64)
                idx[:, j] = cj * 2 + ref[:, j]
                p = self._p1(state, mode, j, idx[:, j])
                resid[:, j] = r.get_bernoulli(p)
                b[:, j] = resid[:, j] ^ ref[:, j]
            self._update(state, mode, idx, resid)
            state.mode_counts += [float((mode[hp] == INTER).sum()), float(hp.sum())]
            out[sl] = b
        return np.packbits(out.astype(np.uint8), axis=1)
