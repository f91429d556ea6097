"""Robot->edge link rate: the robot service's pipeline vs all-frames intra coding, same run.

Run: ``.venv/bin/python benchmarks/bench_link_rate.py [--dataset PATH ...] [--skip N ...]``;
writes ``benchmarks/results/link_rate.md``. Defaults: the real EuRoC excerpt, and the
synthetic robot sequence ``/tmp/synth_bench/*/`` when it exists
(``recslam dataset synth --out /tmp/synth_bench --robots 1 --seconds 20 --seed 1``).

Both pipelines are the robot service's own :class:`services.robot.app.RobotApp` (IMU-assisted
LK, ORB keyframes, feature + IMU codecs) fed the same decoded images and IMU samples:

- *robot*: the default front end (keyframes by tracked count / fraction / 1 s interval);
- *all-frames intra* (the baseline of the target): ``KeyframeDecisionConfig(every_frame=True)``
  and ``code_links=False``: every frame an ORB keyframe coded on its own (keypoints, word,
  XOR residual; no links, no inter prediction): the paper's reference [55] mode;
- *all-frames inter* (a stronger reference): every frame a keyframe, with links to the
  previous frame's tracks so that descriptors may be coded against the previous ones.

Every ``RobotFrame`` of both goes through a real protocol link on loopback (one client per
pipeline, one server); the rate is the client's transmitted bytes from the protocol's
per-type counters (frame header included), divided by the sequence's camera duration. The
split (features / IMU / message + header overhead) is computed from the payload sizes; the
"all control" column adds the handshake, heartbeats, acks and the sequence end.
``--skip N`` plays every N-th frame (IMU in between kept), where motion per frame is larger.
"""

from __future__ import annotations

import argparse
import logging
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.data.euroc import EurocSequence
from common.links.robot_edge import RobotFrame, RobotSequenceEnd
from common.protocol import HEADER_SIZE, SessionConfig
from common.protocol.messages import encode_payload
from common.transport import Client, Delivery, Server, run
from common.vocabulary import Vocabulary
from lab.datasets import euroc_micro_path
from services.robot.app import RobotApp
from services.robot.config import FrontEndConfig, KeyframeDecisionConfig

log = logging.getLogger("bench_link_rate")
RESULTS = Path(__file__).resolve().parent / "results" / "link_rate.md"
EXCERPT = euroc_micro_path()
SYNTH = Path("/tmp/synth_bench")
TARGET_RATIO = 0.12
SECRET = b"bench-link-rate-secret"
PARTS = ("keypoint", "link", "mode", "word", "residual", "survival", "new", "side")


@dataclass
class Tally:
    """Bits of one kind of frame (keyframe / non-keyframe) of one pipeline."""

    frames: int = 0
    features: int = 0
    parts: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PARTS, 0.0))
    overhead: float = 0.0
    payload_bits: int = 0

    def add(self, n: int, bits: dict[str, float], overhead: float, payload_bytes: int) -> None:
        self.frames += 1
        self.features += n
        for k, v in bits.items():
            self.parts[k] = self.parts.get(k, 0.0) + v
        self.overhead += overhead
        self.payload_bits += 8 * payload_bytes


@dataclass
class Pipeline:
    name: str
    app: RobotApp
    messages: list[RobotFrame] = field(default_factory=list)
    kf: Tally = field(default_factory=Tally)
    nkf: Tally = field(default_factory=Tally)
    feature_bytes: int = 0
    imu_bytes: int = 0
    wire_bytes_offline: int = 0
    counters: dict = field(default_factory=dict)
    time_s: list[float] = field(default_factory=list)

    def step(self, ts: int, image: np.ndarray, imu) -> None:
        t0 = time.perf_counter()
        msg = self.app.process(ts, image, imu)
        self.time_s.append(time.perf_counter() - t0)
        used = self.app.recorded.pop()  # keep memory flat: tally and drop
        coded = used.coded
        tally = self.kf if msg.keyframe else self.nkf
        tally.add(len(coded.features), coded.bits, coded.overhead_bits, len(msg.features))
        self.feature_bytes += len(msg.features)
        self.imu_bytes += len(msg.imu)
        self.wire_bytes_offline += HEADER_SIZE + len(encode_payload(msg))
        self.messages.append(msg)


