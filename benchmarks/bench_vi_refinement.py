"""VI refinements (full visual-inertial BA over every keyframe) with the Schur solver vs gtsam.

The edge VIO re-runs its visual-inertial initialisation as a full BA over every keyframe at
map ages 4/7/10/15/25/35/50 s (``VioManager.run_vi_init``, 40–240 keyframes). For each robot
of the cached pipeline inputs (``benchmarks/bench_vio_pipeline.py`` writes them), the VIO
runs twice on the same frames: with ``LocalBAConfig.schur_max_keyframes`` 50 (windows of more
free keyframes go to gtsam's LM, the former default) and with the default (every window by
the Schur-complement solver, whose reduced camera system is sparse above 20 keyframes). CPU
time of each ``run_vi_init`` call, VIO CPU per frame, ATE.

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_vi_refinement.py
[--inputs synth_seed1/robot0 synth_default/robot2]``; writes
``benchmarks/results/vi_refinement.md``.
"""

from __future__ import annotations

import argparse
import logging
import platform
import time
from dataclasses import replace
from pathlib import Path

from common.data.euroc import EurocSequence
from lab.vio_replay import DecodedFrame, ReplayScore, load_decoded, score
from services.edge.vio.manager import VioManager
from services.edge.vio.state import VioMap
from services.edge.vio.types import VioConfig

log = logging.getLogger("bench_vi_refinement")
RESULTS = Path(__file__).resolve().parent / "results" / "vi_refinement.md"


class _TimedVio(VioManager):
    """VioManager that records the CPU time of each VI initialisation / refinement."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.vi_cpu_s: list[float] = []

    def run_vi_init(self, vmap: VioMap) -> bool:
        t0 = time.process_time()
        try:
            return super().run_vi_init(vmap)
        finally:
            self.vi_cpu_s.append(time.process_time() - t0)


def _run(
    frames: list[DecodedFrame], seq: EurocSequence, options: VioConfig, name: str
) -> tuple[list[float], float, ReplayScore]:
    vio = _TimedVio(seq.cam0, seq.imu, options, name)
    results = []
    t0 = time.process_time()
    for f in frames:
        if len(f.imu_t_ns):
            vio.feed_imu(f.imu_t_ns, f.gyro, f.accel)
        results.append(vio.feed_frame(f.obs))
    cpu_ms = (time.process_time() - t0) * 1e3 / max(len(frames), 1)
    return vio.vi_cpu_s, cpu_ms, score(results, seq.groundtruth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", nargs="+", default=["synth_seed1/robot0", "synth_default/robot2"])
    ap.add_argument("--data", type=Path, default=Path("/tmp"), help="rendered datasets' parent")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/vio_pipeline_cache"))
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=RESULTS, help="markdown table written")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    default = VioConfig()
    variants = {
        "gtsam > 50 keyframes": replace(
            default, local_ba=replace(default.local_ba, schur_max_keyframes=50)
        ),
        "schur (sparse)": default,
    }
    rows = []
    for item in args.inputs:
        dataset, robot = item.split("/")
        seq = EurocSequence(args.data / dataset / robot)
        frames = load_decoded(args.cache / f"{dataset}_{robot}_{args.seconds:g}s.npz")
        for label, options in variants.items():
            vi_cpu, cpu_ms, s = _run(frames, seq, options, robot)
            rows.append((item, label, vi_cpu, cpu_ms, s))
            print(item, label, [round(t, 2) for t in vi_cpu], f"{cpu_ms:.1f} ms/frame", s)
    lines = [
        "# VI refinements: Schur solver with a sparse reduced camera system vs gtsam",
        "",
        f"Cached pipeline inputs (`{args.cache}`), first {args.seconds:g} s, one process "
        "(`benchmarks/bench_vi_refinement.py`, OPENBLAS_NUM_THREADS=1). VI init/refinement "
        "CPU = process time of each `VioManager.run_vi_init` (the full BA dominates it); VIO "
        "CPU per frame over the whole run. The machine has 2 cores shared with other jobs.",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}.",
        "",
        "| input | big windows by | VI init/refinements CPU [s] | VIO CPU [ms/frame] "
        "| ATE SE(3) [cm] | ATE Sim(3) [cm] | scale error [%] |",
        "|---|---|---|---|---|---|---|",
    ]
    for item, label, vi_cpu, cpu_ms, s in rows:
        lines.append(
            f"| {item} | {label} | {' / '.join(f'{t:.2f}' for t in vi_cpu)} | {cpu_ms:.1f} "
            f"| {s.ate_se3_m * 100:.2f} | {s.ate_sim3_m * 100:.2f} | {s.scale_error * 100:+.2f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
