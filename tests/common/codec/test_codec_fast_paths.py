"""The codec's speed shortcuts give exactly what the plain definitions give."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from common.codec import CodecConfig, FeatureDecoder, FeatureEncoder, KeyframeFeatures
from common.codec import keypoints as kpc
from common.codec.descriptors import DescriptorCoder
from common.codec.entropy import BitWriter
from common.vocabulary import Vocabulary

CFG = CodecConfig()


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def orb_kf() -> KeyframeFeatures:
    img = np.asarray(skimage.data.camera(), dtype=np.uint8)[:480]
    orb = cv2.ORB_create(nfeatures=600, scaleFactor=1.2, nlevels=8)
    kps, desc = orb.detectAndCompute(img, None)
    return KeyframeFeatures.from_cv(kps, desc).canonical()


def _tracks(rng: np.random.Generator, n: int, spread: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions on a coarse grid (many equal distances) and levels 0..3."""
    return rng.integers(0, spread, (n, 2)) * 8, rng.integers(0, 4, n)


@pytest.mark.parametrize("seed", range(4))
def test_link_ranks_per_level_equal_the_definition(seed):
    rng = np.random.default_rng(seed)
    pred, tracks_lev = _tracks(rng, 300, 12)
    q, lev = _tracks(rng, 200, 12)
    tgt = rng.integers(0, 300, 200)
    tgt[:50] = np.flatnonzero(tracks_lev == 0)[:1]  # many queries, one target
    ranks = kpc._link_ranks(q, lev, pred, tracks_lev, tgt)
    assert np.array_equal(ranks, kpc._ranks_full(q, lev, pred, tracks_lev, tgt))
    assert np.any(tracks_lev[tgt] != lev)  # the other-level branch was exercised
    assert np.array_equal(kpc._links_of_ranks(q, lev, pred, tracks_lev, ranks), tgt)


def test_link_ranks_fall_back_for_huge_predictions():
    rng = np.random.default_rng(7)
    pred, tracks_lev = _tracks(rng, 50, 6)
    pred[0] = [1 << 40, -(1 << 40)]  # beyond the per-level shortcut's range
    q, lev = _tracks(rng, 30, 6)
    tgt = rng.integers(0, 50, 30)
    ranks = kpc._link_ranks(q, lev, pred, tracks_lev, tgt)
    assert np.array_equal(ranks, kpc._ranks_full(q, lev, pred, tracks_lev, tgt))
    assert np.array_equal(kpc._links_of_ranks(q, lev, pred, tracks_lev, ranks), tgt)


def test_plane_groups_cover_every_plane_with_parents_outside(vocab):
    coder = DescriptorCoder(vocab, 256)
    starts = [a for a, _, _, _ in coder._groups]
    ends = [b for _, b, _, _ in coder._groups]
    assert starts[0] == 0 and ends[-1] == 256 and starts[1:] == ends[:-1]
    par = vocab.bit_parents.astype(np.int64)
    for a, b, _, _ in coder._groups:
        assert np.all(par[a:b] < a)  # contexts known before the group is decoded
    assert len(coder._groups) < 256  # the point of grouping


def test_failed_keyframe_encode_leaves_tables_untouched(vocab, orb_kf, monkeypatch):
    cfg = CodecConfig(descriptor_block=128)
    enc = FeatureEncoder(vocab, cfg)
    enc.encode_keyframe(orb_kf)
    before = enc.state.copy()
    seen = {"words": 0, "changed": False}
    original = BitWriter.put_categorical

    def failing(self, symbols, probs, part):
        if part == "word":
            seen["words"] += 1
            if seen["words"] == 3:  # two descriptor blocks have updated the tables
                seen["changed"] = not np.array_equal(
                    enc.state.descriptors.total, before.descriptors.total
                )
                raise RuntimeError("injected")
        return original(self, symbols, probs, part)

    monkeypatch.setattr(BitWriter, "put_categorical", failing)
    with pytest.raises(RuntimeError, match="injected"):
        enc.encode_keyframe(orb_kf)
    monkeypatch.setattr(BitWriter, "put_categorical", original)
    assert seen["changed"]  # the tables are updated in place ...
    # ... and rolled back
    assert np.array_equal(enc.state.descriptors.ones, before.descriptors.ones)
    assert np.array_equal(enc.state.descriptors.total, before.descriptors.total)
    assert np.array_equal(enc.state.descriptors.word_counts, before.descriptors.word_counts)
    assert enc.state.seq == before.seq
    # the stream goes on as if the failed call never happened
    fresh, dec = FeatureEncoder(vocab, cfg), FeatureDecoder(vocab, cfg)
    assert dec.decode(fresh.encode_keyframe(orb_kf)).equals(orb_kf)
    again = KeyframeFeatures(orb_kf.keypoints, orb_kf.descriptors, np.arange(len(orb_kf)))
    payload = enc.encode_keyframe(again)
    assert payload == fresh.encode_keyframe(again)
    assert dec.decode(payload).equals(again)


