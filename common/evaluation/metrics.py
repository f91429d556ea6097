"""Absolute trajectory error (per agent and joint) and relative pose error, evo-compatible.

ATE: associate by time, align (see :mod:`common.evaluation.alignment`), then the error of
pose ``i`` is ``|| p_ref_i - (s R p_est_i + t) ||`` [m] (evo's APE, translation part); the
rotation error is the angle of ``R_est_aligned_i^T R_ref_i`` [deg].

Joint ATE (the paper's Table 2): every agent's estimate is expressed in ONE common map frame.
The associated positions of all agents are stacked and aligned with a single transform, so a
wrong map merge (one agent's map offset from the others) shows up as a large joint error even
when each agent, aligned on its own, looks good. Both are reported.

RPE (evo's definition, TUM RGB-D benchmark): for index pairs ``(i, j)`` picked on the estimate
(every ``delta`` frames, or every ``delta`` metres of travelled path) the error pose is
``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; translation error ``||t(E)||`` [m], rotation error the
angle of ``R(E)`` [deg].
"""

from __future__ import annotations

import dataclasses
import enum
import itertools
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from common.evaluation.alignment import AlignMode, SimilarityTransform, align, estimate_alignment
from common.evaluation.association import Association, AssociationConfig, associate
from common.evaluation.errors import MetricsError
from common.evaluation.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a (N,) error array, in the array's unit; ``std`` is the population std."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    count: int

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64).reshape(-1)
        if e.size == 0:
            raise MetricsError("no errors to summarise (empty error array)")
        sq = e * e
        return cls(
            rmse=float(np.sqrt(np.mean(sq))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            sse=float(np.sum(sq)),
            count=int(e.size),
        )

    def as_dict(self) -> dict[str, float | int]:
        return {
            "rmse": self.rmse,
            "mean": self.mean,
            "median": self.median,
            "std": self.std,
            "min": self.min,
            "max": self.max,
            "sse": self.sse,
            "count": self.count,
        }


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles [deg] of rotations (N, 3, 3), accurate for small angles too."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    if R.shape[0] == 0:
        return np.zeros(0)
    return np.rad2deg(Rotation.from_matrix(R).magnitude())


# ----------------------------------------------------------------------------- ATE


@dataclass(frozen=True)
class AteConfig:
    """ATE settings.

    ``align``: alignment mode (default SE(3), the usual for VIO with observable scale).
    ``n_align``: align with only the first ``n_align`` associated poses (per agent for joint
    ATE); None uses all. ``association``: time pairing (default: nearest within 10 ms).
    """

    align: AlignMode = AlignMode.SE3
    n_align: int | None = None
    association: AssociationConfig = field(default_factory=AssociationConfig)


@dataclass(frozen=True)
class AteResult:
    """ATE of one trajectory under ``transform``.

    ``ref`` and ``est_aligned`` are the associated poses (M each), the estimate already mapped
    into the reference frame; ``errors_m`` (M,) [m]; ``rot_errors_deg`` (M,) [deg];
    ``n_ref`` / ``n_est`` the pose counts before association (the associated count M when
    computed by :func:`ate_from_association`, which never saw the full trajectories).
    """

    name: str
    mode: AlignMode
    transform: SimilarityTransform
    ref: Trajectory
    est_aligned: Trajectory
    errors_m: np.ndarray
    rot_errors_deg: np.ndarray
    stats: ErrorStats
    rot_stats: ErrorStats
    n_ref: int
    n_est: int

    @property
    def scale_error(self) -> float:
        """Sim(3) scale - 1 (0 unless the mode estimates scale)."""
        return self.transform.scale_error

    @property
    def timestamps_ns(self) -> np.ndarray:
        """(M,) reference stamps of the associated pairs [ns]."""
        return self.ref.timestamps_ns


@dataclass(frozen=True)
class JointAteResult:
    """Joint ATE of several agents in one map frame, plus each agent aligned on its own.

    ``transform`` is the single alignment of all agents; ``stats`` / ``rot_stats`` summarise
    all agents' errors under it; ``under_joint[agent]`` breaks them down per agent (every entry
    carries the joint transform); ``individual[agent]`` is that agent aligned alone.
    """

    mode: AlignMode
    transform: SimilarityTransform
    stats: ErrorStats
    rot_stats: ErrorStats
    under_joint: dict[str, AteResult]
    individual: dict[str, AteResult]

    @property
    def scale_error(self) -> float:
        return self.transform.scale_error

    @property
    def errors_m(self) -> np.ndarray:
        """(M_total,) joint errors [m], agents in ``under_joint`` order."""
        return np.concatenate([r.errors_m for r in self.under_joint.values()])


def _errors_under(
    name: str,
    assoc: Association,
    mode: AlignMode,
    transform: SimilarityTransform,
) -> AteResult:
    est_aligned = transform.apply(assoc.est)
    errors = np.linalg.norm(est_aligned.p_world_body - assoc.ref.p_world_body, axis=1)
    R_err = np.swapaxes(est_aligned.R_world_body, 1, 2) @ assoc.ref.R_world_body
    rot = rotation_angles_deg(R_err)
    return AteResult(
        name=name,
        mode=mode,
        transform=transform,
        ref=assoc.ref,
        est_aligned=est_aligned,
        errors_m=errors,
        rot_errors_deg=rot,
        stats=ErrorStats.from_errors(errors),
        rot_stats=ErrorStats.from_errors(rot),
        n_ref=len(assoc.ref),
        n_est=len(assoc.est),
    )


def ate_from_association(
    assoc: Association, config: AteConfig | None = None, name: str = ""
) -> AteResult:
    """ATE of already associated poses (``assoc.ref[i]`` pairs with ``assoc.est[i]``)."""
    cfg = config or AteConfig()
    transform = align(assoc.ref, assoc.est, cfg.align, cfg.n_align)
    return _errors_under(name or assoc.est.name, assoc, cfg.align, transform)


def compute_ate(ref: Trajectory, est: Trajectory, config: AteConfig | None = None) -> AteResult:
    """Associate ``est`` with ``ref``, align, and measure the absolute trajectory error."""
    cfg = config or AteConfig()
    assoc = associate(ref, est, cfg.association)
    result = ate_from_association(assoc, cfg, est.name or ref.name)
    return _with_counts(result, len(ref), len(est))


def _with_counts(result: AteResult, n_ref: int, n_est: int) -> AteResult:
    return dataclasses.replace(result, n_ref=n_ref, n_est=n_est)


def compute_joint_ate(
    references: Mapping[str, Trajectory],
    estimates: Mapping[str, Trajectory],
    config: AteConfig | None = None,
    transform: SimilarityTransform | None = None,
) -> JointAteResult:
    """Joint ATE over agents (see module docstring). Keys are agent names.

    Every estimated agent needs a reference; extra references are ignored. With
    ``AlignMode.ORIGIN`` the first agent (in ``estimates`` order) fixes the transform; with
    ``n_align`` the first ``n_align`` poses of every agent are used. ``transform``: measure
    under this alignment instead of estimating one (e.g. an earlier mission's, for estimates
    that should be in that mission's map frame); ``individual`` is still estimated.
    """
    cfg = config or AteConfig()
    if not estimates:
        raise MetricsError("joint ATE needs at least one estimated trajectory")
    missing = sorted(set(estimates) - set(references))
    if missing:
        raise MetricsError(
            f"no reference for agent(s) {missing}; references exist for {sorted(references)}"
        )
    assocs = {
        agent: associate(references[agent], est, cfg.association)
        for agent, est in estimates.items()
    }
    if transform is not None:
        pass
    elif cfg.align is AlignMode.ORIGIN:
        first = next(iter(assocs.values()))
        transform = align(first.ref, first.est, AlignMode.ORIGIN)
    else:
        n = cfg.n_align
        p_ref = np.concatenate([a.ref.p_world_body[:n] for a in assocs.values()])
        p_est = np.concatenate([a.est.p_world_body[:n] for a in assocs.values()])
        transform = estimate_alignment(p_ref, p_est, cfg.align)
    under_joint = {}
    individual = {}
    for agent, assoc in assocs.items():
        n_ref, n_est = len(references[agent]), len(estimates[agent])
        under_joint[agent] = _with_counts(
            _errors_under(agent, assoc, cfg.align, transform), n_ref, n_est
        )
        individual[agent] = _with_counts(ate_from_association(assoc, cfg, agent), n_ref, n_est)
    errors = np.concatenate([r.errors_m for r in under_joint.values()])
    rot = np.concatenate([r.rot_errors_deg for r in under_joint.values()])
    return JointAteResult(
        mode=cfg.align,
        transform=transform,
        stats=ErrorStats.from_errors(errors),
        rot_stats=ErrorStats.from_errors(rot),
        under_joint=under_joint,
        individual=individual,
    )


# ----------------------------------------------------------------------------- RPE


class DeltaUnit(enum.Enum):
    """Unit of the RPE step between the two poses of a pair."""

    FRAMES = "frames"  # index distance in the associated sequence
    METERS = "m"  # travelled path length of the estimate (or reference, see config)


@dataclass(frozen=True)
class RpeConfig:
    """RPE settings (defaults as evo's ``evo_rpe``).

    ``delta`` / ``unit``: pair step, e.g. 1 frame or 1.0 m. ``all_pairs``: every pose starts a
    pair (overlapping) instead of consecutive, non-overlapping pairs. ``rel_delta_tol``: with
    metres and all pairs, accept path lengths within ``delta * rel_delta_tol`` of ``delta``.
    ``pairs_from_reference``: pick pairs on the reference instead of the estimate.
    ``align``: alignment applied before (only its scale changes RPE). ``association``: time
    pairing.
    """

    delta: float = 1.0
    unit: DeltaUnit = DeltaUnit.FRAMES
    all_pairs: bool = False
    rel_delta_tol: float = 0.1
    pairs_from_reference: bool = False
    align: AlignMode = AlignMode.NONE
    association: AssociationConfig = field(default_factory=AssociationConfig)


@dataclass(frozen=True)
class RpeResult:
    """Relative pose errors for ``pairs`` (K, 2) indices into the associated poses."""

    name: str
    delta: float
    unit: DeltaUnit
    pairs: np.ndarray
    trans_errors_m: np.ndarray
    rot_errors_deg: np.ndarray
    trans_stats: ErrorStats
    rot_stats: ErrorStats


def pairs_by_frames(n: int, delta: int, all_pairs: bool = False) -> np.ndarray:
    """(K, 2) index pairs ``(i, i + delta)`` over ``n`` poses (evo's filter_pairs_by_index)."""
    if all_pairs:
        i = np.arange(max(n - delta, 0), dtype=np.int64)
        return np.stack([i, i + delta], axis=1)
    ids = np.arange(0, n, delta, dtype=np.int64)
    return np.stack([ids[:-1], ids[1:]], axis=1) if ids.size > 1 else np.zeros((0, 2), np.int64)


def pairs_by_path(
    p: np.ndarray, delta_m: float, tol_m: float = 0.0, all_pairs: bool = False
) -> np.ndarray:
    """(K, 2) index pairs ``delta_m`` metres of path apart (evo's filter_pairs_by_path).

    Consecutive mode: a new pair ends at the first pose where the path since the previous
    pair end reaches ``delta_m``. All-pairs mode: each pose pairs with the later pose whose
    path distance is closest to ``delta_m``, if within ``tol_m``.
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    steps = np.linalg.norm(p[1:] - p[:-1], axis=1)
    pairs: list[tuple[int, int]] = []
    if all_pairs:
        dist = np.concatenate([[0.0], np.cumsum(steps)])
        for i in range(dist.size - 1):
            rest = dist[i + 1 :] - dist[i]
            k = int(np.argmin(np.abs(rest - delta_m)))
            if abs(rest[k] - delta_m) <= tol_m:
                pairs.append((i, i + 1 + k))
    else:
        ids = [0]
        path = 0.0
        for i, step in enumerate(steps.tolist(), start=1):
            path += step
            if path >= delta_m:
                ids.append(i)
                path = 0.0
        pairs = list(itertools.pairwise(ids))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def rpe_from_association(
    assoc: Association, config: RpeConfig | None = None, name: str = ""
) -> RpeResult:
    """RPE of already associated poses (see module docstring)."""
    cfg = config or RpeConfig()
    if cfg.delta <= 0:
        raise MetricsError(f"RPE delta must be positive, got {cfg.delta}")
    est = align(assoc.ref, assoc.est, cfg.align).apply(assoc.est)
    ref = assoc.ref
    if cfg.unit is DeltaUnit.FRAMES:
        if float(cfg.delta) != int(cfg.delta):
            raise MetricsError(f"RPE delta in frames must be an integer, got {cfg.delta}")
        pairs = pairs_by_frames(len(est), int(cfg.delta), cfg.all_pairs)
    else:
        source = ref if cfg.pairs_from_reference else est
        pairs = pairs_by_path(
            source.p_world_body, cfg.delta, cfg.delta * cfg.rel_delta_tol, cfg.all_pairs
        )
    if pairs.shape[0] == 0:
        raise MetricsError(
            f"RPE delta {cfg.delta} {cfg.unit.value} gives no pose pairs among {len(est)} "
            f"associated poses; use a smaller delta"
        )
    i, j = pairs[:, 0], pairs[:, 1]
    Rq, tq = ref.R_world_body, ref.p_world_body
    Rp, tp = est.R_world_body, est.p_world_body
    RqiT = np.swapaxes(Rq[i], 1, 2)
    RpiT = np.swapaxes(Rp[i], 1, 2)
    Rq_rel = RqiT @ Rq[j]
    tq_rel = np.einsum("kab,kb->ka", RqiT, tq[j] - tq[i])
    Rp_rel = RpiT @ Rp[j]
    tp_rel = np.einsum("kab,kb->ka", RpiT, tp[j] - tp[i])
    Rq_relT = np.swapaxes(Rq_rel, 1, 2)
    R_err = Rq_relT @ Rp_rel
    t_err = np.einsum("kab,kb->ka", Rq_relT, tp_rel - tq_rel)
    trans = np.linalg.norm(t_err, axis=1)
    rot = rotation_angles_deg(R_err)
    return RpeResult(
        name=name or assoc.est.name,
        delta=float(cfg.delta),
        unit=cfg.unit,
        pairs=pairs,
        trans_errors_m=trans,
        rot_errors_deg=rot,
        trans_stats=ErrorStats.from_errors(trans),
        rot_stats=ErrorStats.from_errors(rot),
    )


def compute_rpe(ref: Trajectory, est: Trajectory, config: RpeConfig | None = None) -> RpeResult:
    """Associate ``est`` with ``ref`` and measure the relative pose error."""
    cfg = config or RpeConfig()
    assoc = associate(ref, est, cfg.association)
    return rpe_from_association(assoc, cfg, est.name or ref.name)
