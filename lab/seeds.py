"""How the whole job varies over the generator's seeds: ``recslam experiment seeds``.

For each seed, the project's synthetic dataset of that seed (built once under ``data_root``,
reused after) runs through the whole job as ``recslam demo --no-dashboard`` runs it (cloud,
edge and robots as processes, :func:`lab.links.run_job`), and the run's report gives joint and
per-robot ATE, the maps at the end, merges, loops, lost frames and failed services.
:func:`lab.seeds_report.write_seeds` turns the runs into ``seeds.md`` (one row per seed, the
median and worst against issue 17's targets) and ``seeds.png``; :mod:`lab.seeds_run` runs the
sweep. With ``from_runs`` the runs already under ``out`` are read instead (a sweep resumed, or
runs made by hand, each ``out/<name>/report.json`` next to the ``dataset.json`` it names).

Harder worlds (issue 17, :class:`GeneratorOptions`): ``--flight``, ``--world``,
``--exposure-steps`` and ``--motion-blur-ms`` are passed to the generator; the datasets and
runs of such a sweep are named ``<tag>-seed-<s>`` (``tag``, e.g. ``figure8+aggressive_vicon``)
and its tables are ``seeds_hard.md`` / ``.json`` / ``.png`` (``SeedsConfig.name``), whose header
states the generator settings of its runs, so they never mix with the default sweep's.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import RecslamError
from lab.loop_scoring import LoopCriterion

log = logging.getLogger(__name__)


class SeedsError(RecslamError):
    """Bad sweep arguments, or no runs to report."""


@dataclass(frozen=True)
class SeedTargets:
    """Issue 17's targets over the seeds: median and worst joint ATE, every robot, one map."""

    median_joint_m: float = 0.015
    worst_joint_m: float = 0.02
    robot_m: float = 0.05


@dataclass(frozen=True)
class GeneratorOptions:
    """What the sweep's datasets are built with beyond robots, seconds and seed (the options
    of ``recslam dataset synth`` of the same names); the defaults are the default dataset."""

    flight: str = "ring"
    world: str = "vicon"
    exposure_steps: bool = False
    motion_blur_ms: float = 0.0

    def __post_init__(self) -> None:
        from common.data.synth.flights import parse_flight
        from common.data.synth.trajectory import TrajectoryError
        from common.data.synth.worlds import WORLDS

        try:
            object.__setattr__(self, "flight", parse_flight(self.flight).name)
        except TrajectoryError as exc:
            raise SeedsError(str(exc)) from None
        if self.world not in WORLDS:
            raise SeedsError(f"--world {self.world!r}: unknown (known: {', '.join(WORLDS)})")
        if self.motion_blur_ms < 0:
            raise SeedsError(f"--motion-blur-ms {self.motion_blur_ms:g}: must be >= 0")

    @property
    def is_default(self) -> bool:
        return self == GeneratorOptions()

    @property
    def tag(self) -> str:
        """``""`` for the defaults, else e.g. ``figure8+aggressive_hall_exposure_blur8ms``."""
        if self.is_default:
            return ""
        parts = [self.flight, self.world]
        if self.exposure_steps:
            parts.append("exposure")
        if self.motion_blur_ms:
            parts.append(f"blur{self.motion_blur_ms:g}ms")
        return "_".join(parts)

    def folder(self, seed: int) -> str:
        """Name of the dataset and run folders of ``seed``."""
        return f"{self.tag}-seed-{seed}" if self.tag else f"seed-{seed}"

    def settings(self) -> dict[str, Any]:
        """As :func:`common.data.synth.dataset_settings` states them."""
        return {
            "flight": self.flight,
            "world": self.world,
            "trajectory_files": (),
            "exposure_steps": self.exposure_steps,
            "motion_blur_ms": float(self.motion_blur_ms),
        }


@dataclass(frozen=True)
class SeedsConfig:
    """One sweep: ``seeds``, each a dataset of ``robots`` x ``seconds`` under ``data_root``
    (``seed-<s>``, or ``<tag>-seed-<s>`` with harder ``generator`` options), each run into
    ``out/`` under the same name; tables ``name``.md/.json/.png (default ``seeds``, or
    ``seeds_hard`` with harder options) also copied to ``results``."""

    seeds: tuple[int, ...]
    out: Path
    data_root: Path = Path("data/seeds")
    robots: int = 3
    seconds: float = 60.0
    results: Path | None = None
    rate: str = "realtime"
    timeout_s: float = 2400.0
    from_runs: bool = False
    command: str = ""
    targets: SeedTargets = SeedTargets()
    generator: GeneratorOptions = GeneratorOptions()
    name: str = ""

    @property
    def table_name(self) -> str:
        """Base name of the tables: ``name``, else ``seeds`` / ``seeds_hard``."""
        return self.name or ("seeds" if self.generator.is_default else "seeds_hard")


