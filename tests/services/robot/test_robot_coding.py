"""Adapter from the front end's TrackedFrame to the feature codec: grids, order, checks."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from common.codec import FeatureDecoder, KeyframeFeatures
from common.codec.keypoints import kf_track_q
from common.data.euroc import EurocSequence
from common.vocabulary import Vocabulary
from services.robot.coding import (
    CodingMismatchError,
    FrameCoder,
    codec_config_for,
    imu_used,
    install_codec_grid,
    snap_orb_features,
)
from services.robot.config import (
    FrontEndConfig,
    KeyframeDecisionConfig,
    OrbConfig,
    TrackingMode,
)
from services.robot.orb_extractor import OrbExtractor
from services.robot.tracker import FrontEnd


@pytest.fixture(scope="module")
def seq(euroc_micro: Path) -> EurocSequence:
    return EurocSequence(euroc_micro)


@pytest.fixture(scope="module")
def vocabulary() -> Vocabulary:
    return Vocabulary.load()


def test_snapped_orb_lies_on_the_codec_grid(seq):
    cc = codec_config_for(FrontEndConfig(), seq.cam0.width, seq.cam0.height)
    raw = OrbExtractor(OrbConfig()).extract(seq.load_image(0))
    snapped = snap_orb_features(raw, cc)
    kf = KeyframeFeatures.from_cv(
        [
            type("K", (), {"pt": tuple(p), "octave": int(lv), "angle": float(a)})
            for p, lv, a in zip(raw.keypoints, raw.levels, raw.angles, strict=True)
        ],
        raw.descriptors,
        None,
        cc,
    )
    assert np.array_equal(snapped.keypoints, kf.uv(cc))  # the codec's float64 expression
    assert np.abs(snapped.keypoints - raw.keypoints).max() < 1e-3  # only float32 noise moved
    assert np.array_equal(snapped.descriptors, raw.descriptors)
    back = KeyframeFeatures.from_cv(
        [
            type("K", (), {"pt": tuple(p), "octave": int(lv), "angle": float(a)})
            for p, lv, a in zip(snapped.keypoints, snapped.levels, snapped.angles, strict=True)
        ],
        snapped.descriptors,
        None,
        cc,
    )
    assert np.array_equal(back.keypoints, kf.keypoints)  # grid and angle bins are stable
    # Quarter-pixel snap of the tracker (round half even) = codec's kf_track_q (half up).
    assert np.array_equal(np.round(snapped.keypoints * 4), kf_track_q(kf.keypoints, cc))


def _run(seq, vocabulary, config: FrontEndConfig, n: int):
    cc = codec_config_for(config, seq.cam0.width, seq.cam0.height)
    fe = FrontEnd(config, seq.cam0, seq.imu)
    install_codec_grid(fe, cc)
    install_codec_grid(fe, cc)  # idempotent
    coder, decoder = FrameCoder(vocabulary, cc), FeatureDecoder(vocabulary, cc)
    out = []
    for fr in seq.frames(0, n):
        chunk = imu_used(fr.imu.timestamps_ns, fr.imu.gyro, fr.imu.accel)
        tracked = fe.process(fr.image, fr.timestamp_ns, chunk)
        coded = coder.encode(tracked)
        out.append((tracked, coded, decoder.decode(coded.payload)))
    return cc, out


def test_intra_baseline_codes_every_frame_as_a_keyframe_with_links(seq, vocabulary):
    config = FrontEndConfig(keyframe=KeyframeDecisionConfig(every_frame=True))
    cc, out = _run(seq, vocabulary, config, 4)
    prev_ids = np.zeros(0, np.int64)
    for tracked, coded, decoded in out:
        assert tracked.is_keyframe and isinstance(decoded, KeyframeFeatures)
        assert decoded.equals(coded.features)
        rows = np.argsort(tracked.track_ids)[
            np.searchsorted(np.sort(tracked.track_ids), coded.track_ids)
        ]
        assert np.array_equal(kf_track_q(decoded.keypoints, cc) / 4, tracked.keypoints[rows])
        linked = decoded.links >= 0
        assert np.array_equal(coded.track_ids[linked], prev_ids[decoded.links[linked]])
        prev_ids = coded.track_ids
    assert (out[-1][2].links >= 0).sum() > 100  # consecutive frames share many tracks


def test_mismatches_are_detected(seq, vocabulary):
    _, out = _run(seq, vocabulary, FrontEndConfig(), 3)
    cc = codec_config_for(FrontEndConfig(), 752, 480)
    kf = out[0][0]
    assert kf.is_keyframe
    moved = kf.keypoints.copy()
    moved[5] += 0.25
    with pytest.raises(CodingMismatchError, match="not on the codec grid"):
        FrameCoder(vocabulary, cc).encode(dataclasses.replace(kf, keypoints=moved))
    coder = FrameCoder(vocabulary, cc)
    coder.encode(kf)
    f1 = out[1][0]
    lost = f1.survived_mask_vs_previous.copy()
    lost[np.flatnonzero(lost)[0]] = False  # the tracker says a track ended that goes on
    with pytest.raises(CodingMismatchError, match="do not match"):
        coder.encode(dataclasses.replace(f1, survived_mask_vs_previous=lost))
    # A frame left out (the uplink budget): the next is coded against the last coded one.
    assert len(coder.encode(out[2][0]).stream_ids) == len(out[2][0])
    dup = kf.track_ids.copy()
    dup[1] = dup[0]
    with pytest.raises(CodingMismatchError, match="duplicate"):
        FrameCoder(vocabulary, cc).encode(dataclasses.replace(kf, track_ids=dup))


def test_codec_config_refuses_what_it_cannot_code():
    with pytest.raises(CodingMismatchError, match="optical-flow"):
        codec_config_for(FrontEndConfig(tracking=TrackingMode.ORB_MATCHING), 752, 480)
    with pytest.raises(CodingMismatchError, match="quantisation_px"):
        codec_config_for(FrontEndConfig(quantisation_px=0.3), 752, 480)
    cc = codec_config_for(FrontEndConfig(quantisation_px=0.125), 640, 400)
    assert (cc.subpixel, cc.image_width, cc.image_height) == (8, 640, 400)


def test_intra_only_coder_sends_no_links(seq, vocabulary):
    config = FrontEndConfig(keyframe=KeyframeDecisionConfig(every_frame=True))
    cc = codec_config_for(config, seq.cam0.width, seq.cam0.height)
    fe = FrontEnd(config, seq.cam0, seq.imu)
    install_codec_grid(fe, cc)
    coder = FrameCoder(vocabulary, cc, links=False)
    decoder = FeatureDecoder(vocabulary, cc)
    for fr in seq.frames(0, 3):
        tracked = fe.process(fr.image, fr.timestamp_ns, fr.imu)
        decoded = decoder.decode(coder.encode(tracked).payload)
        assert isinstance(decoded, KeyframeFeatures) and (decoded.links == -1).all()
        assert sorted(map(bytes, decoded.descriptors)) == sorted(map(bytes, tracked.descriptors))
