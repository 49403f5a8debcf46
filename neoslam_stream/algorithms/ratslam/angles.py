"""Angle helpers shared by the experience map and the odometry-bias estimator (a light module, so
that the estimator does not pull in the experience map's numba kernels)."""

from __future__ import annotations

import math

import numpy as np


def clip_pi(a: float) -> float:
    """Wrap into (-pi, pi]."""
    while a > math.pi:
        a -= 2 * math.pi
    while a <= -math.pi:
        a += 2 * math.pi
    return a


def wrap_pi(a: np.ndarray) -> np.ndarray:
    """Wrap every element into [-pi, pi) (arrays; clip_pi's one number lands in (-pi, pi])."""
    return np.remainder(a + math.pi, 2 * math.pi) - math.pi