def parse_seeds(text: str) -> tuple[int, ...]:
    """``"0-9"``, ``"0,3,7"`` or a mix (``"0-2,5"``) as sorted distinct seeds."""
    seeds: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1) if not part.startswith("-") else ("", part)
                lo, hi = int(a), int(b)
                if hi < lo:
                    raise ValueError(part)
                seeds.update(range(lo, hi + 1))
            else:
                seeds.add(int(part))
        except ValueError:
            raise SeedsError(f"--seeds {text!r}: {part!r} is not a seed or a range a-b") from None
    if not seeds or min(seeds) < 0:
        raise SeedsError(f"--seeds {text!r}: give seeds >= 0, e.g. 0-9")
    return tuple(sorted(seeds))


def ensure_dataset(
    folder: Path,
    robots: int,
    seconds: float,
    seed: int,
    generator: GeneratorOptions = GeneratorOptions(),
) -> bool:
    """The synthetic dataset of ``seed`` in ``folder``: built if missing (True), reused if it
    was built with these settings (False); SeedsError if it holds something else."""
    from common.data.synth import SynthConfig, SynthError, dataset_settings, generate_dataset
    from common.data.synth.render import EffectsConfig

    have = dataset_settings(folder)
    if have is not None:
        if (have["robots"], have["seconds"], have["seed"]) != (robots, float(seconds), seed):
            raise SeedsError(
                f"{folder} holds robots {have['robots']} x {have['seconds']} s, seed "
                f"{have['seed']}, not {robots} x {seconds:g} s, seed {seed}: remove it or "
                "choose another --data-root"
            )
        want = generator.settings()
        if any(have[k] != v for k, v in want.items()):
            got = {k: have[k] for k in want}
            raise SeedsError(
                f"{folder} was built with {got}, not {want}: remove it or choose another "
                "--data-root"
            )
        return False
    config = SynthConfig(
        robots=robots,
        seconds=seconds,
        seed=seed,
        flight=generator.flight,
        world=generator.world,
        effects=EffectsConfig(
            exposure_steps=generator.exposure_steps, motion_blur_ms=generator.motion_blur_ms
        ),
    )
    try:
        generate_dataset(folder, config)
    except SynthError as exc:
        raise SeedsError(f"{folder}: {exc}") from None
    return True


def read_report(folder: Path) -> dict[str, Any]:
    """The numbers of one run folder (``report.json`` of ``recslam demo``)."""
    path = folder / "report.json"
    try:
        rep = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SeedsError(f"{path}: not a run report ({exc})") from None
    robots = rep.get("robots", {})
    per_robot = {n: r.get("ate_rmse_m") for n, r in sorted(robots.items())}
    m = rep.get("map", {})
    joint = rep.get("ate", {}).get("joint_rmse_m")
    return {
        "folder": str(folder),
        "joint_m": joint if rep.get("ate", {}).get("joint_frame") else None,
        "per_robot_m": per_robot,
        "worst_robot_m": max((v for v in per_robot.values() if v is not None), default=None),
        "maps": len(m.get("maps", [])),
        "merges": m.get("merges"),
        "loops": m.get("loops"),
        "frames_lost": sum(int(r.get("frames_lost", 0)) for r in robots.values()),
        "failed": list(rep.get("failed", [])),
        "camera_s": rep.get("camera_s"),
        "wall_s": rep.get("wall_s"),
        "keyframes_uplinked": m.get("keyframes_uplinked"),
        "keyframes_kept": m.get("keyframes_after_mbp"),
        "mbp_passes": m.get("mbp_passes"),
    }


def _median(values: Sequence[float]) -> float:
    v = sorted(values)
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def summarize(runs: dict[str, dict[str, Any]], targets: SeedTargets) -> dict[str, Any]:
    """Median / worst joint ATE, worst robot, runs with one map, and the verdicts. A run
    whose robots did not end in one map has no joint ATE and fails the one-map target."""
    joints = [r["joint_m"] for r in runs.values() if r["joint_m"] is not None]
    robots = [r["worst_robot_m"] for r in runs.values() if r["worst_robot_m"] is not None]
    one_map = sum(1 for r in runs.values() if r["maps"] == 1)
    median = _median(joints) if joints else None
    worst = max(joints) if len(joints) == len(runs) and joints else None
    worst_robot = max(robots) if robots else None
    failures = sum(1 for r in runs.values() if r["failed"] or r["frames_lost"])
    checked = [r for r in runs.values() if r.get("constraints") is not None]
    return {
        "runs": len(runs),
        "median_joint_m": median,
        "worst_joint_m": worst,
        "worst_robot_m": worst_robot,
        "one_map": one_map,
        "failures": failures,
        "constraints": sum(r["constraints"] for r in checked) if checked else None,
        "wrong_constraints": sum(r["wrong_constraints"] for r in checked) if checked else None,
        "met": {
            "median": median is not None and median <= targets.median_joint_m,
            "worst": worst is not None and worst <= targets.worst_joint_m,
            "robots": worst_robot is not None and worst_robot <= targets.robot_m,
            "one_map": one_map == len(runs),
        },
    }


def find_runs(out: Path) -> dict[str, Path]:
    """``{name: folder}`` of the finished runs directly under ``out``."""
    return {p.parent.name: p.parent for p in sorted(Path(out).glob("*/report.json"))}


