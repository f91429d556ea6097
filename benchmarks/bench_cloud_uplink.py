"""What the edge -> cloud link carries and what bounds it, replayed from a run's edge journals.

For each robot journal of ``--state`` (the edge's ``--state-dir`` of a finished run, e.g.
``OUT/run/state/edge`` of ``recslam demo``) and each ``--settle`` value, the journal is
replayed in process through the edge's decoding, VIO and cloud uplink
(:func:`lab.journal_replay.replay_journal`, ``EdgeSessionConfig.point_settle_keyframes`` set to
that value; the VIO is the same each time, so the variants differ only in what goes up) and
reports, in kbit/s of camera time (payload bytes, link framing excluded):

- the cloud messages by type, the keyframes' features, and how the map points went up (point
  entries per distinct point, the median move of a re-send);
- the keyframe features' bits per feature as sent (standalone, each decodable alone) against a
  counterfactual stateful coder: one :class:`FeatureEncoder` per robot map, its adaptive tables
  kept across the map's keyframes and each feature linked to its track's row in the previous
  uplinked keyframe (inter / carry coding, as the robot's own stream does);
- how many robot keyframes ORB-SLAM's keyframe culling would drop (>= 90 % of their map points
  seen by >= 3 other robot keyframes) in the VIO's final map.

Run: ``.venv/bin/python benchmarks/bench_cloud_uplink.py --state OUT/run/state/edge --settle
0,3 --out benchmarks/results/cloud_uplink.md`` (writes the .md and a .png beside it).
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from common.codec import KeyframeFeatures
from common.codec.frames import FeatureDecoder, FeatureEncoder, fill_carried
from common.links.edge_cloud import KeyframeUpdateCoded
from common.vocabulary import Vocabulary
from lab.journal_replay import JournalReplay, cloud_bytes, point_sends, replay_journal
from lab.links import git_commit
from services.edge.session_config import EdgeSessionConfig

RESULTS = Path(__file__).resolve().parent / "results"
TYPES = ("KeyframeUpdateCoded", "MapPointUpdateCoded", "KeyframePoses", "CullEvent")


@dataclass(frozen=True)
class Row:
    """One robot under one settle value."""

    robot: str
    settle: int
    kbps: dict[str, float]
    features_kbps: float
    sends_per_point: float
    median_move_mm: float
    standalone_bits: float  # per keyframe feature, as sent
    stateful_bits: float  # per keyframe feature, the counterfactual
    robot_keyframes: int
    redundant: int


def keyframe_bits(rep: JournalReplay, vocab: Vocabulary) -> tuple[float, float]:
    """Bits per feature of the uplinked keyframes' features: as sent, and re-coded by one
    stateful encoder per map with links to the previous uplinked keyframe's rows."""
    decoder = FeatureDecoder(vocab, rep.sessions[0].codec)
    encoders: dict[int, FeatureEncoder] = {}
    last: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # map -> (track numbers, descriptors)
    sent = coded = n = 0
    for m in rep.cloud:
        if not isinstance(m, KeyframeUpdateCoded):
            continue
        map_id, feats = int(m.map_id), decoder.decode_detached(m.features)
        assert isinstance(feats, KeyframeFeatures)
        if (feats.links >= 0).any():
            feats = fill_carried(feats, last[map_id][1])
        tracks = rep.keyframe_tracks[int(m.timestamp_ns)]
        links = np.full(len(feats), -1, np.int32)
        if map_id in last and len(tracks) == len(feats):
            row_of = {int(t): i for i, t in enumerate(last[map_id][0])}
            links = np.array([row_of.get(int(t), -1) for t in tracks], np.int32)
        if map_id not in encoders:  # (a new map: its first keyframe links nothing)
            encoders[map_id] = FeatureEncoder(vocab, rep.sessions[0].codec)
        coded += len(
            encoders[map_id].encode_keyframe(
                KeyframeFeatures(feats.keypoints, feats.descriptors, links)
            )
        )
        sent += len(m.features)
        n += len(feats)
        last[map_id] = (tracks, feats.descriptors)
    return 8 * sent / max(n, 1), 8 * coded / max(n, 1)


