"""Feature codec: bit-exact round trips for every mode, state handling, hostile input."""

from __future__ import annotations

import contextlib
import struct
import zlib

import cv2
import numpy as np
import pytest
import skimage.data
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.codec import (
    CodecConfig,
    CodecError,
    CodecUsageError,
    FeatureDecoder,
    FeatureEncoder,
    KeyframeFeatures,
    NonKeyframeFeatures,
    quantise_uv,
)
from common.vocabulary import Vocabulary

CFG = CodecConfig()


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def orb_kf() -> KeyframeFeatures:
    img = np.asarray(skimage.data.camera(), dtype=np.uint8)[:480]
    orb = cv2.ORB_create(nfeatures=400, scaleFactor=1.2, nlevels=8)
    kps, desc = orb.detectAndCompute(img, None)
    return KeyframeFeatures.from_cv(kps, desc).canonical()


def pair(vocab):
    return FeatureEncoder(vocab), FeatureDecoder(vocab)


def roundtrip(enc, dec, frame):
    payload = (
        enc.encode_keyframe(frame)
        if isinstance(frame, KeyframeFeatures)
        else (enc.encode_non_keyframe(frame))
    )
    out = dec.decode(payload)
    assert type(out) is type(frame)
    assert out.equals(frame)
    return payload


def random_kf(rng, n, n_prev=0, cfg=CFG) -> KeyframeFeatures:
    lev = rng.integers(0, cfg.n_levels, n)
    kp = np.zeros((n, 4), np.int32)
    for i, lv in enumerate(lev):
        w, h = cfg.level_size(int(lv))
        kp[i] = [rng.integers(0, w), rng.integers(0, h), lv, rng.integers(0, cfg.angle_bins)]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    links = rng.integers(-1, n_prev, n) if n_prev else np.full(n, -1)
    return KeyframeFeatures(kp, desc, links).canonical()


def test_orb_keyframe_roundtrip_and_cost(vocab, orb_kf):
    enc, dec = pair(vocab)
    payload = roundtrip(enc, dec, orb_kf)
    assert 8 * len(payload) / len(orb_kf) < 256 + 40  # well below raw 256-bit descriptor + kp
    assert set(enc.last_bits) >= {"keypoint", "word", "residual"}


def test_inter_coding_against_previous_descriptor(vocab, orb_kf):
    enc = FeatureEncoder(vocab, CodecConfig(carry_track_descriptors=False))
    dec = FeatureDecoder(vocab)
    roundtrip(enc, dec, orb_kf)
    # Same features again, each continuing its own track, a few bits flipped: inter wins.
    rng = np.random.default_rng(0)
    desc = orb_kf.descriptors.copy()
    flips = rng.integers(0, 256, size=len(orb_kf))
    desc[np.arange(len(orb_kf)), flips // 8] ^= (1 << (flips % 8)).astype(np.uint8)
    kf2 = KeyframeFeatures(orb_kf.keypoints, desc, np.arange(len(orb_kf)))
    assert kf2.is_canonical()
    payload = roundtrip(enc, dec, kf2)
    assert 8 * len(payload) / len(kf2) < 100
    assert enc.last_bits.get("word", 0.0) < 0.1 * len(kf2)  # words are not sent for inter


def test_continued_tracks_carry_their_descriptor(vocab, orb_kf):
    """Default: a keyframe feature continuing a track with a descriptor and having that very
    descriptor costs a flag and no descriptor bits; one whose descriptor changed is coded
    against the track's (inter or intra), new features as before; all decode exactly."""
    from common.codec.frames import HEADER, KIND_KEYFRAME_CARRY

    enc, dec = pair(vocab)
    roundtrip(enc, dec, orb_kf)
    n = len(orb_kf)
    rng = np.random.default_rng(5)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)  # fresh descriptors, unlike the track's
    links = np.where(np.arange(n) % 2 == 0, np.arange(n), -1)  # every other feature continues
    carried = np.arange(n) % 4 == 0  # half of those keep the track's descriptor
    desc[carried] = orb_kf.descriptors[carried]
    changed = (links >= 0) & ~carried  # the other half: a few bits flipped
    flips = rng.integers(0, 256, size=n)
    desc[changed] = orb_kf.descriptors[changed]
    desc[np.flatnonzero(changed), flips[changed] // 8] ^= (1 << (flips[changed] % 8)).astype(
        np.uint8
    )
    kf2 = KeyframeFeatures(orb_kf.keypoints, desc, links)
    assert kf2.is_canonical()
    payload = roundtrip(enc, dec, kf2)
    assert HEADER.unpack(payload[: HEADER.size])[1] & 0xF == KIND_KEYFRAME_CARRY
    # The same frame without carrying: every continued feature pays its residual.
    enc_b = FeatureEncoder(vocab, CodecConfig(carry_track_descriptors=False))
    enc_b.encode_keyframe(orb_kf)
    plain = enc_b.encode_keyframe(kf2)
    assert 8 * (len(plain) - len(payload)) > 0.5 * carried.sum() * 8  # > 8 bits a carried one


