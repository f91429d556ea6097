"""Every frame's trajectory at the cloud: relative frame poses placed on the final keyframes."""

from __future__ import annotations

import numpy as np

from common.evaluation.trajectory import Trajectory
from common.geometry import make_T, so3_exp
from services.cloud.store.frame_trajectories import FrameTrack


def test_frames_land_on_their_keyframes_corrected_poses_and_orphans_are_left_out() -> None:
    # The keyframes as the cloud ends with them (moved by a correction after the edge sent the
    # frames): stamps in float seconds, rounded, like robot_trajectories' (a few ns off).
    T_kf = [
        make_T(so3_exp(np.array([0.0, 0.0, 0.1 * k])), np.array([k, 0.0, 1.0])) for k in range(3)
    ]
    t_kf = np.array([1_000_000_000, 2_000_000_000, 3_000_000_000], np.int64)
    kf_traj = Trajectory.from_poses(t_kf + np.array([0, 64, -64]), np.array(T_kf), "r")
    rel = make_T(so3_exp(np.array([0.02, 0.0, 0.0])), np.array([0.1, 0.0, 0.0]))
    track = FrameTrack()
    track.add("r", np.array([1_050_000_000, 2_050_000_000]), t_kf[:2], np.array([rel, rel]))
    track.add("r", np.array([2_050_000_000]), t_kf[1:2], np.array([rel]))  # a replay: no copy
    track.add("r", np.array([9_000_000_000]), np.array([8_000_000_000]), np.array([rel]))
    track.add("other", np.array([1]), np.array([0]), np.array([rel]))  # no keyframes: no file
    out = track.trajectories({"r": kf_traj})
    assert list(out) == ["r"] and track.count("r") == 3
    traj = out["r"]
    # the three keyframes and the two frames with a keyframe, in time order
    assert len(traj) == 5
    assert np.all(np.diff(traj.timestamps_ns) > 0)
    i = int(np.flatnonzero(traj.timestamps_ns == 2_050_000_000)[0])
    assert np.allclose(traj.T_world_body[i], T_kf[1] @ rel, atol=1e-9)
    assert 9_000_000_000 not in traj.timestamps_ns.tolist()  # its keyframe is not in the map
