"""A small synthetic world for the cloud's tests and benchmarks (like OpenVINS' simulator).

Landmarks lie on the walls of a rectangular room; each has a random ORB-like descriptor and a
visual word. Robots move with a gravity-aligned body (z up) and a forward-looking camera;
keyframes see the landmarks in view (projected with the radial-tangential model, pixel noise),
observed descriptors are the landmark's with a few bits flipped, and every keyframe also holds
clutter features without map points. Each agent's map frame differs from the world by a known
yaw + translation, exactly what the cloud must recover when it merges maps.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.camera import camera_model
from common.codec.frames import FeatureEncoder
from common.codec.types import CodecConfig, KeyframeFeatures
from common.data.synth.cameras import EUROC_CAM0
from common.geometry import inverse_T, make_T, so3_exp, transform_points
from common.links.edge_cloud import (
    KeyframeUpdate,
    MapPointUpdate,
    pack_keyframe_update,
    pack_map_point_update,
)
from common.vocabulary import Vocabulary
from services.cloud.atlas.atlas import Atlas, KeyframeInput, MapPointInput
from services.cloud.optimization.full_ba import FullBAProblem
from services.cloud.optimization.inertial import ImuStore, ImuTerms

# The simulated robots' body is gravity-aligned (x forward, z up), unlike EuRoC's IMU frame, so
# EuRoC's camera sits on a forward-looking mount: camera z = body x, camera x = -body y,
# camera y = -body z, 5 cm ahead of the body's origin.
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BODY_CAM = make_T(R_BODY_CAM, np.array([0.05, 0.0, 0.0]))
T_BODY_CAM.setflags(write=False)


def default_camera() -> CameraCalibration:
    """EuRoC cam0 (752×480 radial-tangential: the synthetic generator's preset,
    :data:`common.data.synth.cameras.EUROC_CAM0`) at 20 Hz on the forward-looking
    :data:`T_BODY_CAM`."""
    return EUROC_CAM0.to_calibration(T_BODY_CAM, 20.0)


def yaw_T(yaw: float, t: np.ndarray) -> np.ndarray:
    """(4, 4) rotation about z by ``yaw`` rad followed by translation ``t (3,)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    return make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), t)


@dataclass(frozen=True, eq=False)
class World:
    """Landmarks ``points (P, 3)`` world metres, ``descriptors (P, 32) uint8``, ``words (P,)``;
    ``n_words`` vocabulary size and ``idf (n_words,)``."""

    points: np.ndarray
    descriptors: np.ndarray
    words: np.ndarray
    n_words: int
    idf: np.ndarray


def make_world(
    seed: int = 0, n_points: int = 4000, size: float = 12.0, n_words: int = 20000
) -> World:
    """Landmarks on the four walls (height 0–3 m) of a ``size`` × ``size`` room centred at 0."""
    rng = np.random.default_rng(seed)
    half = size / 2
    side = rng.integers(0, 4, n_points)
    along = rng.uniform(-half, half, n_points)
    z = rng.uniform(0.0, 3.0, n_points)
    x = np.where(side == 0, half, np.where(side == 1, -half, along))
    y = np.where(side == 2, half, np.where(side == 3, -half, along))
    pts = np.stack([x, y, z], axis=1)
    desc = rng.integers(0, 256, (n_points, 32), dtype=np.uint8)
    words = rng.integers(0, n_words, n_points).astype(np.int32)
    idf = np.log(n_words / 10.0) * np.ones(n_words)
    return World(pts, desc, words, n_words, idf)


def circle_poses(
    n: int, radius: float = 2.0, height: float = 1.5, turns: float = 1.0, phase: float = 0.0
) -> np.ndarray:
    """(n, 4, 4) T_world_body on a circle, looking outwards (yaw = position angle)."""
    ang = phase + np.linspace(0.0, 2 * np.pi * turns, n, endpoint=False)
    return np.stack(
        [yaw_T(a, np.array([radius * np.cos(a), radius * np.sin(a), height])) for a in ang]
    )