def test_tracks_predicted_from_their_last_step(vocab, orb_kf):
    """Kind 5 (default): tracks moving each at their own steady speed (parallax) cost fewer
    bits than one affine flow for all (kind 2), and both decode bit-exactly; a frame where
    the last steps do not help falls back to the affine flow (the encoder's flag)."""
    from common.codec.frames import HEADER, KIND_NON_KEYFRAME, KIND_NON_KEYFRAME_VELOCITY

    rng = np.random.default_rng(6)
    n = len(orb_kf)
    speed = rng.uniform(-3.0, 3.0, (n, 2))  # px per frame, one per track (depth)
    sizes = {}
    for velocity in (True, False):
        cfg = CodecConfig(track_velocity=velocity)
        enc, dec = FeatureEncoder(vocab, cfg), FeatureDecoder(vocab)
        roundtrip(enc, dec, orb_kf)
        uv, lev, total = orb_kf.uv(), orb_kf.keypoints[:, 2].astype(float), 0
        for k in range(6):
            uv = quantise_uv(uv + speed + rng.normal(0, 0.05, uv.shape))
            nkf = NonKeyframeFeatures(np.ones(n, bool), np.c_[uv, lev])
            payload = roundtrip(enc, dec, nkf)
            kind = HEADER.unpack(payload[: HEADER.size])[1] & 0xF
            assert kind == (KIND_NON_KEYFRAME_VELOCITY if velocity else KIND_NON_KEYFRAME)
            total += len(payload) if k else 0  # the first step has no last step yet
        # a jump of every track against its last step: still exact
        roundtrip(
            enc,
            dec,
            NonKeyframeFeatures(np.ones(n, bool), np.c_[quantise_uv(uv - 40 * speed), lev]),
        )
        sizes[velocity] = total
    assert sizes[True] < 0.7 * sizes[False], sizes


def test_empty_and_single_feature_frames(vocab):
    rng = np.random.default_rng(1)
    enc, dec = pair(vocab)
    roundtrip(enc, dec, random_kf(rng, 0))
    roundtrip(enc, dec, NonKeyframeFeatures(np.zeros(0, bool), np.zeros((0, 3))))
    roundtrip(enc, dec, random_kf(rng, 1))
    roundtrip(enc, dec, NonKeyframeFeatures(np.ones(1, bool), [[12.25, 7.5, 0]]))
    roundtrip(enc, dec, random_kf(rng, 1, n_prev=1))


def test_all_levels_angles_and_borders(vocab):
    rng = np.random.default_rng(2)
    rows = []
    for lv in range(CFG.n_levels):
        w, h = CFG.level_size(lv)
        for x, y in [(0, 0), (w - 1, h - 1), (0, h - 1), (w - 1, 0)]:
            rows.append([x, y, lv, rng.integers(0, 32)])
    for a in range(32):
        rows.append([100 + a, 50, 0, a])
    kp = np.array(rows, np.int32)
    desc = rng.integers(0, 256, (len(rows), 32), dtype=np.uint8)
    kf = KeyframeFeatures(kp, desc, np.full(len(rows), -1)).canonical()
    enc, dec = pair(vocab)
    roundtrip(enc, dec, kf)
    # Non-keyframe keypoints at the grid's extremes, every level, new tracks at borders.
    n = len(kf)
    surv = np.ones(n, bool)
    uv = kf.uv()
    uv[:4] = [[0, 0], [751.75, 479.75], [-10.5, 3.25], [760.0, 490.0]]
    kp_nkf = np.concatenate([quantise_uv(uv), kf.keypoints[:, 2:3]], axis=1)
    new = np.array([[0.0, 0.0, 7], [751.75, 479.75, 0], [0.25, 479.5, 3]])
    nkf = NonKeyframeFeatures(surv, np.concatenate([kp_nkf, new]))
    roundtrip(enc, dec, nkf)


