"""Errors of the evaluation package: one base, one subclass per module."""

from __future__ import annotations

from common.errors import RecslamError


class EvaluationError(RecslamError):
    """Base of every error raised on purpose by ``common.evaluation``."""


class TrajectoryError(EvaluationError):
    """A trajectory's arrays are malformed (shapes, non-finite values, unsorted stamps)."""


class AssociationError(EvaluationError):
    """Two trajectories share no (or too few) timestamps within the allowed difference."""


class AlignmentError(EvaluationError):
    """The alignment problem is degenerate (too few or collinear positions)."""


class MetricsError(EvaluationError):
    """A metric cannot be computed from the given data (e.g. RPE delta yields no pairs)."""


class TumFormatError(EvaluationError):
    """A TUM trajectory file is malformed; the message names file and line."""


class ResultFolderError(EvaluationError):
    """A result folder or ground-truth source does not follow the documented layout."""
