"""Live ROS 1 robots against the folder run: joint ATE, % frames with odometry, pose latency.

Two runs of the same robots (default: the 3-robot synthetic dataset, 60 s, seed 0), each with
a fresh cloud and edge as processes on loopback:

- ``folder``: ``recslam robot --dataset DATA/robotK --rate realtime`` per robot;
- ``ros1``: a real ``roscore`` on a free port; per robot a player publishes ``DATA/robotK`` on
  its own topics at 20 Hz (``lab.ros_live.Player``: IMU then image, stamped with their sensor
  times) and ``recslam robot --source ros1`` consumes them live and publishes Odometry, which
  the player's subscriber counts.

Per run: the joint ATE of the cloud's keyframe trajectories (SE(3), one alignment for all
robots, ``common.evaluation``), the frames per robot, how many came back with a metric pose,
how many Odometry messages a subscriber saw (ros1), and the latency camera frame -> its pose
at the robot (median, p95; the robot's own ``--stats-out``). Writes
``benchmarks/results/ros_live.md`` and ``ros_live.png``.

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/bench_ros_live.py --data DATA`` (DATA is made
with ``recslam dataset synth --out DATA --robots 3 --seconds 60 --seed 0`` if missing).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from common.evaluation import (
    AlignMode,
    AteConfig,
    compute_joint_ate,
    load_groundtruth,
    read_result_trajectories,
)
from lab.links import git_commit
from lab.ros_live import Player, RosMaster, free_port, start_recslam, stop_process
from services.robot.ros1.process import Ros1Config

RESULTS = Path(__file__).resolve().parent / "results"
SECRET = "bench-ros-live-secret-0123456789abcdef"


def run(mode: str, data: Path, robots: list[str], out: Path) -> dict[str, Any]:
    """One run (``folder``, or ``ros1:N``: live with at most N images waiting for tracking):
    cloud, edge and the robots; their numbers."""
    mode, _, pending = mode.partition(":")
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "RECSLAM_SECRET": SECRET, "PYTHONPATH": os.getcwd()}
    cport, eport = free_port(), free_port()
    state = ["--state-dir", str(out / "state")]
    cloud = start_recslam(
        ["cloud", "--listen", f"127.0.0.1:{cport}", "--results", str(out / "results"), *state],
        env,
        out / "cloud.log",
    )
    time.sleep(3.0)
    edge = start_recslam(
        ["edge", "--listen", f"127.0.0.1:{eport}", "--cloud", f"127.0.0.1:{cport}"],
        env,
        out / "edge.log",
    )
    time.sleep(3.0)
    odometry: dict[str, int] = {}
    published: dict[str, int] = {}
    master = RosMaster(out / "ros") if mode == "ros1" else None
    t0 = time.monotonic()
    procs: dict[str, subprocess.Popen] = {}
    try:
        if master is not None:
            env.update(master.env)
        for r in robots:
            common = ["--edge", f"127.0.0.1:{eport}", "--agent-id", r]
            common += ["--stats-out", str(out / f"{r}.json"), "--pose-out", str(out / f"{r}.tum")]
            if mode == "folder":
                args = ["robot", "--dataset", str(data / r), "--rate", "realtime"]
                args += ["--pose-wait", "30", *common]
            else:
                args = ["robot", "--source", "ros1", "--calibration", str(data / r)]
                args += ["--image-topic", f"/{r}/cam0/image_raw", "--imu-topic", f"/{r}/imu0"]
                args += ["--odom-topic", f"/{r}/odom", "--base-frame", f"{r}/base_link", *common]
                args += ["--max-pending-images", pending or "2"]
            procs[r] = start_recslam(args, env, out / f"{r}.log")
        if master is not None:
            time.sleep(5.0)  # the robots' bridges subscribe
            players = {
                r: Player(
                    data / r,
                    Ros1Config(f"/{r}/cam0/image_raw", f"/{r}/imu0", f"/{r}/odom"),
                    master.env,
                )
                for r in robots
            }
            threads = [threading.Thread(target=pl.play) for pl in players.values()]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            for r, player in players.items():
                # a CPU-bound robot may still be tracking its queue: until no Odometry came
                # for 30 s (or 15 minutes passed)
                player.wait_odometry(timeout_s=900.0, settle_s=30.0)
                odometry[r], published[r] = len(player.odometry), len(player.published)
                player.close()
            for p in procs.values():
                stop_process(p, 900.0)
        else:
            for p in procs.values():
                p.wait()
        wall = time.monotonic() - t0
        stop_process(edge, 120.0)
        stop_process(cloud, 300.0)
    finally:
        for p in (edge, cloud, *procs.values()):
            if p.poll() is None:
                p.kill()
        if master is not None:
            master.close()
    (out / "player.json").write_text(
        json.dumps({"odometry": odometry, "published": published, "wall_s": wall})
    )
    return evaluate(mode + (f":{pending}" if pending else ""), data, robots, out)


def evaluate(mode: str, data: Path, robots: list[str], out: Path) -> dict[str, Any]:
    """A finished run's numbers from its folder (``--reuse`` evaluates without running)."""
    mode, _, pending = mode.partition(":")
    player = out / "player.json"
    seen = json.loads(player.read_text()) if player.exists() else {}
    odometry, published = seen.get("odometry", {}), seen.get("published", {})
    est = read_result_trajectories(out / "results")
    refs, _ = load_groundtruth(sorted(est), data)
    ate = compute_joint_ate(refs, est, AteConfig(align=AlignMode.SE3))
    per: dict[str, Any] = {}
    for r in robots:
        s = json.loads((out / f"{r}.json").read_text())
        frames = int(s.get("frames_sent", s.get("frames", 0)))
        poses = s["poses"]
        per[r] = {
            "frames": frames,
            "published": published.get(r, frames),
            "with_pose": int(poses["with_pose"]),
            "odometry": odometry.get(r),
            "median_s": float(poses["median_s"]),
            "p95_s": float(poses["p95_s"]),
            "dropped": int(s.get("faults", {}).get("dropped_backpressure", 0)),
            "wall_s": float(s.get("wall_s", float("nan"))),
        }
    label = mode if mode == "folder" else f"ros1, queue {pending or 2}"
    load = os.getloadavg()[1]  # 5-minute load average: the 2 cores are shared
    return {
        "mode": label,
        "joint_ate_m": float(ate.stats.rmse),
        "wall_s": float(seen.get("wall_s", float("nan"))),
        "load5": load,
        "robots": per,
    }


