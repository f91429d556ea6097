"""A synthetic collaborative map for tests, the benchmark and ``recslam dashboard --demo``.

Three (or more) agents walk loops inside a 10 m x 8 m x 3 m room; map points lie on the walls
and the floor, owned by the agent whose sector of the room they are in; estimated keyframe
poses drift slowly away from the ground truth; each agent closes one loop, and merges link
neighbouring agents. Bandwidth samples imitate robot→edge and edge→cloud traffic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import make_T, so3_exp
from common.map_view import (
    AgentRecord,
    AgentState,
    BandwidthSample,
    Direction,
    GroundTruth,
    KeyframeSet,
    MapDelta,
    PointSet,
    StatsSnapshot,
    counts_of,
)

ROOM_HALF_X_M = 5.0
ROOM_HALF_Y_M = 4.0
ROOM_HEIGHT_M = 3.0


@dataclass(frozen=True)
class DemoConfig:
    """Size of the synthetic map.

    n_points: map points in total; n_agents: robots; keyframes_per_agent: keyframes each;
    duration_s: length of the run (timestamps and bandwidth history); pruned_keyframes /
    pruned_points: fraction flagged as removed by MBP; seed: random generator seed.
    """

    n_points: int = 20_000
    n_agents: int = 3
    keyframes_per_agent: int = 80
    duration_s: float = 120.0
    pruned_keyframes: float = 0.3
    pruned_points: float = 0.15
    seed: int = 0


def _wall_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) points on the four walls (3/4) and the floor (1/4) of the room."""
    n_floor = n // 4
    n_wall = n - n_floor
    perim = 4 * (ROOM_HALF_X_M + ROOM_HALF_Y_M)
    s = rng.uniform(0, perim, n_wall)
    z = rng.uniform(0, ROOM_HEIGHT_M, n_wall)
    hx, hy = ROOM_HALF_X_M, ROOM_HALF_Y_M
    x = np.empty(n_wall)
    y = np.empty(n_wall)
    e = [2 * hx, 2 * hy, 2 * hx, 2 * hy]
    edges = np.cumsum([0, *e])
    for k in range(4):
        m = (s >= edges[k]) & (s < edges[k + 1])
        u = s[m] - edges[k]
        if k == 0:
            x[m], y[m] = -hx + u, -hy
        elif k == 1:
            x[m], y[m] = hx, -hy + u
        elif k == 2:
            x[m], y[m] = hx - u, hy
        else:
            x[m], y[m] = -hx, hy - u
    walls = np.stack([x, y, z], axis=1) + rng.normal(0, 0.02, (n_wall, 3))
    floor = np.stack(
        [rng.uniform(-hx, hx, n_floor), rng.uniform(-hy, hy, n_floor), np.zeros(n_floor)], axis=1
    )
    return np.concatenate([walls, floor])