def test_sequence_with_losses_new_tracks_and_relinks(vocab, orb_kf):
    rng = np.random.default_rng(3)
    enc, dec = pair(vocab)
    roundtrip(enc, dec, orb_kf)
    uv = orb_kf.uv()
    lev = orb_kf.keypoints[:, 2].astype(float)
    for _ in range(4):
        surv = rng.random(uv.shape[0]) > 0.1
        uv = quantise_uv(uv[surv] + [1.3, -0.7] + rng.normal(0, 0.3, (surv.sum(), 2)))
        lev = lev[surv]
        new_uv = quantise_uv(rng.uniform([0, 0], [751, 479], (5, 2)))
        kp = np.concatenate([np.c_[uv, lev], np.c_[new_uv, rng.integers(0, 8, 5)]])
        roundtrip(enc, dec, NonKeyframeFeatures(surv, kp))
        uv, lev = kp[:, :2], kp[:, 2]
    # All tracks lost.
    roundtrip(enc, dec, NonKeyframeFeatures(np.zeros(uv.shape[0], bool), np.zeros((0, 3))))
    # Keyframe continuing tracks of a non-keyframe with new tracks, then levels that change.
    roundtrip(enc, dec, NonKeyframeFeatures(np.zeros(0, bool), [[5.0, 6.0, 2], [9.0, 9.0, 1]]))
    kf = random_kf(rng, 30, n_prev=2)
    roundtrip(enc, dec, kf)
    kp = np.c_[quantise_uv(kf.uv()), (kf.keypoints[:, 2] + 1) % 8]
    roundtrip(enc, dec, NonKeyframeFeatures(np.ones(len(kf), bool), kp))
    assert enc.state.seq == dec.state.seq == 9
    assert np.array_equal(enc.state.tracks_q, dec.state.tracks_q)


def test_encoder_rejects_misuse(vocab):
    rng = np.random.default_rng(4)
    enc = FeatureEncoder(vocab)
    kf = random_kf(rng, 20)
    shuffled = KeyframeFeatures(kf.keypoints[::-1], kf.descriptors[::-1], kf.links)
    with pytest.raises(CodecUsageError, match="canonical"):
        enc.encode_keyframe(shuffled)
    with pytest.raises(CodecUsageError, match="links"):
        enc.encode_keyframe(KeyframeFeatures(kf.keypoints, kf.descriptors, np.full(20, 3)))
    bad = kf.keypoints.copy()
    bad[-1, 0] = 10_000
    with pytest.raises(CodecUsageError, match="outside"):
        enc.encode_keyframe(KeyframeFeatures(bad, kf.descriptors, kf.links).canonical())
    enc.encode_keyframe(kf)
    with pytest.raises(CodecUsageError, match="grid"):
        enc.encode_non_keyframe(
            NonKeyframeFeatures(np.ones(20, bool), np.c_[kf.uv() + 0.1, np.zeros(20)])
        )
    with pytest.raises(CodecUsageError, match="entries"):
        enc.encode_non_keyframe(NonKeyframeFeatures(np.ones(3, bool), np.zeros((3, 3))))
    with pytest.raises(CodecUsageError):
        KeyframeFeatures(kf.keypoints, kf.descriptors.astype(np.int16), kf.links)