def observe(
    world: World,
    cam: CameraCalibration,
    T_world_body: np.ndarray,
    rng: np.random.Generator,
    pixel_noise: float = 0.5,
    flip_bits: int = 4,
    n_clutter: int = 100,
    max_range: float = 12.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What a keyframe at ``T_world_body`` sees: (keypoints (N, 2) distorted px, levels (N,),
    descriptors (N, 32), words (N,), landmark index (N,) or -1 for clutter)."""
    T_cam_world = inverse_T(T_world_body @ cam.T_body_cam)
    p_cam = transform_points(T_cam_world, world.points)
    front = (p_cam[:, 2] > 0.3) & (np.linalg.norm(p_cam, axis=1) < max_range)
    idx = np.flatnonzero(front)
    uv = camera_model(cam).project(p_cam[idx])
    # Undistorted normalised coordinates must be in a sane range for the model to hold.
    xn = p_cam[idx, :2] / p_cam[idx, 2:3]
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] < cam.width)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < cam.height)
        & (np.abs(xn[:, 0]) < 1.0)
        & (np.abs(xn[:, 1]) < 0.8)
    )
    idx, uv = idx[inside], uv[inside] + rng.normal(0.0, pixel_noise, (int(inside.sum()), 2))
    desc = world.descriptors[idx].copy()
    if flip_bits > 0 and desc.shape[0]:
        bits = np.unpackbits(desc, axis=1)
        flip = np.argpartition(rng.random((desc.shape[0], 256)), flip_bits, axis=1)[:, :flip_bits]
        bits[np.arange(desc.shape[0])[:, None], flip] ^= 1
        desc = np.packbits(bits, axis=1)
    words = world.words[idx]
    c_uv = rng.uniform([0, 0], [cam.width, cam.height], (n_clutter, 2))
    c_desc = rng.integers(0, 256, (n_clutter, 32), dtype=np.uint8)
    c_words = rng.integers(0, world.n_words, n_clutter).astype(np.int32)
    kps = np.concatenate([uv, c_uv])
    levels = rng.integers(0, 3, len(kps)).astype(np.int16)
    return (
        kps,
        levels,
        np.concatenate([desc, c_desc]),
        np.concatenate([words, c_words]),
        np.concatenate([idx, np.full(n_clutter, -1)]),
    )


def make_session(
    world: World,
    cam: CameraCalibration,
    agent_id: int,
    T_world_body: np.ndarray,
    T_agent_world: np.ndarray,
    seed: int = 0,
    dt: float = 0.5,
    point_noise: float = 0.0,
    drift_T: np.ndarray | None = None,
    keyframe_id0: int = 0,
    t0: float = 0.0,
    track_gap: int = 3,
) -> tuple[list[KeyframeInput], list[MapPointInput]]:
    """Keyframes and map points of one agent flying ``T_world_body (K, 4, 4)``, expressed in
    the agent's map frame ``T_agent_world``.

    As in a real odometry front end, a landmark keeps its map point only while it is tracked:
    unseen for more than ``track_gap`` keyframes, it gets a new map point when seen again, so
    a revisit is *not* already closed in the map. ``landmark_of_point`` is returned implicitly
    nowhere: tests compare geometry, not ids.

    drift_T (4, 4): per-keyframe odometry error composed onto the estimated poses (the
    estimate of keyframe i is the truth with i-fold accumulated drift); None = no drift.
    """
    rng = np.random.default_rng(seed)
    kfs: list[KeyframeInput] = []
    obs: dict[int, list[tuple[int, int]]] = {}
    T_est = None
    last_seen: dict[int, int] = {}
    current: dict[int, int] = {}
    landmark: dict[int, int] = {}
    next_id = [0]
    for i, T in enumerate(T_world_body):
        kps, lv, desc, words, lm = observe(world, cam, T, rng)
        kid = keyframe_id0 + i
        if drift_T is None or T_est is None:
            T_est = T_agent_world @ T
        else:
            T_rel = inverse_T(T_world_body[i - 1]) @ T
            T_est = T_est @ T_rel @ drift_T
        mp_ids = np.full(lm.shape[0], -1, np.int64)
        for j in np.flatnonzero(lm >= 0):
            L = int(lm[j])
            if L not in last_seen or i - last_seen[L] > track_gap:
                current[L] = next_id[0]
                landmark[next_id[0]] = L
                next_id[0] += 1
            last_seen[L] = i
            mp_ids[j] = current[L]
            obs.setdefault(current[L], []).append((kid, int(j)))
        kfs.append(
            KeyframeInput(
                agent_id=agent_id,
                keyframe_id=kid,
                timestamp=t0 + i * dt,
                T_world_body=T_est,
                keypoints=kps,
                levels=lv,
                descriptors=desc,
                word_ids=words,
                map_point_ids=mp_ids,
            )
        )
    mps = []
    for mp_id, o in sorted(obs.items()):
        if len(o) < 2:
            continue
        p = transform_points(T_agent_world, world.points[landmark[mp_id]])[0]
        p = p + rng.normal(0.0, point_noise, 3) if point_noise > 0 else p
        mps.append(MapPointInput(agent_id, mp_id, p, np.array(o, np.int64)))
    # Keypoints whose landmark has fewer than two observations carry no map point.
    kept = {m.map_point_id for m in mps}
    out = []
    for k in kfs:
        ids = np.array([i if i in kept else -1 for i in k.map_point_ids.tolist()], np.int64)
        out.append(
            KeyframeInput(
                agent_id=k.agent_id,
                keyframe_id=k.keyframe_id,
                timestamp=k.timestamp,
                T_world_body=k.T_world_body,
                keypoints=k.keypoints,
                levels=k.levels,
                descriptors=k.descriptors,
                word_ids=k.word_ids,
                map_point_ids=ids,
            )
        )
    return out, mps


# ------------------------------------------------------------------ as an edge sends it
def keyframe_features(
    keypoints: np.ndarray, levels: np.ndarray, descriptors: np.ndarray, codec: CodecConfig
) -> tuple[KeyframeFeatures, np.ndarray]:
    """Snap level-0 keypoints ``(N, 2)`` with ``levels (N,)`` to the codec grid and put them in
    canonical order; returns the features and ``order (N,)`` (feature i = input order[i])."""
    lev = np.asarray(levels, np.int64)
    s = codec.level_scale(lev)
    kp = np.zeros((lev.shape[0], 4), np.int32)
    xy = np.floor(np.asarray(keypoints, np.float64) / s[:, None] + 0.5)
    for level in np.unique(lev):
        w, h = codec.level_size(int(level))
        sel = lev == level
        xy[sel, 0] = np.clip(xy[sel, 0], 0, w - 1)
        xy[sel, 1] = np.clip(xy[sel, 1], 0, h - 1)
    kp[:, :2] = xy
    kp[:, 2] = lev
    raw = KeyframeFeatures(kp, descriptors, np.full(lev.shape[0], -1, np.int32))
    order = raw.canonical_order()
    return KeyframeFeatures(kp[order], raw.descriptors[order], raw.links[order]), order


def encode_keyframe_update(
    kf: KeyframeInput,
    agent_name: str,
    vocabulary: Vocabulary,
    edge_map_id: int = 0,
    previous_keyframe_id: int = -1,
    timestamp_ns: int | None = None,
    codec: CodecConfig | None = None,
) -> tuple[KeyframeUpdate, np.ndarray]:
    """What an edge sends for ``kf``: the message and ``order (N,)``, the coded order of the
    features (coded feature i is ``kf``'s feature ``order[i]``; map point observations must
    use coded indices)."""
    cfg = codec or CodecConfig()
    feats, order = keyframe_features(kf.keypoints, kf.levels, kf.descriptors, cfg)
    payload = FeatureEncoder(vocabulary, cfg).encode_keyframe(feats)
    ts = round(kf.timestamp * 1e9) if timestamp_ns is None else int(timestamp_ns)
    msg = pack_keyframe_update(
        agent_name,
        edge_map_id,
        kf.keyframe_id,
        previous_keyframe_id,
        ts,
        kf.T_world_body,
        kf.velocity,
        kf.bias_gyro,
        kf.bias_accel,
        payload,
        kf.map_point_ids[order],
    )
    return msg, order


def encode_map_point_update(
    points: list[MapPointInput],
    agent_name: str,
    edge_map_id: int = 0,
    coded_index: dict[int, np.ndarray] | None = None,
) -> MapPointUpdate:
    """A MapPointUpdate of ``points``; ``coded_index {keyframe_id: inverse order (N,)}`` maps
    a keyframe's input feature index to its coded index (see :func:`encode_keyframe_update`)."""
    ids = np.array([p.map_point_id for p in points], np.int64)
    P = np.array([p.p_world for p in points], np.float64).reshape(-1, 3)
    rows = []
    for p in points:
        for kf_id, idx in p.observations.tolist():
            if coded_index is not None and kf_id in coded_index:
                idx = int(coded_index[kf_id][idx])
            rows.append((p.map_point_id, kf_id, idx))
    return pack_map_point_update(agent_name, edge_map_id, ids, P, np.array(rows, np.int64))


def encode_session(
    keyframes: list[KeyframeInput],
    map_points: list[MapPointInput],
    agent_name: str,
    vocabulary: Vocabulary,
    edge_map_id: int = 0,
    codec: CodecConfig | None = None,
) -> list[list[KeyframeUpdate | MapPointUpdate]]:
    """What an edge sends for one agent's session, per keyframe in order: its
    :class:`KeyframeUpdate`, then (if any) one :class:`MapPointUpdate` of the map points that
    keyframe observed first (the lowest keyframe id in a point's observations); observations
    in coded feature indices; ``codec``: the robot's feature codec (default: a 752×480
    image). For simulations (:func:`make_session`),
    tests and benchmarks."""
    coded: dict[int, KeyframeUpdate] = {}
    inv: dict[int, np.ndarray] = {}
    for k in keyframes:  # every keyframe first: observations need the coded indices
        coded[k.keyframe_id], order = encode_keyframe_update(
            k, agent_name, vocabulary, edge_map_id, codec=codec
        )
        inv[k.keyframe_id] = np.argsort(order)
    first = {m.map_point_id: int(m.observations[:, 0].min()) for m in map_points}
    out: list[list[KeyframeUpdate | MapPointUpdate]] = []
    for k in keyframes:
        msgs: list[KeyframeUpdate | MapPointUpdate] = [coded[k.keyframe_id]]
        new = [m for m in map_points if first[m.map_point_id] == k.keyframe_id]
        if new:
            msgs.append(encode_map_point_update(new, agent_name, edge_map_id, coded_index=inv))
        out.append(msgs)
    return out


# ------------------------------------------------------------------ visual-inertial maps
@dataclass(frozen=True, eq=False)
class ViCircle:
    """Ground truth of :func:`vi_circle_atlas`: keyframe poses ``T_world_body (N, 4, 4)``,
    velocities ``velocity (N, 3)`` m/s, and the IMU calibration the samples are meant with."""

    T_world_body: np.ndarray
    velocity: np.ndarray
    imu: ImuCalibration


def wavy_circle(
    t_s: np.ndarray, radius: float, omega: float, height: float, amp: float, nu: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A circle of ``radius`` at ``omega`` rad/s (yaw = position angle, body x outwards, z
    up) whose height oscillates as ``height + amp · sin(nu · t)``, at times ``t_s (K,)``:
    ``(T_world_body (K, 4, 4), velocity (K, 3), gyro (K, 3), accel (K, 3))``, the last two
    the exact IMU (gravity 9.81 along -z)."""
    a = omega * t_s
    z = height + amp * np.sin(nu * t_s)
    T = np.stack(
        [
            yaw_T(ai, np.array([radius * np.cos(ai), radius * np.sin(ai), zi]))
            for ai, zi in zip(a, z, strict=True)
        ]
    )
    vel = np.stack(
        [-radius * omega * np.sin(a), radius * omega * np.cos(a), amp * nu * np.cos(nu * t_s)],
        axis=1,
    )
    gyro = np.tile([0.0, 0.0, omega], (t_s.size, 1))
    accel = np.stack(
        [
            np.full(t_s.size, -radius * omega**2),
            np.zeros(t_s.size),
            9.81 - amp * nu**2 * np.sin(nu * t_s),
        ],
        axis=1,
    )
    return T, vel, gyro, accel


def vi_circle_atlas(
    n_keyframes: int,
    n_landmarks: int = 600,
    scale: float = 1.0,
    seed: int = 0,
    dt: float = 0.25,
    radius: float = 2.0,
    omega: float = 0.5,
    pose_noise: float = 0.01,
    amp: float = 0.3,
    nu: float = 2.0,
) -> tuple[Atlas, ImuStore, ViCircle]:
    """A single-agent visual-inertial map (agent 0) on :func:`wavy_circle` (height 1.5 m)
    with its exact 200 Hz IMU (keyframes every ``dt`` s; the height's oscillation makes the
    scale observable apart from an accelerometer bias), started off the truth as a map whose
    scale drifted: keyframe positions and points scaled by ``scale`` about the first
    keyframe, then the poses (not the first) perturbed by ``pose_noise`` m / rad per axis.
    Returns the atlas, the IMU store holding the samples, and the truth."""
    cam = default_camera()
    world = make_world(seed, n_points=n_landmarks)
    t_kf = dt * np.arange(n_keyframes)
    poses, vel, _, _ = wavy_circle(t_kf, radius, omega, 1.5, amp, nu)
    kfs, mps = make_session(world, cam, 0, poses, np.eye(4), seed=seed + 1, dt=dt)
    atlas = Atlas()
    for kf in kfs:
        atlas.add_keyframe(kf)
    for m in mps:
        atlas.add_map_point(m)
    store = ImuStore()
    t_imu = np.arange(0, round((n_keyframes - 1) * dt * 1e9) + 5_000_000, 5_000_000)
    _, _, gyro, accel = wavy_circle(t_imu * 1e-9, radius, omega, 1.5, amp, nu)
    store.add(0, t_imu, gyro, accel)
    rng = np.random.default_rng(seed + 2)
    keys = atlas.keyframe_keys()
    p0 = poses[0, :3, 3]
    new = {}
    for i, k in enumerate(keys):
        T = atlas.T_map_body(k).copy()
        T[:3, 3] = p0 + scale * (T[:3, 3] - p0)
        if i:
            D = make_T(so3_exp(rng.normal(0.0, pose_noise, 3)), rng.normal(0.0, pose_noise, 3))
            T = T @ D
        new[k] = T
    pk = np.array(atlas.map_point_keys(), np.int64)
    P = p0 + scale * (atlas.map_point_positions(pk) - p0)
    atlas.set_keyframe_poses(new)
    atlas.set_map_point_positions(dict(zip(pk.tolist(), P, strict=True)))
    return atlas, store, ViCircle(poses, vel, EUROC_IMU)


def map_scale(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """Least-squares scale of estimated keyframe positions (N, 4, 4) relative to the truth's,
    both about their first keyframe (1.0: metric)."""
    d_est = T_est[:, :3, 3] - T_est[0, :3, 3]
    d_true = T_true[:, :3, 3] - T_true[0, :3, 3]
    return float(np.sum(d_est * d_true) / np.sum(d_true * d_true))


def problem_prefix(problem: FullBAProblem, n: int) -> FullBAProblem:
    """The full-BA problem of the first ``n`` keyframes of ``problem`` (its observations,
    edges and IMU pairs among them; points seen by fewer than two of them dropped): the map
    as it was earlier, to feed an incremental solver in time order."""
    keep_obs = problem.obs_kf < n
    counts = np.bincount(problem.obs_point[keep_obs], minlength=problem.point_keys.size)
    used = np.flatnonzero(counts >= 2)
    remap = np.full(problem.point_keys.size, -1, np.int64)
    remap[used] = np.arange(used.size)
    keep_obs &= remap[problem.obs_point] >= 0
    keep_e = (problem.edge_i < n) & (problem.edge_j < n)
    imu = problem.imu
    if imu is not None:
        pairs = np.flatnonzero((imu.pair_i < n) & (imu.pair_j < n))
        segs = [imu.segment(int(k)) for k in pairs]
        sizes = [s.timestamps_ns.size for s in segs]
        imu = ImuTerms(
            pair_i=imu.pair_i[pairs],
            pair_j=imu.pair_j[pairs],
            offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            timestamps_ns=np.concatenate(
                [s.timestamps_ns for s in segs] or [np.zeros(0, np.int64)]
            ),
            gyro=np.concatenate([s.gyro for s in segs] or [np.zeros((0, 3))]),
            accel=np.concatenate([s.accel for s in segs] or [np.zeros((0, 3))]),
            noise=imu.noise[pairs],
            bias_gyro=imu.bias_gyro[:n],
            bias_accel=imu.bias_accel[:n],
            first=imu.first[imu.first < n],
            agent_offsets=imu.agent_offsets,
        )
    return dataclasses.replace(
        problem,
        keys=problem.keys[:n],
        T_world_body=problem.T_world_body[:n],
        point_keys=problem.point_keys[used],
        p_world=problem.p_world[used],
        obs_kf=problem.obs_kf[keep_obs],
        obs_point=remap[problem.obs_point[keep_obs]],
        obs_xy=problem.obs_xy[keep_obs],
        obs_sigma=problem.obs_sigma[keep_obs],
        T_body_cam=problem.T_body_cam[:n],
        edge_i=problem.edge_i[keep_e],
        edge_j=problem.edge_j[keep_e],
        T_i_j=problem.T_i_j[keep_e],
        sigmas=problem.sigmas[keep_e],
        robust=problem.robust[keep_e],
        up_body=None if problem.up_body is None else problem.up_body[:n],
        imu=imu,
        held=None if problem.held is None else problem.held[problem.held < n],
        held_points=None,
    )