async def _send_all(pipelines: list[Pipeline]) -> None:
    """Send every pipeline's frames over a real loopback link; keep the client counters."""
    done: dict[str, int] = {}

    async def sink(d: Delivery) -> None:
        if isinstance(d.message, RobotSequenceEnd):
            done[d.peer] = d.message.frames

    server = Server(SessionConfig("edge", "edge-bench", SECRET), sink)
    host, port = await server.start()
    try:
        for i, p in enumerate(pipelines):
            client = Client(SessionConfig("robot", f"robot-{i}", SECRET), sink, host, port)
            await client.start()
            for msg in p.messages:
                await client.send(msg)
            await client.send(RobotSequenceEnd(frames=len(p.messages)))
            await client.flush()
            p.counters = client.counters()
            await client.close()
            assert done.get(f"robot-{i}") == len(p.messages)
    finally:
        await server.close()


def measure(path: Path, skip: int, vocabulary: Vocabulary) -> tuple[dict, list[Pipeline]]:
    seq = EurocSequence(path)
    every = FrontEndConfig(keyframe=KeyframeDecisionConfig(every_frame=True))
    pipelines = [
        Pipeline("robot", RobotApp(FrontEndConfig(), seq.cam0, seq.imu, vocabulary, record=True)),
        Pipeline(
            "all-frames intra",
            RobotApp(every, seq.cam0, seq.imu, vocabulary, record=True, code_links=False),
        ),
        Pipeline("all-frames inter", RobotApp(every, seq.cam0, seq.imu, vocabulary, record=True)),
    ]
    idx = range(0, len(seq), skip)
    prev: int | None = None
    for i in idx:
        ts = int(seq.frame_timestamps_ns[i])
        image = seq.load_image(i)
        imu = seq.imu_between(prev, ts)
        for p in pipelines:
            p.step(ts, image, imu)
        prev = ts
    run(_send_all(pipelines))
    stamps = seq.frame_timestamps_ns[list(idx)]
    period = float(np.median(np.diff(stamps))) * 1e-9 if len(stamps) > 1 else 0.05
    duration = float(stamps[-1] - stamps[0]) * 1e-9 + period
    info = {
        "name": f"{seq.name}" + ("" if skip == 1 else f", every {skip}th frame"),
        "frames": len(stamps),
        "duration_s": duration,
    }
    return info, pipelines


def kbps(nbytes: float, duration: float) -> float:
    return 8.0 * nbytes / duration / 1000.0


def link_row(info: dict, robot: Pipeline, intra: Pipeline, inter: Pipeline) -> str:
    d = info["duration_s"]
    rf = robot.counters["tx"]["by_type"]["RobotFrame"]["bytes"]
    assert rf == robot.wire_bytes_offline, (rf, robot.wire_bytes_offline)  # no retransmissions
    other = robot.counters["tx"]["bytes"] - rf
    intra_rf = intra.counters["tx"]["by_type"]["RobotFrame"]["bytes"]
    inter_rf = inter.counters["tx"]["by_type"]["RobotFrame"]["bytes"]
    ratio = rf / intra_rf
    verdict = (
        f"met ({TARGET_RATIO / ratio:.1f}x under)"
        if ratio <= TARGET_RATIO
        else f"missed by {ratio / TARGET_RATIO:.2f}x"
    )
    overhead = rf - robot.feature_bytes - robot.imu_bytes
    return (
        f"| {info['name']} | {info['frames']} | {robot.kf.frames} "
        f"| {100 * robot.kf.payload_bits / max(8 * robot.feature_bytes, 1):.0f} % | {d:.2f} "
        f"| {kbps(robot.feature_bytes, d):.1f} | {kbps(robot.imu_bytes, d):.1f} "
        f"| {kbps(overhead, d):.1f} | **{kbps(rf, d):.1f}** | {kbps(other, d):.1f} "
        f"| {kbps(intra_rf, d):.1f} | **{ratio:.3f}x** | {verdict} "
        f"| {kbps(inter_rf, d):.1f} | {rf / inter_rf:.3f}x |"
    )


