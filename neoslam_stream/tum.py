"""TUM trajectory files (``t x y z qx qy qz qw``), the one format every part of the project writes
poses in: sources (ground truth, odometry), the recorder (trajectory.tum) and the evaluation."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger("neoslam.tum")


def _parse_line(text: str) -> tuple[float, float, float, float] | str:
    """(t, x, y, yaw) of one data line, or why it cannot be used."""
    fields = text.replace(",", " ").split()
    if len(fields) < 8:
        return f"TUM lines need 8 values (t x y z qx qy qz qw), got {len(fields)}"
    values: list[float] = []
    for name, field in zip(("t", "x", "y", "z", "qx", "qy", "qz", "qw"), fields[:8], strict=True):
        try:
            v = float(field)
        except ValueError:
            return f"{name} = {field[:40]!r} is not a number"
        if not math.isfinite(v):  # NaN/inf would poison every pose integrated after it
            return f"{name} = {field[:40]} is NaN or infinite"
        values.append(v)
    t, x, y, _z, qx, qy, qz, qw = values
    # numpy's atan2, as before: the yaw of every file read stays bit-identical
    yaw = float(np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)))
    return t, x, y, yaw


def read_tum_rows(path: str | Path) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Every data line of a TUM file: an (n, 4) array of stamp, x, y, yaw with one row per data
    line (a row that cannot be used is all NaN, so that row i still belongs to image i), and
    ``(row index, cause)`` for each such row; the cause names the file and its line number.

    Accepted: a UTF-8 byte-order mark, blank lines, comments (``#``, indented or not), commas
    between values, extra columns. Refused rows: fewer than 8 values, a value that is not a
    number, any NaN or infinite value (the quaternion's included).
    """
    path = Path(path)
    text = path.read_bytes().decode("utf-8-sig", errors="replace")
    rows: list[tuple[float, float, float, float]] = []
    errors: list[tuple[int, str]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parsed = _parse_line(s)
        if isinstance(parsed, str):
            errors.append((len(rows), f"{path.name} line {lineno}: {parsed}: row skipped"))
            rows.append((math.nan,) * 4)
        else:
            rows.append(parsed)
    return np.array(rows, dtype=np.float64).reshape(-1, 4), errors


def read_tum(path: str | Path) -> np.ndarray:
    """(n, 4) array of stamp, x, y, yaw from a TUM file (``t x y z qx qy qz qw``): the usable
    rows only; each skipped row is logged with its line number (:func:`read_tum_rows`)."""
    rows, errors = read_tum_rows(path)
    for _i, cause in errors:
        log.warning("%s", cause)
    return rows[np.isfinite(rows).all(axis=1)] if errors else rows


def write_tum(path: str | Path, rows: np.ndarray) -> None:
    with open(path, "w") as fh:
        for t, x, y, yaw in rows:
            fh.write(f"{t:.6f} {x:.6f} {y:.6f} 0 0 0 {np.sin(yaw / 2):.9f} {np.cos(yaw / 2):.9f}\n")


def integrate_odometry(stamps: np.ndarray, odom: np.ndarray) -> np.ndarray:
    """(stamp, x, y, yaw) rows of dead reckoning from (vtrans, vrot, dt) samples, heading first
    (each sample turns by vrot*dt, then advances vtrans*dt along the new heading), starting at the
    origin facing +x: the odometry.tum that sources write and the evaluation compares with."""
    odom = np.asarray(odom, dtype=np.float64).reshape(-1, 3)
    yaw = np.cumsum(odom[:, 1] * odom[:, 2])
    step = odom[:, 0] * odom[:, 2]
    return np.column_stack([np.asarray(stamps, dtype=np.float64), np.cumsum(step * np.cos(yaw)),
                            np.cumsum(step * np.sin(yaw)), yaw])