def test_out_of_order_and_foreign_vocabulary(vocab, orb_kf, tmp_path):
    enc, dec = pair(vocab)
    p0 = enc.encode_keyframe(orb_kf)
    p1 = enc.encode_non_keyframe(
        NonKeyframeFeatures(
            np.ones(len(orb_kf), bool), np.c_[quantise_uv(orb_kf.uv()), orb_kf.keypoints[:, 2]]
        )
    )
    with pytest.raises(CodecError, match="out of order"):
        dec.decode(p1)
    dec.decode(p0)
    dec.decode(p1)
    other = Vocabulary(
        vocab.node_desc[:1],
        np.array([-1]),
        np.zeros(1),
        np.ones(1),
        np.zeros(256),
        0,
        {"k": 10, "depth": 4},
    )
    with pytest.raises(CodecError, match="vocabulary"):
        FeatureDecoder(other).decode(p0)


@pytest.fixture(scope="module")
def stream(vocab, orb_kf):
    enc = FeatureEncoder(vocab)
    p0 = enc.encode_keyframe(orb_kf)
    kp = np.c_[quantise_uv(orb_kf.uv() + 0.5), orb_kf.keypoints[:, 2]]
    p1 = enc.encode_non_keyframe(NonKeyframeFeatures(np.ones(len(orb_kf), bool), kp))
    return p0, p1


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_corrupted_or_truncated_payload_raises_codec_error(vocab, stream, data):
    which = data.draw(st.sampled_from([0, 1]))
    payload = bytearray(stream[which])
    dec = FeatureDecoder(vocab)
    if which == 1:
        dec.decode(stream[0])
    before = dec.state.copy()
    action = data.draw(st.sampled_from(["flip", "truncate", "extend"]))
    if action == "flip":
        i = data.draw(st.integers(0, len(payload) - 1))
        payload[i] ^= data.draw(st.integers(1, 255))
    elif action == "truncate":
        payload = payload[: data.draw(st.integers(0, len(payload) - 1))]
    else:
        payload += data.draw(st.binary(min_size=1, max_size=8))
    with pytest.raises(CodecError):
        dec.decode(bytes(payload))
    assert dec.state.seq == before.seq
    assert np.array_equal(dec.state.tracks_q, before.tracks_q)
    assert np.array_equal(dec.state.descriptors.ones, before.descriptors.ones)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(body=st.binary(min_size=0, max_size=600), kind=st.sampled_from([1, 2, 3, 4, 5, 6]))
def test_garbage_body_with_valid_header_never_crashes(vocab, stream, body, kind):
    """Bypassing the CRC: the parser itself must fail cleanly (CodecError) or decode."""
    dec = FeatureDecoder(vocab)
    dec.decode(stream[0])
    header = bytearray(stream[1][:6])
    header[1] = (header[1] & 0xF0) | kind
    try:
        out = dec.decode_unchecked(bytes(header) + body)
    except CodecError:
        return
    assert isinstance(out, (KeyframeFeatures, NonKeyframeFeatures))


def test_standalone_keyframe(vocab, orb_kf):
    from common.codec import decode_standalone_keyframe, encode_standalone_keyframe

    linked = KeyframeFeatures(orb_kf.keypoints, orb_kf.descriptors, np.zeros(len(orb_kf)))
    payload = encode_standalone_keyframe(vocab, linked)
    out = decode_standalone_keyframe(vocab, payload)
    assert np.array_equal(out.descriptors, orb_kf.descriptors)
    assert np.all(out.links == -1)
    assert decode_standalone_keyframe(vocab, payload).equals(out)  # no hidden state


