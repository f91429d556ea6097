"""Synthetic generator benchmark: rendering speed on one core, extrapolated to the default set.

Measures (one thread: ``cv2.setNumThreads(1)``, BLAS/OpenMP pools limited to 1):
scene + texture atlas build time; per-frame time of the renderer alone (752x480, along robot
0's flight) split into ray casting + texture lookup and sensor effects; PNG encoding; and the
full pipeline (``generate_dataset``: render, IMU, ground truth, EuRoC writing) on a short
1-robot set. Extrapolates the default 3 robots x 60 s (3600 frames).

Run: ``.venv/bin/python benchmarks/bench_synth.py [--frames 200]``; writes
``benchmarks/results/synth.md``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from common.data.synth import EUROC_CAM0, SynthConfig, generate_dataset  # noqa: E402
from common.data.synth.render import Renderer  # noqa: E402
from common.data.synth.scene import vicon_room  # noqa: E402
from common.data.synth.textures import build_atlas  # noqa: E402
from common.data.synth.trajectory import make_trajectories  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "synth.md"
DEFAULT_FRAMES = 3 * 60 * 20


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="frames for the render timing")
    parser.add_argument(
        "--pipeline-seconds",
        type=float,
        default=10.0,
        help="length of the 1-robot end-to-end run [s]",
    )
    args = parser.parse_args()
    cv2.setNumThreads(1)

    t0 = time.perf_counter()
    scene = vicon_room()
    atlas = build_atlas(scene, seed=0)
    atlas_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    renderer = Renderer(scene, atlas, EUROC_CAM0)
    setup_s = time.perf_counter() - t0
    traj = make_trajectories(scene, 3, 60.0, 0)[0]
    times = np.linspace(0.0, 60.0, args.frames)
    poses = traj.evaluate(times).T_world_cam()
    rng = np.random.default_rng(0)
    renderer.render(poses[0], 0.0, rng)  # warm-up

    cast, full, png = [], [], []
    for T, t in zip(poses, times, strict=True):
        a = time.perf_counter()
        renderer.render_radiance(T)
        b = time.perf_counter()
        img = renderer.render(T, float(t), rng)
        c = time.perf_counter()
        ok, _ = cv2.imencode(".png", img)
        d = time.perf_counter()
        assert ok
        cast.append(b - a)
        full.append(c - b)
        png.append(d - c)
    render_ms = 1e3 * np.median(full)
    render_fps = 1e3 / render_ms
    per_frame_ms = render_ms + 1e3 * np.median(png)

    with tempfile.TemporaryDirectory() as tmp:
        cfg = SynthConfig(
            robots=1, seconds=args.pipeline_seconds, seed=0, progress=False, contact_sheet=False
        )
        t0 = time.perf_counter()
        summary = generate_dataset(Path(tmp) / "synth", cfg)
        pipe_s = time.perf_counter() - t0
    pipe_frames = sum(s.frames for s in summary.sequences)
    pipe_fps = pipe_frames / (pipe_s - atlas_s)  # excludes the (once per run) atlas build

    rows = [
        ("texture atlas build (once per run)", f"{atlas_s:.1f} s"),
        ("renderer setup (pixel rays, once)", f"{1e3 * setup_s:.0f} ms"),
        ("ray cast + trilinear lookup, median", f"{1e3 * np.median(cast):.1f} ms"),
        (
            "full frame render (+ blur, vignetting, exposure, noise), median / p95",
            f"{render_ms:.1f} / {1e3 * np.percentile(full, 95):.1f} ms",
        ),
        ("PNG encode, median", f"{1e3 * np.median(png):.1f} ms"),
        ("render rate", f"{render_fps:.1f} frames/s"),
        ("render + PNG rate", f"{1e3 / per_frame_ms:.1f} frames/s"),
        (
            f"end-to-end generate_dataset, 1 robot x {args.pipeline_seconds:g} s ({pipe_frames} "
            "frames, excl. atlas)",
            f"{pipe_fps:.1f} frames/s ({pipe_s:.1f} s total)",
        ),
        (
            "extrapolated default set (3 robots x 60 s = 3600 frames)",
            f"{(DEFAULT_FRAMES / pipe_fps + atlas_s) / 60:.1f} min",
        ),
    ]
    lines = [
        "# Synthetic dataset generator: speed on one core",
        "",
        f"`benchmarks/bench_synth.py --frames {args.frames}`; {platform.processor() or '?'}, "
        f"Python {platform.python_version()}, OpenCV {cv2.__version__}, one thread. "
        "752x480 frames along robot 0's flight (seed 0). Load average at the end "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (shared machine: other jobs slow "
        "these numbers down).",
        "",
        "| what | value |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in rows],
        "",
    ]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