def write(results: list[dict[str, Any]], path: Path, command: str, commit: str) -> None:
    lines = [
        "# Live ROS 1 robots vs the folder run",
        "",
        f"Command: `{command}` at commit `{commit}`; 3 robots, default synthetic dataset "
        "(60 s, seed 0) at 20 Hz, loopback, 2 cores shared with other jobs. Latency: camera "
        "frame taken (folder) or received from ROS (ros1) -> its pose back at the robot.",
        "",
        "| run | joint ATE [cm] | load (5 min) | robot | frames played | tracked+sent | dropped "
        "| % frames with a metric pose | odometry seen | % frames with odometry "
        "| latency median / p95 [s] | robot wall [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        for r, s in res["robots"].items():
            odo, n = s["odometry"], max(1, s["published"])
            pct = "—" if odo is None else f"{100.0 * odo / n:.1f}"
            lines.append(
                f"| {res['mode']} | {100 * res['joint_ate_m']:.2f} | {res['load5']:.1f} | {r} | "
                f"{s['published']} | {s['frames']} | {s['dropped']} | "
                f"{100.0 * s['with_pose'] / n:.1f} | {'—' if odo is None else odo} | {pct} | "
                f"{s['median_s']:.3f} / {s['p95_s']:.3f} | {s['wall_s']:.0f} |"
            )
    path.write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for i, res in enumerate(results):
        names = list(res["robots"])
        med = [res["robots"][r]["median_s"] for r in names]
        p95 = [res["robots"][r]["p95_s"] for r in names]
        xs = [j + 0.35 * i for j in range(len(names))]
        ax.bar(xs, p95, 0.33, alpha=0.4, label=f"{res['mode']} p95")
        ax.bar(xs, med, 0.33, label=f"{res['mode']} median")
    ax.set_xticks([j + 0.17 for j in range(len(results[0]["robots"]))])
    ax.set_xticklabels(list(results[0]["robots"]))
    ax.set_ylabel("camera -> pose at robot [s]")
    ax.legend(fontsize=7)
    ax.set_title("pose latency: folder vs live ROS 1 (joint ATE in the .md)")
    fig.tight_layout()
    fig.savefig(path.with_suffix(".png"), dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("data/synth"))
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("out/bench_ros_live"))
    ap.add_argument("--out", type=Path, default=RESULTS / "ros_live.md")
    ap.add_argument(
        "--reuse", action="store_true", help="evaluate runs already in --work instead of redoing"
    )
    ap.add_argument(
        "--modes",
        default="folder,ros1:1000,ros1:2",
        help="runs: folder, ros1:N (live, at most N images waiting: 2 is the default robot, "
        "1000 never drops, like the folder run)",
    )
    args = ap.parse_args()
    synth = ["--robots", str(args.robots), "--seconds", "60", "--seed", "0"]
    if not (args.data / "robot0").is_dir():
        subprocess.run(
            [sys.executable, "-m", "recslam", "dataset", "synth", "--out", str(args.data), *synth],
            check=True,
        )
    robots = [f"robot{k}" for k in range(args.robots)]
    modes = args.modes.split(",")
    results = []
    for m in modes:
        work = args.work / m.replace(":", "-")
        done = args.reuse and (work / f"{robots[-1]}.json").exists()
        results.append((evaluate if done else run)(m, args.data, robots, work))
    commit = git_commit()
    command = "python benchmarks/bench_ros_live.py " + " ".join(sys.argv[1:])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write(results, args.out, command.strip(), commit)
    (args.work / "results.json").write_text(json.dumps(results, indent=1))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
