"""Edge service real-time factor: 1 and 3 robots through the whole network path.

Each robot is a simulated, coded robot (``sim.robot``: the VIO simulator's
tracks and IMU as RobotFrame messages, seeds 0, 1, 2) sending as fast as the link allows
(``--rate max``) over loopback TCP to one in-process :class:`EdgeServer` (decode, journal-less,
VIO, feedback, uplink to a stub cloud). Workers are started before the clock starts.

RT factor per robot = its frames processed per wall second ÷ 20 Hz (≥ 1 keeps up);
aggregate = all frames per wall second ÷ 20 Hz. Worker = "process" (one spawned process per
robot) or "thread" (one thread per robot in the edge process).

With ``--synth DIR`` (``recslam dataset synth --out DIR --robots 3 --seconds 20 --seed 2``)
the robots are the rendered synthetic sequences instead: each is first played once by the
real image-based robot (``RobotService``, max rate) into a recording stub, and the recorded
``RobotFrame`` messages are then replayed into the edge exactly like the simulated ones (so
the robots' own image processing does not compete with the edge for the 2 cores).

Run: ``.venv/bin/python benchmarks/bench_edge_rtf.py [--seconds 20] [--synth DIR]``; writes
``benchmarks/results/edge_rtf.md`` (``edge_rtf_synth.md`` with ``--synth``).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import multiprocessing
import os
import platform
import time
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from common.data.euroc import find_mav0, read_camera_yaml, read_imu_yaml
from common.links.robot_edge import RobotFrame
from common.links.sensors import Sensors
from common.protocol import SessionConfig
from common.transport import Delivery, Server, TransportConfig
from common.vocabulary import Vocabulary
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from sim.robot import code_sequence, play
from sim.vio import SimConfig, simulate

log = logging.getLogger("bench_edge_rtf")
RESULTS = Path(__file__).resolve().parent / "results" / "edge_rtf.md"
SECRET = b"bench-edge-secret-0123456789"
RATE_HZ = 20.0


def _ms(values: list[float]) -> str:
    if not values:
        return "-"
    a = np.asarray(values) * 1e3
    return f"{np.median(a):.1f} / {np.percentile(a, 95):.1f}"


async def _peers(frames_by_robot: dict, sensors: Sensors, conn: Connection) -> None:
    """The robot players and a stub cloud (in the peers process): sends the cloud's port,
    receives the edge's, plays every robot, and after "done" reports its CPU seconds."""

    async def on_cloud(d: Delivery) -> None:
        return None  # the uplink is received (and acknowledged) and dropped

    loop = asyncio.get_running_loop()
    cloud = Server(SessionConfig("cloud", "cloud", SECRET), on_cloud)
    _, cport = await cloud.start()
    conn.send(cport)
    port = await loop.run_in_executor(None, conn.recv)
    cpu0 = time.process_time()
    done = asyncio.Event()
    cfg = TransportConfig()
    tasks = [
        asyncio.create_task(
            play(
                fr,
                "127.0.0.1",
                port,
                name,
                SECRET,
                sensors,
                transport=cfg,
                flush_timeout_s=3600.0,
                linger=done,
            )
        )
        for name, fr in frames_by_robot.items()
    ]
    await loop.run_in_executor(None, conn.recv)  # "done": every robot processed
    cpu = time.process_time() - cpu0
    done.set()
    await asyncio.gather(*tasks)
    await cloud.close()
    conn.send(cpu)


def _peers_main(frames_by_robot: dict, sensors: Sensors, conn: Connection) -> None:
    asyncio.run(_peers(frames_by_robot, sensors, conn))


async def run_case(frames_by_robot: dict, camera, imu, vocab, worker: str) -> dict:
    """One measurement. The robots and the stub cloud run in their own process (they are
    other machines in a deployment; here they still compete for the same cores), so the
    edge process holds only the edge: event loop, decoding, uplink coding."""
    loop = asyncio.get_running_loop()
    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    sensors = Sensors(camera, imu)
    peers = ctx.Process(target=_peers_main, args=(frames_by_robot, sensors, child), daemon=True)
    peers.start()
    cport = await loop.run_in_executor(None, conn.recv)
    edge = EdgeServer(
        SECRET,
        vocab,
        EdgeConfig(worker=worker),
        EdgeServiceConfig(agent_id="edge", cloud_host="127.0.0.1", cloud_port=cport),
    )
    _, port = await edge.start()
    await edge.app.prepare({name: sensors for name in frames_by_robot})
    t0 = time.monotonic()
    cpu0 = time.process_time()  # this process: the edge's event loop, decoding, uplink coding
    conn.send(port)
    finish: dict[str, float] = {}

    async def watch() -> None:
        while len(finish) < len(frames_by_robot):
            for name, rb in edge.app.robots.items():
                if name not in finish and rb.ended.is_set() and rb.idle.is_set():
                    finish[name] = time.monotonic() - t0
            await asyncio.sleep(0.02)

    await watch()
    wall = time.monotonic() - t0
    main_cpu = time.process_time() - cpu0
    conn.send("done")
    peers_cpu = await loop.run_in_executor(None, conn.recv)
    peers.join(30.0)
    stats = edge.stats()["robots"]
    await edge.stop()
    out = {
        "worker": worker,
        "robots": len(frames_by_robot),
        "wall": wall,
        "per_robot": {},
        "main_cpu": main_cpu,
        "peers_cpu": peers_cpu,
    }
    track, ba, frame = [], [], []
    for name in frames_by_robot:
        s = stats[name]
        out["per_robot"][name] = {
            "frames": s["frames_processed"],
            "rtf": s["frames_processed"] / finish[name] / RATE_HZ,
            "state": s["state"],
            "feedback": s["feedback_sent"],
            "keyframes": s["keyframes_uplinked"],
        }
        track += s["track_s"]
        frame += s["frame_s"]
        ba += s["local_ba_s"]
    n = sum(v["frames"] for v in out["per_robot"].values())
    out["aggregate_rtf"] = n / wall / RATE_HZ
    out["track"], out["ba"], out["frame"] = _ms(track), _ms(ba), _ms(frame)
    return out


