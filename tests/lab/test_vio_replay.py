"""The edge VIO on the real pipeline's data: a freshly rendered 10 s synthetic robot through the
robot front end, the codecs and the edge's decoding (lab.vio_replay)."""

from __future__ import annotations

import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, generate_dataset
from lab.vio_replay import decode_sequence, load_decoded, run_vio, save_decoded, score
from services.edge.vio.types import TrackingStatus


@pytest.mark.slow
def test_vio_replay_rendered_robot_initialises_and_tracks(tmp_path):
    cfg = SynthConfig(robots=1, seconds=10.0, seed=7, progress=False, contact_sheet=False)
    generate_dataset(tmp_path / "synth", cfg)
    seq = EurocSequence(tmp_path / "synth" / "robot0")
    frames = decode_sequence(seq.root)
    assert len(frames) == len(seq)
    # The cache round-trips exactly.
    save_decoded(tmp_path / "decoded.npz", frames)
    again = load_decoded(tmp_path / "decoded.npz")
    k = next(i for i, f in enumerate(frames) if f.obs.is_keyframe)
    np.testing.assert_array_equal(again[k].obs.track_ids, frames[k].obs.track_ids)
    np.testing.assert_array_equal(again[k].obs.descriptors, frames[k].obs.descriptors)
    np.testing.assert_array_equal(again[-1].accel, frames[-1].accel)

    results = run_vio(again, seq.cam0, seq.imu)
    s = score(results, seq.groundtruth)
    assert not any(r.status is TrackingStatus.LOST for r in results)
    assert s.maps == 1
    assert s.first_tracking_s < 5.0  # VI-initialised within 5 s of a hovering start
    assert s.tracked > 0.5 * s.frames
    assert s.ate_sim3_m < 0.03
    assert s.ate_se3_m < 0.15
    assert abs(s.scale_error) < 0.10