def scale_check(report_dir: Path, data: Path | None) -> dict[str, float | None]:
    """Joint ATE after a Sim(3) alignment and its scale, of the trajectories the cloud wrote
    (``run/results/trajectories/*.tum``) against the ground truth of the dataset ``data`` it
    played: how much of the run's SE(3) joint ATE is one error of the whole map's scale. None
    where not computable."""
    from common.evaluation.alignment import AlignMode
    from common.evaluation.metrics import AteConfig, compute_joint_ate
    from common.evaluation.results import load_groundtruth
    from common.evaluation.tum import read_tum

    none: dict[str, float | None] = {"sim3_joint_m": None, "scale": None}
    tum = sorted((report_dir / "run" / "results" / "trajectories").glob("*.tum"))
    if not tum or data is None:
        return none
    try:
        est = {p.stem: read_tum(p) for p in tum}
        refs, _ = load_groundtruth(sorted(est), data)
        res = compute_joint_ate({n: refs[n] for n in est}, est, AteConfig(align=AlignMode.SIM3))
    except RecslamError as exc:
        log.info("%s: no Sim(3) check (%s)", report_dir, exc)
        return none
    return {"sim3_joint_m": res.stats.rmse, "scale": res.transform.scale}


def constraint_check(
    report_dir: Path, data: Path | None, criterion: LoopCriterion | None = None
) -> dict[str, float | int | None]:
    """Every loop and merge constraint the cloud ended with (its state under ``run/state``)
    against the ground truth of the dataset ``data``: a constraint ``T_a_b`` (body b in body
    a) is *wrong* when it is farther than ``criterion``'s thresholds (0.3 m, 10 deg) from
    ``inv(T_world_a) T_world_b`` of the truth (a false merge or loop). Keys:
    ``constraints``, ``wrong_constraints``, ``max_constraint_err_m`` / ``_deg``; None where
    not computable (no state, no ground truth)."""
    criterion = criterion or LoopCriterion()
    from common.evaluation.results import load_groundtruth
    from lab.loop_scoring import Detection, GroundTruthPoses, KeyframeInfo, score_detection
    from services.cloud.store.persistence import CloudStore

    none: dict[str, float | int | None] = dict.fromkeys(
        ("constraints", "wrong_constraints", "max_constraint_err_m", "max_constraint_err_deg")
    )
    state = report_dir / "run" / "state" / "cloud"
    if data is None or not (state / "cloud.sqlite").is_file():
        return none
    try:
        with CloudStore(state) as store:
            atlas, names = store.load(), {a: n for a, (n, _e, _m) in store.agents().items()}
        refs, _ = load_groundtruth(sorted(set(names.values())), data)
    except RecslamError as exc:
        log.info("%s: no constraint check (%s)", report_dir, exc)
        return none
    # Identity extrinsic: body poses only (constraints are between keyframe bodies).
    gt = GroundTruthPoses(refs, np.eye(4), criterion.max_gt_gap_s)
    info = {
        k.key: KeyframeInfo(k.key, names[k.agent_id], k.timestamp)
        for k in (atlas.keyframe(key) for key in atlas.keyframe_keys())
    }
    # T_a_b: body b in body a, the detection's T_match_query with b as the query.
    detections = (Detection(e.key_b, e.key_a, e.T_a_b, True, "loop", "", 0) for e in atlas.loops())
    scores = [score_detection(d, info, gt, criterion) for d in detections]
    errors = [(s.trans_err_m, s.rot_err_deg, s.true) for s in scores]
    judged = [(m, d, ok) for m, d, ok in errors if m is not None and d is not None]
    return {
        "constraints": len(judged),
        "wrong_constraints": sum(1 for _, _, ok in judged if not ok),
        "max_constraint_err_m": max((m for m, _, _ in judged), default=None),
        "max_constraint_err_deg": max((d for _, d, _ in judged), default=None),
    }


def dataset_folder(report_dir: Path) -> Path | None:
    """The dataset folder a run played, from the command line its first robot's log starts
    with (``--dataset FOLDER/robotK``)."""
    for log_file in sorted((report_dir / "run" / "logs").glob("robot*.log")):
        try:
            words = log_file.read_text().splitlines()[0].split()
        except (OSError, IndexError):
            continue
        if "--dataset" in words:
            return Path(words[words.index("--dataset") + 1]).parent
        break
    return None


def dataset_of(folder: Path | None) -> dict[str, Any] | None:
    """Robots, seconds and seed of the synthetic dataset in ``folder``, and its issue-17
    generator settings where they are not the defaults; None if not synthetic (or not
    found)."""
    from common.data.synth import dataset_settings

    have = None if folder is None else dataset_settings(folder)
    if have is None:
        return None
    out = {k: have[k] for k in ("robots", "seconds", "seed")}
    defaults = GeneratorOptions().settings()
    if any(have.get(k, v) != v for k, v in defaults.items()):
        out["generator"] = {k: have[k] for k in defaults} | {
            "trajectory_files": list(have["trajectory_files"])
        }
    return out


def fmt_cm(v: float | None) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f}"
