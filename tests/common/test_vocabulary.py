"""Vocabulary tree: training determinism, lookup = descent, persistence, tf-idf scores."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from common.vocabulary import (
    Vocabulary,
    VocabularyError,
    VocabularyTrainingConfig,
    fit_bit_context_model,
)

TINY = VocabularyTrainingConfig(k=4, depth=3, max_iterations=5, seed=3, bit_context_parents=2)


@pytest.fixture(scope="module")
def orb_sets() -> list[np.ndarray]:
    orb = cv2.ORB_create(nfeatures=300, scaleFactor=1.2, nlevels=8)
    out = []
    for name in ("camera", "coins", "brick", "moon"):
        img = np.asarray(getattr(skimage.data, name)(), dtype=np.uint8)
        out.append(orb.detectAndCompute(img, None)[1])
    return out


@pytest.fixture(scope="module")
def tiny(orb_sets) -> Vocabulary:
    return Vocabulary.train(orb_sets, TINY, trained_on="test")


@pytest.fixture(scope="module")
def default_vocab() -> Vocabulary:
    return Vocabulary.load()


def test_training_is_deterministic_per_seed(orb_sets, tiny):
    again = Vocabulary.train(orb_sets, TINY, trained_on="test")
    assert np.array_equal(again.node_desc, tiny.node_desc)
    assert np.array_equal(again.parent, tiny.parent)
    assert np.array_equal(again.bit_parents, tiny.bit_parents)
    assert tiny.n_words > TINY.k  # really a tree
    assert tiny.node_level.max() <= TINY.depth
    assert np.all(tiny.children[tiny.node_of_word] == -1)


def test_save_load_identity(tmp_path, tiny):
    path = tmp_path / "v.npz"
    tiny.save(path)
    back = Vocabulary.load(path)
    for name in (
        "node_desc",
        "parent",
        "idf",
        "word_count",
        "residual_ones",
        "bit_parents",
        "bit_p1",
    ):
        assert np.array_equal(getattr(back, name), getattr(tiny, name)), name
    assert back.meta == tiny.meta
    assert back.fingerprint() == tiny.fingerprint()


def test_load_rejects_garbage(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a vocabulary")
    with pytest.raises(VocabularyError, match=r"bad\.npz"):
        Vocabulary.load(bad)
    with pytest.raises(VocabularyError, match=r"missing\.npz"):
        Vocabulary.load(tmp_path / "missing.npz")


@pytest.mark.parametrize("which", ["tiny", "default_vocab"])
def test_lookup_equals_bruteforce_descent(which, request):
    voc = request.getfixturevalue(which)
    rng = np.random.default_rng(7)
    desc = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    words = voc.lookup(desc)
    assert words.dtype == np.int32 and words.min() >= 0 and words.max() < voc.n_words
    assert [voc.lookup_bruteforce_descent(d) for d in desc] == words.tolist()


def test_training_descriptors_are_near_their_words(orb_sets, tiny):
    words = tiny.lookup(orb_sets[0])
    dist = np.unpackbits(orb_sets[0] ^ tiny.words[words], axis=1).sum(1)
    rng = np.random.default_rng(1)
    rand = rng.integers(0, 256, size=(300, 32), dtype=np.uint8)
    rdist = np.unpackbits(rand ^ tiny.words[tiny.lookup(rand)], axis=1).sum(1)
    assert dist.mean() < rdist.mean() - 20


def test_bow_scores(orb_sets, default_vocab):
    a = default_vocab.bow(orb_sets[0])
    b = default_vocab.bow(orb_sets[1])
    assert np.isclose(a.weights.sum(), 1.0)
    assert np.all(np.diff(a.words) > 0)
    assert Vocabulary.score(a, a) == pytest.approx(1.0)
    assert Vocabulary.score(a, b) < 0.5
    assert Vocabulary.score(a, b) == pytest.approx(Vocabulary.score(b, a))
    empty = default_vocab.bow(np.zeros((0, 32), np.uint8))
    assert Vocabulary.score(a, empty) == 0.0


def test_direct_index(default_vocab):
    words = np.arange(default_vocab.n_words)
    lvl1 = default_vocab.ancestor_at_level(words, 1)
    assert np.all(default_vocab.node_level[lvl1] == 1)
    assert np.all(default_vocab.parent[lvl1] == 0)
    assert np.array_equal(default_vocab.ancestor_at_level(words, 0), np.zeros_like(words))


def test_default_vocabulary_metadata(default_vocab):
    m = default_vocab.meta
    assert m["k"] == default_vocab.k and m["n_words"] == default_vocab.n_words
    assert "skimage" in m["trained_on"]
    assert default_vocab.bit_parents.shape[0] == 256


def test_bit_context_model_uses_earlier_bits():
    rng = np.random.default_rng(0)
    desc = rng.integers(0, 256, size=(500, 32), dtype=np.uint8)
    bits = np.unpackbits(desc, axis=1)
    bits[:, 9] = bits[:, 3]  # make bit 9 a copy of bit 3
    parents, p1 = fit_bit_context_model(np.packbits(bits, axis=1), n_parents=2, n_candidates=8)
    assert np.all(parents < np.arange(256)[:, None])
    assert 3 in parents[9]
    assert p1.shape == (256, 4)


def test_bad_descriptors_rejected(tiny):
    with pytest.raises(VocabularyError, match="uint8"):
        tiny.lookup(np.zeros((3, 32), np.int64))
    with pytest.raises(VocabularyError):
        Vocabulary.train([], TINY)