async def record_robot(dataset: Path, name: str) -> list:
    """The RobotFrames the real robot sends for ``dataset`` (no edge feedback)."""
    from services.robot.server import RobotService
    from services.robot.service_config import Rate, RobotServiceConfig

    frames: list = []

    async def on_message(d: Delivery) -> None:
        if isinstance(d.message, RobotFrame):
            frames.append(d.message)

    stub = Server(SessionConfig("edge", "recorder", SECRET), on_message)
    _, port = await stub.start()
    cfg = RobotServiceConfig(
        dataset=dataset,
        edge_host="127.0.0.1",
        edge_port=port,
        agent_id=name,
        secret=SECRET,
        rate=Rate.MAX,
    )
    await RobotService(cfg).run()
    await stub.close()
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="sequence length (s)")
    ap.add_argument("--workers", default="process,thread", help="worker kinds to measure")
    ap.add_argument("--synth", type=Path, default=None, help="rendered synthetic dataset")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    vocab = Vocabulary.load()
    if args.synth is None:
        seqs = [simulate(SimConfig(duration_s=args.seconds, seed=s)) for s in range(3)]
        coded = [code_sequence(q, vocab) for q in seqs]
        cam, imu = seqs[0].camera, seqs[0].imu
        source = (
            f"`sim.robot` coded simulator sequences ({args.seconds:.0f} s, seeds "
            "0-2, 20 Hz camera, 200 Hz IMU, 150 tracks)"
        )
        results = RESULTS
    else:
        robots = sorted(p for p in args.synth.iterdir() if p.is_dir())[:3]
        coded = [asyncio.run(record_robot(p, p.name)) for p in robots]
        mav0 = find_mav0(robots[0])
        cam = read_camera_yaml(mav0 / "cam0" / "sensor.yaml")
        imu = read_imu_yaml(mav0 / "imu0" / "sensor.yaml")
        source = (
            f"rendered synthetic dataset `{args.synth}` ({', '.join(p.name for p in robots)}; "
            f"{', '.join(str(len(c)) for c in coded)} frames), RobotFrames recorded from the "
            "real image-based robot"
        )
        results = RESULTS.with_name("edge_rtf_synth.md")
    rows = []
    for worker in args.workers.split(","):
        for n in (1, 3):
            frames = {f"robot-{i}": coded[i] for i in range(n)}
            load0 = os.getloadavg()[0]
            res = asyncio.run(run_case(frames, cam, imu, vocab, worker))
            res["load"] = f"{load0:.1f} -> {os.getloadavg()[0]:.1f}"
            log.warning("%s", res)
            rows.append(res)
    lines = [
        "# Edge service real-time factor (1 and 3 robots)",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores (shared with other jobs while "
        f"measured), Python {platform.python_version()}.",
        f"Robots: {source}, sent at max rate over loopback TCP to one in-process `EdgeServer` "
        "(decode, VIO, feedback, uplink to a stub cloud). The robot players and the stub cloud "
        "run in one separate process on the same cores (peers CPU).",
        "RT factor per robot = its frames processed per wall second / 20 Hz (>= 1 keeps up); "
        "aggregate = all robots' frames per wall second / 20 Hz. Track = the VIO's per-frame "
        "tracking; feed_frame = the whole call (keyframes add mapping, local BA, VI init); "
        "local BA = each local BA (median / p95 over all robots of the run). Main process "
        "CPU = the edge's own process (event loop, frame decoding, keyframe re-coding for the "
        "cloud); with the process worker the "
        "VIO runs in one process per robot besides it. Load average: "
        "the machine is shared with other engineers' jobs.",
        "",
        "| worker | robots | wall s | RT factor per robot (min) | aggregate | "
        "track ms (med / p95) | feed_frame ms (med / p95) | local BA ms (med / p95) | states | "
        "main process CPU s (% of wall) | peers CPU s | load avg (1 min) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        pr = r["per_robot"].values()
        lines.append(
            f"| {r['worker']} | {r['robots']} | {r['wall']:.1f} | "
            f"{min(v['rtf'] for v in pr):.2f} | {r['aggregate_rtf']:.2f} | {r['track']} | "
            f"{r['frame']} | "
            f"{r['ba']} | {', '.join(v['state'] for v in pr)} | "
            f"{r['main_cpu']:.1f} ({100 * r['main_cpu'] / r['wall']:.0f} %) | "
            f"{r['peers_cpu']:.1f} | {r['load']} |"
        )
    results.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