def bits_row(label: str, t: Tally) -> str:
    if t.features == 0:
        return f"| {label} | {t.frames} | 0 | – | – | – | – | – | – | – | – |"
    f = float(t.features)
    p = t.parts
    return (
        f"| {label} | {t.frames} | {t.features} | {p['keypoint'] / f:.2f} "
        f"| {p['link'] / f:.2f} | {(p['word'] + p['mode']) / f:.2f} | {p['residual'] / f:.2f} "
        f"| {(p['survival'] + p['new']) / f:.2f} | {(p['side'] + t.overhead) / f:.2f} "
        f"| **{t.payload_bits / f:.2f}** | {f / t.frames:.0f} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, action="append", help="EuRoC-layout sequence(s)")
    ap.add_argument("--skip", type=int, action="append", help="frame skips (default 1 and 4)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for noisy in ("services", "common"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    datasets = args.dataset
    if not datasets:
        datasets = [EXCERPT]
        if SYNTH.is_dir():
            datasets += sorted(p for p in SYNTH.iterdir() if (p / "mav0").is_dir())
    skips = args.skip or [1, 4]
    vocabulary = Vocabulary.load()
    link_rows, bit_rows, times = [], [], []
    for path in datasets:
        for skip in skips:
            log.info("%s, every %d. frame", path, skip)
            info, (robot, intra, inter) = measure(path, skip, vocabulary)
            link_rows.append(link_row(info, robot, intra, inter))
            name = info["name"]
            bit_rows += [
                bits_row(f"{name}: robot keyframes", robot.kf),
                bits_row(f"{name}: robot non-keyframes", robot.nkf),
                bits_row(f"{name}: all-frames intra", intra.kf),
                bits_row(f"{name}: all-frames inter", inter.kf),
            ]
            times.append(
                f"| {name} | {1e3 * np.median(robot.time_s):.1f} "
                f"| {1e3 * np.median(intra.time_s):.1f} | {1e3 * np.median(inter.time_s):.1f} |"
            )
            log.info("%s", link_rows[-1])
    lines = [
        "# Robot -> edge link rate",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_link_rate.py`. Machine: "
        f"{platform.machine()}, Python {platform.python_version()}. Vocabulary: default "
        f"({vocabulary.n_words} words). Both pipelines run in the same process on the same "
        "decoded images and IMU samples; their `RobotFrame`s cross a real loopback protocol "
        "link and the rate is the sending client's per-type byte counter (22 B frame header "
        "included) over the camera duration.",
        "",
        "## Rate (kbit/s)",
        "",
        "`features`, `IMU`: coded payloads; `msg+hdr`: msgpack fields + 22 B protocol header; "
        "`total`: all `RobotFrame` bytes on the wire; `control`: everything else the robot "
        "sent (handshake, heartbeats, acks, sequence end). Target: total ≤ "
        f"{TARGET_RATIO}× the all-frames intra baseline.",
        "",
        "| sequence | frames | keyframes | KF share of feature bits | duration s | features "
        "| IMU | msg+hdr | total "
        "| control | all-frames intra total | ratio | target ≤ 0.12× | all-frames inter total "
        "| ratio to inter |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *link_rows,
        "",
        "Keyframes carry most of the robot's bits: on a slow sequence they come from the "
        "1 s maximum keyframe interval (`KeyframeDecisionConfig.max_interval_s`), so the "
        "robot's rate hardly depends on the frame rate while the all-frames baselines scale "
        "with it (at 5 Hz, every 4th frame, the target is missed for that reason).",
        "",
        "## Bits per feature",
        "",
        "Split by the codec models' information content (`word` includes the intra/inter "
        "mode flag; `surv/new` the survival flags and new-track positions; `side+ovh` model "
        "side information, header, CRC and coder padding); `total` = payload bits / features.",
        "",
        "| frames | count | features | keypoint | link | word | residual | surv/new "
        "| side+ovh | total | features/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *bit_rows,
        "",
        "## Front end + coding time per frame (ms, median, this machine, not one core pinned)",
        "",
        "| sequence | robot | all-frames intra | all-frames inter |",
        "|---|---|---|---|",
        *times,
        "",
    ]
    if not (SYNTH.is_dir() or args.dataset):
        lines += [
            "No synthetic robot sequence was found at /tmp/synth_bench (the generator "
            "`recslam dataset synth` was not available when this was run).",
            "",
        ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
