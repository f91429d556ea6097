"""Evaluate a result folder against ground truth and write ``ate.json``, ``ate.md`` and plots.

:func:`evaluate_run` is what ``recslam eval`` calls: read ``RESULT_DIR/trajectories`` (see
:mod:`common.evaluation.results`), load ground truth, compute joint and per-agent ATE and
per-agent RPE, write the report files into the output folder.

A joint ATE is meaningful only when every agent is in one map frame. When the result folder's
``cloud_maps.json`` (written by the cloud, :data:`~common.evaluation.results.MAPS_FILE`) says
the maps did not merge, ``ate.md`` has no "joint" row but a line saying so, and ``ate.json``
has ``"joint_frame": false`` with the cloud's note (the joint numbers stay in ``joint`` for
whoever wants to look at them).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from common.evaluation.alignment import AlignMode, SimilarityTransform
from common.evaluation.errors import AlignmentError, MetricsError, ResultFolderError
from common.evaluation.metrics import (
    AteConfig,
    AteResult,
    DeltaUnit,
    JointAteResult,
    RpeConfig,
    RpeResult,
    compute_joint_ate,
    compute_rpe,
)
from common.evaluation.results import (
    EVAL_DIR,
    MAPS_FILE,
    load_groundtruth,
    read_result_trajectories,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalConfig:
    """Settings of a run evaluation.

    ``ate``: alignment and association for ATE (default SE(3), 10 ms). ``rpe``: RPE settings
    (default 1 m consecutive pairs, no alignment beyond ``ate.align``'s scale if Sim(3));
    ``rpe_enabled`` turns RPE off. ``plots``: write PNGs.
    """

    ate: AteConfig = field(default_factory=AteConfig)
    rpe: RpeConfig = field(default_factory=lambda: RpeConfig(delta=1.0, unit=DeltaUnit.METERS))
    rpe_enabled: bool = True
    plots: bool = True


@dataclass(frozen=True)
class EvalReport:
    """What :func:`evaluate_run` computed and where it wrote it."""

    joint: JointAteResult
    rpe: dict[str, RpeResult | None]
    groundtruth_files: dict[str, Path]
    out_dir: Path
    files: list[Path]
    maps: MapFrames | None = None

    @property
    def joint_frame(self) -> bool:
        """True unless the cloud said the agents' maps did not merge."""
        return self.maps is None or self.maps.joint_frame


@dataclass(frozen=True)
class MapFrames:
    """What the cloud's ``cloud_maps.json`` says: which map each agent is in."""

    joint_frame: bool
    maps_of_agents: dict[str, int]
    note: str

    def sentence(self) -> str:
        """One line for the report: the maps did (not) merge, and which agent is in which."""
        if self.joint_frame:
            return "All agents are in one map frame."
        groups: dict[int, list[str]] = {}
        for agent, m in sorted(self.maps_of_agents.items()):
            groups.setdefault(m, []).append(agent)
        where = "; ".join(f"map {m}: {', '.join(a)}" for m, a in sorted(groups.items()))
        return (
            f"**Maps did not merge** ({len(groups)} maps: {where}): no joint ATE, the agents' "
            "trajectories are in different map frames."
        )


def read_map_frames(result_dir: Path | str) -> MapFrames | None:
    """``RESULT_DIR/cloud_maps.json`` as :class:`MapFrames`; None when the folder has none
    (not a cloud's result folder) or it cannot be read (logged)."""
    path = Path(result_dir) / MAPS_FILE
    if not path.is_file():
        return None
    try:
        info = json.loads(path.read_text())
        robots = {str(a): int(m) for a, m in dict(info.get("robots", {})).items()}
        return MapFrames(bool(info["joint_frame"]), robots, str(info.get("note", "")))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        log.warning("%s: cannot read which map each agent is in (%s)", path, exc)
        return None


def _ate_block(res: AteResult) -> dict[str, object]:
    return {
        "stats_m": res.stats.as_dict(),
        "rot_stats_deg": res.rot_stats.as_dict(),
        "transform": res.transform.as_dict(),
        "scale_error": res.scale_error,
    }


def _rpe_block(res: RpeResult | None) -> dict[str, object] | None:
    if res is None:
        return None
    return {
        "delta": res.delta,
        "unit": res.unit.value,
        "pairs": int(res.pairs.shape[0]),
        "trans_stats_m": res.trans_stats.as_dict(),
        "rot_stats_deg": res.rot_stats.as_dict(),
    }


def report_dict(
    joint: JointAteResult,
    rpe: dict[str, RpeResult | None] | None = None,
    config: EvalConfig | None = None,
    sources: dict[str, str] | None = None,
    maps: MapFrames | None = None,
) -> dict[str, object]:
    """JSON-ready summary (schema in the module docstring of ``recslam.commands.evaluate``;
    ``joint_frame`` and ``maps_note`` from ``maps``)."""
    cfg = config or EvalConfig()
    rpe = rpe or {}
    agents = {}
    for agent, ind in joint.individual.items():
        agents[agent] = {
            "n_est": ind.n_est,
            "n_ref": ind.n_ref,
            "n_matched": ind.stats.count,
            "individual": _ate_block(ind),
            "under_joint": {
                "stats_m": joint.under_joint[agent].stats.as_dict(),
                "rot_stats_deg": joint.under_joint[agent].rot_stats.as_dict(),
            },
            "rpe": _rpe_block(rpe.get(agent)),
        }
    return {
        "align": joint.mode.value,
        "n_align": cfg.ate.n_align,
        "max_diff_ns": cfg.ate.association.max_diff_ns,
        "offset_ns": cfg.ate.association.offset_ns,
        "sources": sources or {},
        "joint": {
            "agents": list(joint.under_joint),
            "stats_m": joint.stats.as_dict(),
            "rot_stats_deg": joint.rot_stats.as_dict(),
            "transform": joint.transform.as_dict(),
            "scale_error": joint.scale_error,
        },
        "joint_frame": maps is None or maps.joint_frame,
        "maps_note": maps.note if maps is not None else "",
        "agents": agents,
    }


def _f(x: float) -> str:
    return f"{x:.4f}"


def markdown_table(
    joint: JointAteResult,
    rpe: dict[str, RpeResult | None] | None = None,
    maps: MapFrames | None = None,
) -> str:
    """ATE table (one row per agent aligned alone, then the joint row) in markdown; when
    ``maps`` says the maps did not merge, no joint row and no "under joint" column values,
    but a line saying so."""
    rpe = rpe or {}
    mode = joint.mode.value
    lines = [
        f"ATE [m] after {mode} alignment; 'joint' = all agents aligned with one transform.",
        "",
        "| agent | poses est/gt/matched | RMSE | mean | median | max | std | scale err "
        "| RMSE under joint | rot RMSE [deg] | RPE trans RMSE [m] | RPE rot RMSE [deg] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    merged = maps is None or maps.joint_frame
    for agent, ind in joint.individual.items():
        s = ind.stats
        r = rpe.get(agent)
        under = _f(joint.under_joint[agent].stats.rmse) if merged else "-"
        rpe_t = _f(r.trans_stats.rmse) if r else "-"
        rpe_r = _f(r.rot_stats.rmse) if r else "-"
        lines.append(
            f"| {agent} | {ind.n_est}/{ind.n_ref}/{s.count} | {_f(s.rmse)} | {_f(s.mean)} "
            f"| {_f(s.median)} | {_f(s.max)} | {_f(s.std)} | {ind.scale_error:+.4f} "
            f"| {under} | {_f(ind.rot_stats.rmse)} "
            f"| {rpe_t} | {rpe_r} |"
        )
    if not merged:
        assert maps is not None
        return "\n".join([*lines, "", maps.sentence()]) + "\n"
    s = joint.stats
    n_est = sum(r.n_est for r in joint.under_joint.values())
    n_ref = sum(r.n_ref for r in joint.under_joint.values())
    lines.append(
        f"| **joint** | {n_est}/{n_ref}/{s.count} | {_f(s.rmse)} | {_f(s.mean)} "
        f"| {_f(s.median)} | {_f(s.max)} | {_f(s.std)} | {joint.scale_error:+.4f} "
        f"| {_f(s.rmse)} | {_f(joint.rot_stats.rmse)} | - | - |"
    )
    return "\n".join(lines) + "\n"


def evaluate_run(
    result_dir: Path | str,
    groundtruth: Path | str | None = None,
    out_dir: Path | str | None = None,
    config: EvalConfig | None = None,
) -> EvalReport:
    """Evaluate ``RESULT_DIR`` and write ``ate.json``, ``ate.md`` and PNGs into ``out_dir``.

    ``out_dir`` defaults to ``RESULT_DIR/eval``. ``RESULT_DIR/cloud_maps.json``, when there,
    decides whether a joint ATE is reported (module docstring). Raises EvaluationError
    (ResultFolderError, AssociationError, ...) with a message naming the offending file or
    agent.
    """
    cfg = config or EvalConfig()
    root = Path(result_dir)
    out = Path(out_dir) if out_dir is not None else root / EVAL_DIR
    estimates = read_result_trajectories(root)
    references, gt_files = load_groundtruth(list(estimates), groundtruth, root)
    joint = compute_joint_ate(references, estimates, cfg.ate)
    rpe: dict[str, RpeResult | None] = {}
    if cfg.rpe_enabled:
        rpe_cfg = dataclasses.replace(
            cfg.rpe, association=cfg.ate.association, align=_rpe_align(cfg)
        )
        for agent, est in estimates.items():
            try:
                rpe[agent] = compute_rpe(references[agent], est, rpe_cfg)
            except MetricsError as exc:
                log.warning("RPE of %s skipped: %s", agent, exc)
                rpe[agent] = None
    out.mkdir(parents=True, exist_ok=True)
    sources = {a: str(p) for a, p in gt_files.items()}
    maps = read_map_frames(root)
    files = [out / "ate.json", out / "ate.md"]
    summary = report_dict(joint, rpe, cfg, sources, maps)
    files[0].write_text(json.dumps(summary, indent=2) + "\n")
    files[1].write_text(
        f"# Trajectory evaluation of `{root}`\n\n" + markdown_table(joint, rpe, maps)
    )
    if cfg.plots:
        from common.evaluation.plots import plot_ate_over_time, plot_trajectories

        mode = joint.mode.value
        files.append(
            plot_trajectories(
                joint.under_joint,
                out / "trajectories_joint.png",
                f"joint {mode} alignment: ATE RMSE {joint.stats.rmse:.4f} m"
                if maps is None or maps.joint_frame
                else f"maps did not merge: one {mode} alignment over different map frames",
            )
        )
        files.append(
            plot_trajectories(
                joint.individual, out / "trajectories_individual.png", f"per-agent {mode} alignment"
            )
        )
        files.append(
            plot_ate_over_time(
                {"joint alignment": joint.under_joint, "per-agent alignment": joint.individual},
                out / "ate_over_time.png",
                f"ATE over time ({mode})",
            )
        )
    return EvalReport(joint, rpe, gt_files, out, files, maps)


def _rpe_align(cfg: EvalConfig) -> AlignMode:
    """RPE uses the ATE alignment only for its scale (rigid parts cancel in RPE)."""
    if cfg.ate.align in (AlignMode.SIM3, AlignMode.SCALE):
        return AlignMode.SCALE
    return AlignMode.NONE


PRIOR_FRAME_FILE = "ate_prior_frame.json"
"""The report of :func:`evaluate_in_frame`, next to ``ate.json``."""


def read_joint_transform(ate_json: Path | str) -> SimilarityTransform:
    """The joint alignment an ``ate.json`` (of :func:`evaluate_run`) holds; ResultFolderError
    when the file is missing or has none."""
    path = Path(ate_json)
    try:
        return SimilarityTransform.from_dict(json.loads(path.read_text())["joint"]["transform"])
    except (OSError, ValueError, KeyError, TypeError, AlignmentError) as exc:
        raise ResultFolderError(f"{path}: no joint alignment to measure in ({exc})") from exc


def evaluate_in_frame(
    result_dir: Path | str,
    frame_of: Path | str,
    groundtruth: Path | str | None = None,
    out_dir: Path | str | None = None,
    config: EvalConfig | None = None,
) -> tuple[JointAteResult, Path]:
    """ATE of ``RESULT_DIR``'s trajectories under the joint alignment of an earlier run's
    ``ate.json`` (``frame_of``), without aligning again: for a mission that started inside
    that run's saved map (``services.cloud.store.mission``), whose trajectories are in its map
    frame, this measures how well the new mission sits in the old map, not just its own
    shape. Writes ``OUT/ate_prior_frame.json`` (``out_dir`` defaults to ``RESULT_DIR/eval``)
    and returns the result and that file."""
    cfg = config or EvalConfig()
    root = Path(result_dir)
    out = Path(out_dir) if out_dir is not None else root / EVAL_DIR
    frame = read_joint_transform(frame_of)
    estimates = read_result_trajectories(root)
    references, _ = load_groundtruth(list(estimates), groundtruth, root)
    joint = compute_joint_ate(references, estimates, cfg.ate, transform=frame)
    summary = {
        "frame_of": str(frame_of),
        "transform": frame.as_dict(),
        "joint": {"stats_m": joint.stats.as_dict(), "rot_stats_deg": joint.rot_stats.as_dict()},
        "agents": {
            a: {
                "stats_m": r.stats.as_dict(),
                "own_alignment_rmse_m": joint.individual[a].stats.rmse,
            }
            for a, r in joint.under_joint.items()
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    path = out / PRIOR_FRAME_FILE
    path.write_text(json.dumps(summary, indent=2) + "\n")
    return joint, path
