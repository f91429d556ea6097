"""In-process replay of the real pipeline into the VIO, with ATE against ground truth.

Rendered EuRoC-layout sequence → robot front end and codecs (:class:`RobotApp.process`) →
edge decoding (:meth:`RobotSession.decode`: stream track numbers, level-0 distorted px) →
:class:`VioManager`. No network, no edge feedback to the robot. The decoded inputs can be
cached to a ``.npz`` (:func:`save_decoded` / :func:`load_decoded`) to iterate on the VIO
without re-running the front end.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from services.edge.vio.manager import VioManager
from services.edge.vio.types import FrameObservation, FrameResult, TrackingStatus, VioConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class DecodedFrame:
    """One frame as the edge's VIO receives it: IMU since the previous frame and features."""

    imu_t_ns: np.ndarray  # (K,) int64
    gyro: np.ndarray  # (K, 3) rad/s
    accel: np.ndarray  # (K, 3) m/s²
    obs: FrameObservation


def decode_sequence(root: Path | str, seconds: float | None = None) -> list[DecodedFrame]:
    """Run the robot (front end + codecs) and the edge's decoding on the first ``seconds``
    (all if None) of the EuRoC-layout sequence at ``root``."""
    from common.data.euroc import EurocSequence
    from common.vocabulary import Vocabulary
    from services.edge.robot_session import RobotSession
    from services.robot.app import RobotApp
    from services.robot.config import FrontEndConfig

    seq = EurocSequence(root)
    vocab = Vocabulary.load()
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, vocab)
    session = RobotSession(seq.name, seq.cam0, vocab)
    ts = seq.frame_timestamps_ns
    stop = len(ts) if seconds is None else int(np.searchsorted(ts, ts[0] + seconds * 1e9))
    out = []
    for fr in seq.frames(0, stop):
        assert fr.image is not None  # frames() loads the images
        msg = app.process(fr.timestamp_ns, fr.image, fr.imu)
        item = session.decode(msg)
        assert item.obs is not None
        out.append(DecodedFrame(item.imu_t_ns, item.gyro, item.accel, item.obs))
    logger.info("%s: %d frames decoded, %d robot keyframes", seq.name, len(out), app.keyframes)
    return out


def save_decoded(path: Path | str, frames: list[DecodedFrame]) -> None:
    """Write decoded frames to a ``.npz`` (ragged arrays concatenated with offsets)."""
    n_imu = np.array([len(f.imu_t_ns) for f in frames])
    n_kp = np.array([len(f.obs.track_ids) for f in frames])
    has_desc = np.array([f.obs.descriptors is not None for f in frames])
    desc = [f.obs.descriptors for f in frames if f.obs.descriptors is not None]
    np.savez_compressed(
        path,
        n_imu=n_imu,
        n_kp=n_kp,
        has_desc=has_desc,
        t=np.array([f.obs.timestamp_ns for f in frames], np.int64),
        kf=np.array([f.obs.is_keyframe for f in frames]),
        imu_t=np.concatenate([f.imu_t_ns for f in frames]).astype(np.int64),
        gyro=np.concatenate([f.gyro for f in frames]).reshape(-1, 3),
        accel=np.concatenate([f.accel for f in frames]).reshape(-1, 3),
        ids=np.concatenate([f.obs.track_ids for f in frames]).astype(np.int64),
        uv=np.concatenate([f.obs.keypoints_px for f in frames]).reshape(-1, 2),
        levels=np.concatenate([f.obs.levels for f in frames]).astype(np.uint8),
        desc=np.concatenate(desc) if desc else np.zeros((0, 32), np.uint8),
    )


def load_decoded(path: Path | str) -> list[DecodedFrame]:
    """Read what :func:`save_decoded` wrote."""
    with np.load(path) as npz:  # read each array once (indexing an NpzFile re-reads it)
        z = {k: npz[k] for k in npz.files}
    oi = np.concatenate([[0], np.cumsum(z["n_imu"])])
    ok = np.concatenate([[0], np.cumsum(z["n_kp"])])
    out, d = [], 0
    for i in range(len(z["t"])):
        a, b = ok[i], ok[i + 1]
        desc = None
        if z["has_desc"][i]:
            desc = z["desc"][d : d + b - a]
            d += b - a
        obs = FrameObservation(
            timestamp_ns=int(z["t"][i]),
            track_ids=z["ids"][a:b],
            keypoints_px=z["uv"][a:b],
            levels=z["levels"][a:b],
            is_keyframe=bool(z["kf"][i]),
            descriptors=desc,
        )
        s = slice(oi[i], oi[i + 1])
        out.append(DecodedFrame(z["imu_t"][s], z["gyro"][s], z["accel"][s], obs))
    return out


def run_vio(
    frames: list[DecodedFrame],
    camera: CameraCalibration,
    imu: ImuCalibration,
    options: VioConfig | None = None,
    name: str = "robot",
) -> list[FrameResult]:
    """Feed every frame (IMU first) to a fresh :class:`VioManager`; the per-frame results."""
    vio = VioManager(camera, imu, options, name)
    results = []
    for f in frames:
        if len(f.imu_t_ns):
            vio.feed_imu(f.imu_t_ns, f.gyro, f.accel)
        results.append(vio.feed_frame(f.obs))
    return results


@dataclass(frozen=True)
class ReplayScore:
    """Accuracy of a replay: tracked share, maps, ATE [m] after SE(3) and Sim(3) alignment,
    Sim(3) scale error (scale - 1), over the frames tracked in the final map's metric state."""

    frames: int
    tracked: int
    maps: int
    first_tracking_s: float
    ate_se3_m: float
    ate_sim3_m: float
    scale_error: float


def score(results: list[FrameResult], groundtruth, last_map_only: bool = True) -> ReplayScore:
    """Score ``results`` against a :class:`common.data.euroc.EurocGroundTruth` (TRACKING frames of
    the last map when ``last_map_only``, else of every map, each map aligned on its own is not
    done: use it only with one map)."""
    from common.evaluation import AlignMode, AteConfig, Trajectory, compute_ate

    ok = [r for r in results if r.status is TrackingStatus.TRACKING]
    maps = len({r.map_id for r in results if r.status is not TrackingStatus.INITIALIZING} or {0})
    t0 = results[0].timestamp_ns
    first = (ok[0].timestamp_ns - t0) * 1e-9 if ok else float("nan")
    if last_map_only and ok:
        ok = [r for r in ok if r.map_id == ok[-1].map_id]
    if len(ok) < 3:
        nan = float("nan")
        return ReplayScore(len(results), len(ok), maps, first, nan, nan, nan)
    est = Trajectory.from_poses(
        np.array([r.timestamp_ns for r in ok], np.int64),
        np.stack([r.T_world_body for r in ok]),
    )
    ref = Trajectory.from_groundtruth(groundtruth)
    se3 = compute_ate(ref, est, AteConfig(align=AlignMode.SE3))
    sim3 = compute_ate(ref, est, AteConfig(align=AlignMode.SIM3))
    return ReplayScore(
        len(results),
        len(ok),
        maps,
        first,
        float(se3.stats.rmse),
        float(sim3.stats.rmse),
        float(sim3.scale_error),
    )