def _look_at(p_body: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose z axis (camera forward) points from ``p_body`` to ``target``."""
    z = target - p_body
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def make_demo_map(config: DemoConfig | None = None) -> tuple[MapDelta, StatsSnapshot]:
    """A full :class:`MapDelta` and matching :class:`StatsSnapshot` of the synthetic room."""
    cfg = config or DemoConfig()
    rng = np.random.default_rng(cfg.seed)
    A, K = cfg.n_agents, cfg.keyframes_per_agent
    p_world = _wall_points(rng, cfg.n_points)
    # Owner: the agent whose angular sector (around the room centre) holds the point.
    angle = np.mod(np.arctan2(p_world[:, 1], p_world[:, 0]), 2 * np.pi)
    owner = np.minimum((angle / (2 * np.pi) * A).astype(np.int32), A - 1)
    order = np.argsort(angle - 2 * np.pi * owner / A, kind="stable")  # sweep order per agent
    p_world, owner = p_world[order], owner[order]
    pt_ids = (owner.astype(np.int64) << 32) | np.arange(cfg.n_points)
    pts = PointSet(pt_ids, p_world, owner, rng.random(cfg.n_points) < cfg.pruned_points)

    ids: list[int] = []
    agents: list[int] = []
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    gts: list[GroundTruth] = []
    current: dict[int, np.ndarray] = {}
    for a in range(A):
        t = np.linspace(0, cfg.duration_s, K)
        phase = 2 * np.pi * a / A
        theta = phase + np.linspace(0, 2 * np.pi * 0.9, K)  # almost a full loop each
        radius = 1.5 + 0.6 * a / max(A - 1, 1)
        p_gt = np.stack(
            [radius * np.cos(theta), 0.8 * radius * np.sin(theta), np.full(K, 1.2)], axis=1
        )
        drift = np.cumsum(rng.normal(0, 0.01, (K, 3)), axis=0)
        drift[:, 2] *= 0.3
        p_est = p_gt + drift
        for k in range(K):
            look = 1.8 * np.array([np.cos(theta[k] + 0.3), np.sin(theta[k] + 0.3), 0.0])
            R = _look_at(p_est[k], np.array([look[0] * 3, look[1] * 3, 1.2]))
            R = R @ so3_exp(rng.normal(0, 0.01, 3))
            poses.append(make_T(R, p_est[k]))
        ids.extend(((a << 32) | k) for k in range(K))
        agents.extend([a] * K)
        stamps.extend(t.tolist())
        gts.append(GroundTruth(a, t, p_gt))
        current[a] = poses[-1]
    kf_pruned = rng.random(A * K) < cfg.pruned_keyframes
    kf_pruned[::K] = False
    kf_pruned[K - 1 :: K] = False
    kfs = KeyframeSet(
        np.array(ids, np.int64),
        np.array(agents, np.int32),
        np.array(stamps),
        np.array(poses),
        kf_pruned,
    )
    loops = [((a << 32) | (K - 1), (a << 32) | 2) for a in range(A)]
    merges = [((((a + 1) % A) << 32) | (K // 2), (a << 32) | (K // 2)) for a in range(A - 1)]
    delta = MapDelta(
        version=1,
        since_version=-1,
        full=True,
        points=pts,
        keyframes=kfs,
        current_pose=current,
        loops=np.array(loops, np.int64).reshape(-1, 2),
        merges=np.array(merges, np.int64).reshape(-1, 2),
        ground_truth=tuple(gts),
    )
    records = tuple(
        AgentRecord(
            agent_id=a,
            status=AgentState.MERGED if a > 0 else AgentState.TRACKING,
            frames=int(cfg.duration_s * 20),
            keyframes=K,
            last_seen=cfg.duration_s,
            map_id=0,
            name=f"robot{a}",
            edge=demo_edge(a),
        )
        for a in range(A)
    )
    counts = counts_of(pts, kfs, len(loops), len(merges))
    return delta, StatsSnapshot(cfg.duration_s, records, counts, _demo_bandwidth(rng, cfg))


def _demo_bandwidth(rng: np.random.Generator, cfg: DemoConfig) -> tuple[BandwidthSample, ...]:
    """One sample per second, link and message type: robots send frames (tracks) at ~20 Hz and
    keyframes at ~1 Hz to the edge; the edge forwards keyframes and map points to the cloud."""
    out: list[BandwidthSample] = []
    up, down = Direction.UP, Direction.DOWN
    for s in range(int(cfg.duration_s)):
        t = float(s)
        for a in range(cfg.n_agents):
            link = f"robot{a}→{demo_edge(a)}"
            out.append(BandwidthSample(t, link, up, "frame", int(rng.normal(12_000, 1_500))))
            out.append(BandwidthSample(t, link, up, "keyframe", int(rng.normal(9_000, 3_000))))
            out.append(BandwidthSample(t, link, up, "imu", int(rng.normal(4_000, 200))))
            out.append(BandwidthSample(t, link, down, "ack", int(rng.normal(600, 50))))
        for edge in sorted({demo_edge(a) for a in range(cfg.n_agents)}):
            n = sum(demo_edge(a) == edge for a in range(cfg.n_agents))
            link = f"{edge}→cloud"
            kf = int(abs(rng.normal(14_000 * n, 4_000)))
            out.append(BandwidthSample(t, link, up, "keyframe", kf))
            mp = int(abs(rng.normal(6_000 * n, 2_000)))
            out.append(BandwidthSample(t, link, up, "map_points", mp))
            out.append(BandwidthSample(t, link, down, "map_update", int(rng.normal(800, 80))))
    return tuple(out)


def demo_edge(agent: int) -> str:
    """The demo's two sites: robot 0 and 1 on edge ``site-a``, the others on ``site-b``."""
    return "site-a" if agent < 2 else "site-b"