def test_roundtrip_without_bit_context_model(orb_kf):
    """A vocabulary without a bit model (P = 0): one plane group, no context products."""
    full = Vocabulary.load()
    flat = Vocabulary(
        full.node_desc,
        full.parent,
        full.idf,
        full.word_count,
        full.residual_ones,
        full.residual_total,
        full.meta,
    )
    enc, dec = FeatureEncoder(flat), FeatureDecoder(flat)
    for kf in (
        orb_kf,
        KeyframeFeatures(orb_kf.keypoints, orb_kf.descriptors, np.arange(len(orb_kf))),
    ):
        assert dec.decode(enc.encode_keyframe(kf)).equals(kf)


def test_failed_keyframe_decode_leaves_tables_untouched(vocab, orb_kf, monkeypatch):
    from common.codec import CodecError
    from common.codec.entropy import BitReader

    cfg = CodecConfig(descriptor_block=128)
    enc, dec = FeatureEncoder(vocab, cfg), FeatureDecoder(vocab, cfg)
    dec.decode(enc.encode_keyframe(orb_kf))
    payload = enc.encode_keyframe(orb_kf)
    before = dec.state.copy()
    seen = {"words": 0}
    original = BitReader.get_categorical

    def failing(self, probs, n=None):
        if np.ndim(probs) == 1 and np.size(probs) == vocab.n_words:
            seen["words"] += 1
            if seen["words"] == 3:
                raise CodecError("injected")
        return original(self, probs, n)

    monkeypatch.setattr(BitReader, "get_categorical", failing)
    with pytest.raises(CodecError, match="injected"):
        dec.decode(payload)
    monkeypatch.setattr(BitReader, "get_categorical", original)
    assert np.array_equal(dec.state.descriptors.ones, before.descriptors.ones)
    assert np.array_equal(dec.state.descriptors.total, before.descriptors.total)
    assert np.array_equal(dec.state.descriptors.word_counts, before.descriptors.word_counts)
    assert dec.decode(payload).equals(orb_kf)  # and the same payload now decodes


def _best_scale_by_scan(values: np.ndarray, signed: bool) -> int:
    from common.codec.entropy import N_SCALES, geometric_cost, signed_cost

    mean = float(np.mean(np.abs(values)))
    centre = int(np.clip(np.round(4 * (np.log2(max(mean, 0.125)) + 3)), 0, N_SCALES - 1))
    best, best_cost = centre, np.inf
    for i in range(max(0, centre - 6), min(N_SCALES, centre + 7)):
        cost = (signed_cost if signed else geometric_cost)(values, i)
        if cost < best_cost:
            best, best_cost = i, cost
    return best


def test_best_scale_index_equals_a_scan_over_candidates():
    from common.codec.entropy import best_scale_index

    rng = np.random.default_rng(3)
    for _ in range(300):
        v = rng.laplace(0, 10 ** rng.uniform(-1, 4), int(rng.integers(1, 200)))
        v = v.round().astype(np.int64)
        v[0] = 10**9 if rng.random() < 0.1 else v[0]  # escapes
        assert best_scale_index(v, True) == _best_scale_by_scan(v, True)
        assert best_scale_index(np.abs(v), False) == _best_scale_by_scan(np.abs(v), False)