def test_a_standalone_keyframe_carries_descriptors_of_the_previous_one(vocab, orb_kf):
    """Kind 6: features whose descriptor the receiver's previous keyframe holds send its row
    instead; decoded, they are links with zero descriptors until fill_carried; a row the
    previous keyframe does not have is refused by name."""
    from common.codec import decode_standalone_keyframe, encode_standalone_keyframe, fill_carried
    from common.codec.frames import HEADER, KIND_STANDALONE_CARRY

    n = len(orb_kf)
    rng = np.random.default_rng(7)
    previous = rng.integers(0, 256, (n + 50, 32), dtype=np.uint8)
    carried = np.where(np.arange(n) % 3 == 0, np.arange(n) + 10, -1)
    desc = orb_kf.descriptors.copy()
    desc[carried >= 0] = previous[carried[carried >= 0]]
    kf = KeyframeFeatures(orb_kf.keypoints, desc, np.full(n, -1))
    whole = encode_standalone_keyframe(vocab, kf)
    payload = encode_standalone_keyframe(vocab, kf, carried=carried)
    assert HEADER.unpack(payload[: HEADER.size])[1] & 0xF == KIND_STANDALONE_CARRY
    assert len(payload) < 0.75 * len(whole)  # a third of the features: ~no descriptor bits
    out = decode_standalone_keyframe(vocab, payload)
    assert np.array_equal(out.links, carried)
    assert not out.descriptors[carried >= 0].any()
    assert fill_carried(out, previous).equals(kf)
    with pytest.raises(CodecError, match="carries row"):
        fill_carried(out, previous[:20])
    # nothing carried: the plain standalone kind
    assert encode_standalone_keyframe(vocab, kf, carried=np.full(n, -1)) == whole


def test_a_standalone_keyframe_is_one_block_that_leaves_the_tables_alone(vocab, orb_kf):
    """Kind 3: the same descriptor bits as one adaptive block of the stream's coder, read by
    a decoder whose tables it does not change, and a keyframe of the stream's kind (1)
    still decodes (recordings made before kind 3)."""
    from common.codec import FeatureDecoder, FeatureEncoder, encode_standalone_keyframe
    from common.codec.frames import HEADER, KIND_KEYFRAME, KIND_STANDALONE_KEYFRAME
    from common.codec.types import CodecConfig

    plain = KeyframeFeatures(orb_kf.keypoints, orb_kf.descriptors, np.full(len(orb_kf), -1))
    payload = encode_standalone_keyframe(vocab, plain)
    assert HEADER.unpack(payload[: HEADER.size])[1] & 0xF == KIND_STANDALONE_KEYFRAME
    one_block = CodecConfig(descriptor_block=len(orb_kf))
    stream = FeatureEncoder(vocab, one_block)
    same = stream.encode_keyframe(plain)
    assert HEADER.unpack(same[: HEADER.size])[1] & 0xF == KIND_KEYFRAME
    assert payload[HEADER.size : -4] == same[HEADER.size : -4]  # the same coded body
    dec = FeatureDecoder(vocab)
    ones = dec.state.descriptors.ones.copy()
    assert np.array_equal(dec.decode(payload).descriptors, orb_kf.descriptors)
    assert np.array_equal(dec.state.descriptors.ones, ones)  # tables untouched
    old_kind = FeatureDecoder(vocab, one_block).decode(same)
    assert np.array_equal(old_kind.descriptors, orb_kf.descriptors)


def test_detached_decoding_leaves_the_decoder_at_its_state(vocab, orb_kf):
    """Keyframes each coded by a fresh encoder, decoded by one decoder in turn (a corrupt
    one among them): each as a fresh decoder decodes it, and the tables end as they began."""
    n = len(orb_kf.keypoints[::2])
    half = KeyframeFeatures(orb_kf.keypoints[::2], orb_kf.descriptors[::2], np.full(n, -1))
    payloads = [FeatureEncoder(vocab, CFG).encode_keyframe(kf) for kf in (orb_kf, half, orb_kf)]
    dec = FeatureDecoder(vocab, CFG)
    ones, total = dec.state.descriptors.ones.copy(), dec.state.descriptors.total.copy()
    # cut in the descriptors, with a valid checksum: garbage or an error, after updating
    # the tables either way
    body = payloads[1][: len(payloads[1]) * 3 // 4]
    with contextlib.suppress(CodecError):
        dec.decode_detached(body + struct.pack("<I", zlib.crc32(body)))
    for p in payloads:
        out = dec.decode_detached(p)
        assert out.equals(FeatureDecoder(vocab, CFG).decode(p))
    assert dec.state.seq == 0
    assert np.array_equal(dec.state.descriptors.ones, ones)
    assert np.array_equal(dec.state.descriptors.total, total)
    # A decoder that kept the first keyframe's state would not decode the others alike.
    kept = FeatureDecoder(vocab, CFG)
    kept.decode(payloads[0])
    assert not np.array_equal(kept.state.descriptors.total, total)