def redundant_keyframes(rep: JournalReplay, share: float = 0.9, others: int = 3) -> tuple[int, int]:
    """(robot keyframes, of them redundant by ORB-SLAM's culling rule) in the last VIO map."""
    vmap = rep.runners[-1].vio.current_map
    if vmap is None:
        return 0, 0
    robot = {k.id for k in vmap.keyframe_list() if k.descriptors is not None}
    seen: dict[int, list[int]] = {k: [] for k in robot}
    for p in vmap.points.values():
        obs = [k for k in p.observations if k in robot]
        for k in obs:
            seen[k].append(len(obs) - 1)
    red = sum(1 for v in seen.values() if v and np.mean(np.array(v) >= others) >= share)
    return len(robot), red


def measure(state: Path, robot: str, settle: int, vocab: Vocabulary) -> Row:
    rep = replay_journal(
        state, robot, vocab, session=replace(EdgeSessionConfig(), point_settle_keyframes=settle)
    )
    s = max(rep.seconds, 1e-9)
    kbps = {t: 8 * b / s / 1e3 for t, b in cloud_bytes(rep.cloud).items()}
    feats = sum(len(m.features) for m in rep.cloud if isinstance(m, KeyframeUpdateCoded))
    ps = point_sends(rep.cloud)
    standalone, stateful = keyframe_bits(rep, vocab)
    n_robot, red = redundant_keyframes(rep)
    return Row(
        robot,
        settle,
        kbps,
        8 * feats / s / 1e3,
        ps.sends / max(ps.distinct, 1),
        float(np.median(ps.moves_m)) * 1e3 if len(ps.moves_m) else float("nan"),
        standalone,
        stateful,
        n_robot,
        red,
    )


def table(rows: list[Row]) -> list[str]:
    head = ["robot", "settle", "edge→cloud", *(f"↳ {t}" for t in TYPES)]
    head += ["↳↳ keyframe features", "point entries per point", "median re-send move mm"]
    head += ["keyframe bits/feature sent", "stateful counterfactual", "robot keyframes"]
    head += ["redundant (ORB-SLAM rule)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r.robot, str(r.settle), f"**{sum(r.kbps.values()):.1f}**"]
        cells += [f"{r.kbps.get(t, 0.0):.1f}" for t in TYPES]
        cells += [f"{r.features_kbps:.1f}", f"{r.sends_per_point:.2f}", f"{r.median_move_mm:.1f}"]
        cells += [f"{r.standalone_bits:.1f}", f"{r.stateful_bits:.1f}"]
        cells += [str(r.robot_keyframes), str(r.redundant)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(rows: list[Row], path: Path) -> None:
    robots = sorted({r.robot for r in rows})
    settles = sorted({r.settle for r in rows})
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(1, len(settles))
    for i, st in enumerate(settles):
        by = {r.robot: r for r in rows if r.settle == st}
        bottom = np.zeros(len(robots))
        for t in TYPES[:2]:
            vals = np.array([by[r].kbps.get(t, 0.0) for r in robots])
            xs = [k + i * width for k in range(len(robots))]
            ax.bar(xs, vals, width, bottom=bottom, label=f"settle {st}: {t}")
            bottom += vals
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(robots))], robots)
    ax.set_ylabel("kbit/s of camera time")
    ax.set_title("edge → cloud per robot, replayed from the edge journals")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--state", type=Path, required=True, help="the edge's state folder")
    ap.add_argument("--robots", default="", help="comma-separated (default: every journal)")
    ap.add_argument("--settle", default="0,3", help="point_settle_keyframes values")
    ap.add_argument("--out", type=Path, default=RESULTS / "cloud_uplink.md")
    ap.add_argument("--note", default="", help="a sentence on the run the journals come from")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    vocab = Vocabulary.load()
    robots = (
        args.robots.split(",")
        if args.robots
        else sorted(p.stem for p in args.state.glob("*.journal"))
    )
    t0 = time.monotonic()
    rows = []
    for robot in robots:
        for settle in (int(x) for x in args.settle.split(",")):
            rows.append(measure(args.state, robot, settle, vocab))
            print(f"{robot} settle {settle}: done ({time.monotonic() - t0:.0f} s)", flush=True)
    png = args.out.with_suffix(".png")
    plot(rows, png)
    lines = [
        "# The edge → cloud link replayed from the edge journals: what it carries, what bounds it",
        "",
        f"`benchmarks/bench_cloud_uplink.py --state {args.state} --settle {args.settle}` "
        f"(script of {git_commit()}; {time.monotonic() - t0:.0f} s). {args.note}",
        "",
        *table(rows),
        "",
        f"![edge to cloud by robot]({png.name})",
    ]
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
