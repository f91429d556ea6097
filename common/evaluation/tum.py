"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, one space apart.

Timestamps are seconds written as ``<int>.<9 digits>`` from int64 nanoseconds, so a write/read
round trip is exact; positions in metres and quaternions (Hamilton, scalar last as TUM wants)
with 17 significant digits (float64 round trip). Lines starting with ``#`` are comments; our
files start with one header comment, which evo's ``read_tum_trajectory_file`` skips.

Reading accepts any whitespace between fields and timestamps in any decimal or exponent
notation (as numpy's ``savetxt`` writes them, e.g. evo's own files); a malformed line raises
:class:`TumFormatError` naming file and line.
"""

from __future__ import annotations

import logging
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from common.evaluation.errors import TrajectoryError, TumFormatError
from common.evaluation.trajectory import Trajectory

log = logging.getLogger(__name__)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


def parse_timestamp_ns(text: str) -> int:
    """Seconds as text (``1403636579.763555527``, ``1.4e9``) -> int ns, rounded half-even."""
    try:
        value = Decimal(text)
    except InvalidOperation as exc:
        raise ValueError(f"not a number: {text!r}") from exc
    if not value.is_finite():
        raise ValueError(f"not a finite timestamp: {text!r}")
    return int((value * 1_000_000_000).to_integral_value())


def format_timestamp_ns(t_ns: int) -> str:
    """int ns -> seconds with exactly 9 decimals (``-0.000000001`` for -1)."""
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    sec, frac = divmod(abs(t), 1_000_000_000)
    return f"{sign}{sec}.{frac:09d}"


def format_tum(traj: Trajectory) -> str:
    """The TUM text of a trajectory (header line included, trailing newline)."""
    q_xyzw = traj.q_wxyz[:, [1, 2, 3, 0]]
    lines = [TUM_HEADER]
    for t, p, q in zip(traj.timestamps_ns.tolist(), traj.p_world_body, q_xyzw, strict=True):
        values = " ".join(repr(float(v)) for v in (*p, *q))
        lines.append(f"{format_timestamp_ns(t)} {values}")
    return "\n".join(lines) + "\n"


def write_tum(path: Path | str, traj: Trajectory) -> Path:
    """Write ``traj`` to ``path`` (parents created); returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(format_tum(traj), encoding="utf-8")
    log.debug("wrote %d poses to %s", len(traj), out)
    return out


def parse_tum(text: str, source: str = "<string>", name: str = "") -> Trajectory:
    """Parse TUM text; ``source`` names the file in error messages."""
    stamps: list[int] = []
    values: list[list[float]] = []
    line_numbers: list[int] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 8:
            raise TumFormatError(
                f"{source}:{lineno}: expected 8 fields 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(fields)}"
            )
        try:
            stamps.append(parse_timestamp_ns(fields[0]))
            values.append([float(v) for v in fields[1:]])
        except ValueError as exc:
            raise TumFormatError(f"{source}:{lineno}: {exc}") from exc
        line_numbers.append(lineno)
    if not stamps:
        raise TumFormatError(f"{source}: no poses (empty or only comments)")
    v = np.asarray(values, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if bad.size:
        raise TumFormatError(f"{source}:{line_numbers[int(bad[0])]}: non-finite value")
    norms = np.linalg.norm(v[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-2)
    if bad.size:
        i = int(bad[0])
        raise TumFormatError(f"{source}:{line_numbers[i]}: quaternion norm {norms[i]:.6g} is not 1")
    ts = np.asarray(stamps, dtype=np.int64)
    steps = np.diff(ts)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise TumFormatError(
            f"{source}:{line_numbers[i]}: timestamp {format_timestamp_ns(ts[i])} s does not "
            f"increase (previous {format_timestamp_ns(ts[i - 1])} s)"
        )
    try:
        return Trajectory(ts, v[:, 0:3], v[:, [6, 3, 4, 5]], name)
    except TrajectoryError as exc:
        raise TumFormatError(f"{source}: {exc}") from exc


def read_tum(path: Path | str, name: str | None = None) -> Trajectory:
    """Read a TUM file; ``name`` defaults to the file stem."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError as exc:
        raise TumFormatError(f"{p}: no such TUM file") from exc
    except UnicodeDecodeError as exc:
        raise TumFormatError(f"{p}: not a text file ({exc.reason})") from exc
    return parse_tum(text, str(p), p.stem if name is None else name)
