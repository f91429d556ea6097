"""Stream track numbers from decoded features alone (``common.codec.tracks``)."""

import numpy as np

from common.codec import KeyframeFeatures, NonKeyframeFeatures
from common.codec.tracks import next_stream_numbers


def _kf(links: list[int]) -> KeyframeFeatures:
    n = len(links)
    kp = np.zeros((n, 4), np.int32)
    kp[:, 0] = np.arange(n)
    return KeyframeFeatures(kp, np.zeros((n, 32), np.uint8), np.array(links, np.int32))


def _nkf(survived: list[bool], n_new: int) -> NonKeyframeFeatures:
    n = int(sum(survived)) + n_new
    kp = np.zeros((n, 3))
    kp[:, 0] = np.arange(n)
    return NonKeyframeFeatures(np.array(survived), kp)


def test_first_keyframe_numbers_from_zero() -> None:
    nums, nxt = next_stream_numbers(np.zeros(0, np.int64), 0, _kf([-1, -1, -1]))
    assert nums.tolist() == [0, 1, 2] and nxt == 3
    assert not nums.flags.writeable


def test_survivors_keep_numbers_and_new_tracks_continue() -> None:
    nums, nxt = next_stream_numbers(np.array([0, 1, 2]), 3, _nkf([True, False, True], 2))
    assert nums.tolist() == [0, 2, 3, 4] and nxt == 5


def test_keyframe_links_inherit_and_fresh_features_count_on() -> None:
    prev = np.array([7, 9, 11])
    nums, nxt = next_stream_numbers(prev, 12, _kf([2, -1, 0, -1]))
    assert nums.tolist() == [11, 12, 7, 13] and nxt == 14


def test_a_sequence_never_reuses_a_number() -> None:
    rng = np.random.default_rng(0)
    nums, nxt = np.zeros(0, np.int64), 0
    seen: set[int] = set()
    for k in range(30):
        if k % 5 == 0:
            links = [int(i) if rng.random() < 0.6 else -1 for i in rng.permutation(len(nums))]
            feats = _kf(links + [-1] * 3)
        else:
            feats = _nkf(list(rng.random(len(nums)) < 0.8), int(rng.integers(0, 4)))
        before = set(nums.tolist())
        nums, nxt = next_stream_numbers(nums, nxt, feats)
        assert len(set(nums.tolist())) == len(nums)
        new = set(nums.tolist()) - before
        assert not (new & seen - before)
        seen |= set(nums.tolist())
    assert nxt == max(seen) + 1
