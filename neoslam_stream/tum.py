"""TUM trajectory files (``t x y z qx qy qz qw``), the one format every part of the project writes
poses in: sources (ground truth, odometry), the recorder (trajectory.tum) and the evaluation."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_tum(path: str | Path) -> np.ndarray:
    """(n, 4) array of stamp, x, y, yaw from a TUM file (``t x y z qx qy qz qw``)."""
    rows = []
    for line in Path(path).read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        p = [float(v) for v in line.replace(",", " ").split()]
        if len(p) < 8:
            raise ValueError(f"{path}: TUM lines need 8 values, got {len(p)}")
        t, x, y, _z, qx, qy, qz, qw = p[:8]
        yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        rows.append((t, x, y, yaw))
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def write_tum(path: str | Path, rows: np.ndarray) -> None:
    with open(path, "w") as fh:
        for t, x, y, yaw in rows:
            fh.write(f"{t:.6f} {x:.6f} {y:.6f} 0 0 0 {np.sin(yaw / 2):.9f} {np.cos(yaw / 2):.9f}\n")
