"""How firmly each flight's IMU fixes the map's scale, against the scale error the map ends with.

Run: ``.venv/bin/python benchmarks/bench_scale_observability.py --ab RECORDING:DATASET [...]
[--jobs 2]``; writes ``benchmarks/results/scale_observability.md`` and
``scale_observability.png``.

Each recording (``recslam demo --record-uplink``) is replayed through the cloud service's own
core without MBP (:func:`lab.table3.replay`, modelled schedule, deterministic). The last full
BA (at shutdown, the final map) is captured from the replay's solve function; on its result
:func:`lab.scale_observability.scale_profile` sweeps the map's scale with the poses held and
solves velocities and biases against the IMU factors alone: the scale the IMU prefers for the
map's shape and the scale's standard deviation from the IMU (sigma), once with the noise the
full BA assumes (``FullBAConfig.imu_noise_scale``) and once with the IMU's calibrated noise.
The map's actual scale error is the Sim(3) alignment's scale of the final trajectories to
the ground truth (map size / true size - 1). A run whose error is a few sigmas of the
calibrated noise has scale information the estimate did not use; one within about a sigma has
the error its flight allows.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import functools
import logging
import platform
import time
from pathlib import Path

import numpy as np

from common.evaluation.metrics import AlignMode
from common.evaluation.results import load_groundtruth
from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
from lab.links import git_commit
from lab.scale_observability import nominal, scale_profile
from lab.table3 import joint_ate, replay_recording, service_config
from services.cloud.core_actions import SolveKind, SolveRequest, SolveResult, solve
from services.cloud.optimization.full_ba import FullBAProblem, FullBAResult
from services.cloud.runner import find_camera

log = logging.getLogger("bench_scale_observability")
RESULTS = Path(__file__).resolve().parent / "results"


class _LastFullBA:
    """The service's solve, keeping the last full BA's request and result."""

    def __init__(self) -> None:
        self.last: tuple[SolveRequest, FullBAResult] | None = None

    def __call__(self, request: SolveRequest) -> SolveResult:
        result = solve(request)
        if request.kind is SolveKind.FULL_BA and isinstance(result, FullBAResult):
            self.last = (request, result)
        return result


@functools.cache
def _vocabulary() -> Vocabulary:
    return Vocabulary.load(DEFAULT_VOCABULARY_PATH)


def run_one(rec: Path, data: Path, span: float) -> dict:
    """Replay ``rec`` without MBP; the final map's scale profile and its scale error."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    cfg = service_config(False)
    capture = _LastFullBA()
    camera = find_camera(None, data)
    r = replay_recording(rec, camera, _vocabulary(), cfg, "no MBP", full_ba=True, solve_fn=capture)
    if capture.last is None:
        raise RuntimeError(f"{rec}: the replay ran no full BA")
    request, result = capture.last
    problem = request.problem
    assert isinstance(problem, FullBAProblem) and request.full_ba is not None
    if problem.imu is None:
        raise RuntimeError(f"{rec}: the last full BA had no IMU factors")
    full_ba = dataclasses.replace(request.full_ba, incremental=False)
    T, fixed = result.T_world_body, problem.fixed
    assumed = scale_profile(T, fixed, problem.imu, full_ba, span=span)
    calibrated = scale_profile(T, fixed, problem.imu, nominal(full_ba), span=span)
    refs, _ = load_groundtruth(sorted(r.trajectories), data)
    se3 = joint_ate(refs, r.trajectories)
    sim = joint_ate(refs, r.trajectories, AlignMode.SIM3)
    row = {
        "recording": str(rec),
        "dataset": data.name,
        "maps": len(r.maps),
        "keyframes": int(problem.keys.shape[0]),
        "pairs": assumed.pairs,
        "noise_scale": full_ba.imu_noise_scale,
        "joint_m": None if se3 is None else se3.stats.rmse,
        "sim3_m": None if sim is None else sim.stats.rmse,
        # map size / true size - 1 (Sim(3) maps the estimate onto the truth with ``scale``).
        "scale_error": None if sim is None else 1.0 / sim.transform.scale - 1.0,
        "best_assumed": assumed.best_scale - 1.0,
        "sigma_assumed": assumed.sigma,
        "best_calibrated": calibrated.best_scale - 1.0,
        "sigma_calibrated": calibrated.sigma,
        "profile": (calibrated.scales.tolist(), calibrated.costs.tolist()),
    }
    log.info("%s: %s", rec, {k: v for k, v in row.items() if k != "profile"})
    return row


