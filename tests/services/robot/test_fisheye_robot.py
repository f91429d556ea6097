"""A robot with a fisheye (equidistant) camera tracks a rendered flight, and its features code
and decode bit-exactly, with no fisheye-specific code in the front end or the codec."""

from __future__ import annotations

import numpy as np
import pytest

from common.codec import FeatureDecoder, KeyframeFeatures
from common.codec.keypoints import kf_track_q
from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, generate_dataset
from common.vocabulary import Vocabulary
from services.robot.coding import FrameCoder, codec_config_for, imu_used, install_codec_grid
from services.robot.config import FrontEndConfig
from services.robot.tracker import FrontEnd

SECONDS = 3.0


@pytest.fixture(scope="module")
def fisheye_robot(tmp_path_factory) -> EurocSequence:
    out = tmp_path_factory.mktemp("fisheye")
    config = SynthConfig(
        robots=1, seconds=SECONDS, seed=5, cameras=("fisheye",), contact_sheet=False, progress=False
    )
    generate_dataset(out, config)
    return EurocSequence(out / "robot0")


@pytest.fixture(scope="module")
def run(fisheye_robot: EurocSequence):
    seq = fisheye_robot
    config = FrontEndConfig()
    cc = codec_config_for(config, seq.cam0.width, seq.cam0.height)
    fe = FrontEnd(config, seq.cam0, seq.imu)
    install_codec_grid(fe, cc)
    vocabulary = Vocabulary.load()
    coder, decoder = FrameCoder(vocabulary, cc), FeatureDecoder(vocabulary, cc)
    out = []
    for fr in seq.frames():
        chunk = imu_used(fr.imu.timestamps_ns, fr.imu.gyro, fr.imu.accel)
        tracked = fe.process(fr.image, fr.timestamp_ns, chunk)
        coded = coder.encode(tracked)
        out.append((tracked, coded, decoder.decode(coded.payload)))
    return cc, out


@pytest.mark.slow
def test_fisheye_robot_keeps_its_tracks(fisheye_robot: EurocSequence, run) -> None:
    assert fisheye_robot.cam0.model == "equidistant"
    _, out = run
    frames = [tracked for tracked, _, _ in out]
    assert len(frames) == round(SECONDS * 20) + 1
    for tracked in frames[1:]:
        assert tracked.stats.n_inliers > 700  # 794 at worst (seed 5; EuRoC cam0: 828)
        assert len(tracked) > 700
    keyframes = sum(t.is_keyframe for t in frames)
    assert 2 <= keyframes <= len(frames) / 3  # tracking carries most frames
    # Tracks persist: many of the first frame's features are still tracked a second later.
    first = set(frames[0].track_ids.tolist())
    assert len(first & set(frames[20].track_ids.tolist())) > 800  # 923


def test_fisheye_features_decode_bit_exactly(run) -> None:
    cc, out = run
    n_kf = 0
    for tracked, coded, decoded in out:
        assert type(decoded) is type(coded.features)
        assert decoded.equals(coded.features)
        rows = np.argsort(tracked.track_ids)[
            np.searchsorted(np.sort(tracked.track_ids), coded.track_ids)
        ]
        if isinstance(decoded, KeyframeFeatures):
            n_kf += 1
            assert np.array_equal(kf_track_q(decoded.keypoints, cc) / 4, tracked.keypoints[rows])
            assert tracked.descriptors is not None
            assert np.array_equal(decoded.descriptors, tracked.descriptors[rows])
    assert n_kf >= 2
