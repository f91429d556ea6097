"""Errors of the feature codec."""

from __future__ import annotations

from common.errors import RecslamError


class CodecError(RecslamError):
    """A payload cannot be decoded (corrupted, truncated, out of order, or foreign state)."""


class CodecUsageError(RecslamError, ValueError):
    """The caller handed the encoder data that breaks the codec's contract (local misuse)."""