def _pct(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{100 * x:+.{digits}f}"


def _cm(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def table(rows: list[dict]) -> list[str]:
    lines = [
        "| recording | dataset | maps | keyframes | IMU factors | map scale error % "
        "| IMU's optimum % | sigma, assumed noise % | sigma, calibrated noise % "
        "| error / sigma (calibrated) | joint ATE cm | joint Sim(3) cm |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = r["scale_error"]
        ratio = "–" if err is None else f"{abs(err) / r['sigma_calibrated']:.1f}"
        lines.append(
            f"| `{Path(r['recording']).parent.name}/{Path(r['recording']).name}` "
            f"| {r['dataset']} | {r['maps']} | {r['keyframes']} | {r['pairs']} "
            f"| {_pct(err)} | {_pct(r['best_assumed'], 3)} "
            f"| {100 * r['sigma_assumed']:.3f} | {100 * r['sigma_calibrated']:.3f} | {ratio} "
            f"| {_cm(r['joint_m'])} | {_cm(r['sim3_m'])} |"
        )
    return lines


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10.5, 4.0))
    names = [f"{Path(r['recording']).parent.name}/{Path(r['recording']).stem}" for r in rows]
    x = np.arange(len(rows))
    err = [100 * abs(r["scale_error"] or np.nan) for r in rows]
    ax.bar(x - 0.27, err, 0.27, label="|map scale error|", color="C3")
    ax.bar(x, [100 * r["sigma_calibrated"] for r in rows], 0.27, label="sigma, calibrated IMU")
    ax.bar(x + 0.27, [100 * r["sigma_assumed"] for r in rows], 0.27, label="sigma, assumed")
    ax.set_yscale("log")
    ax.set_xticks(x, names, rotation=40, ha="right", fontsize=7)
    ax.set_ylabel("%")
    ax.set_title("scale error vs the IMU's scale sigma")
    ax.legend(fontsize=7)
    for i, r in enumerate(rows):
        s, c = (np.asarray(v) for v in r["profile"])
        bx.plot(100 * (s - 1), c - c.min(), "o-", ms=3, label=names[i], color=f"C{i % 10}")
    bx.set_xlabel("map scaled by, %")
    bx.set_ylabel("inertial-only cost - min (calibrated noise)")
    bx.set_title("inertial-only cost against the map's scale")
    bx.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _job(spec: str, span: float) -> dict:
    rec, data = spec.split(":", 1)
    return run_one(Path(rec), Path(data), span)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--ab", action="append", required=True, metavar="RECORDING:DATASET", help="repeatable"
    )
    ap.add_argument("--span", type=float, default=0.01, help="scales swept: 1 ± SPAN")
    ap.add_argument("--jobs", type=int, default=1, help="replays run in parallel (processes)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the md and png")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    t0 = time.perf_counter()
    with concurrent.futures.ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(functools.partial(_job, span=args.span), args.ab))
    lines = [
        "# How firmly the IMU fixes each map's scale",
        "",
        f"Command: `benchmarks/bench_scale_observability.py "
        f"{' '.join('--ab ' + a for a in args.ab)} --span {args.span:g} --jobs {args.jobs}`; "
        f"commit {git_commit()}; "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.machine()}, "
        f"{time.perf_counter() - t0:.0f} s in all. Replays without MBP through the service's "
        "core (deterministic); the final map's last full BA swept over its scale with the "
        "IMU factors alone (the script's docstring). Map scale error: map size / true size - "
        "1 (Sim(3) alignment of the final trajectories). IMU's optimum: the scale the IMU "
        "prefers for the map's shape, relative to the map (assumed noise). Sigma: the scale's "
        "standard deviation from the IMU alone, with the noise the full BA assumes "
        f"(x{rows[0]['noise_scale']:g} the calibration) and with the IMU's calibrated noise.",
        "",
        *table(rows),
        "",
        "![scale_observability.png](scale_observability.png)",
        "",
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scale_observability.md").write_text("\n".join(lines))
    plot(rows, args.out / "scale_observability.png")
    log.info("wrote %s", args.out / "scale_observability.md")


if __name__ == "__main__":
    main()
