"""Trajectory evaluation: association, alignment, ATE (per agent and joint), RPE, TUM, plots.

Pure numpy maths in ``trajectory``, ``association``, ``alignment`` and ``metrics`` (checked
against evo in the tests); file formats in ``tum`` and ``results``; ``plots`` and ``report``
produce what ``recslam eval`` writes. Typical use::

    from common.evaluation import AteConfig, AlignMode, compute_ate, read_tum
    res = compute_ate(read_tum("gt.tum"), read_tum("est.tum"), AteConfig(align=AlignMode.SIM3))
    res.stats.rmse, res.scale_error
"""

import logging

from common.evaluation.alignment import AlignMode, SimilarityTransform, align, umeyama
from common.evaluation.association import (
    DEFAULT_MAX_DIFF_NS,
    Association,
    AssociationConfig,
    associate,
    match_timestamps,
)
from common.evaluation.errors import (
    AlignmentError,
    AssociationError,
    EvaluationError,
    MetricsError,
    ResultFolderError,
    TrajectoryError,
    TumFormatError,
)
from common.evaluation.metrics import (
    AteConfig,
    AteResult,
    DeltaUnit,
    ErrorStats,
    JointAteResult,
    RpeConfig,
    RpeResult,
    compute_ate,
    compute_joint_ate,
    compute_rpe,
)
from common.evaluation.results import (
    load_groundtruth,
    read_result_trajectories,
    write_result_trajectories,
)
from common.evaluation.trajectory import Trajectory
from common.evaluation.tum import read_tum, write_tum

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "DEFAULT_MAX_DIFF_NS",
    "AlignMode",
    "AlignmentError",
    "Association",
    "AssociationConfig",
    "AssociationError",
    "AteConfig",
    "AteResult",
    "DeltaUnit",
    "ErrorStats",
    "EvaluationError",
    "JointAteResult",
    "MetricsError",
    "ResultFolderError",
    "RpeConfig",
    "RpeResult",
    "SimilarityTransform",
    "Trajectory",
    "TrajectoryError",
    "TumFormatError",
    "align",
    "associate",
    "compute_ate",
    "compute_joint_ate",
    "compute_rpe",
    "load_groundtruth",
    "match_timestamps",
    "read_result_trajectories",
    "read_tum",
    "umeyama",
    "write_result_trajectories",
    "write_tum",
]
