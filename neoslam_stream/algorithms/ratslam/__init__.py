"""RatSLAM back end (pose cells, experience map, and the yaw-bias estimator and odometry gate that
correct their input) and baseline front end (local-view cells, visual odometry), after OpenRatSLAM
(davidmball/ratslam). See docs/ratslam.md.

Names are imported lazily so that importing one module (e.g. a config model) does not pull in
every other one.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "PoseCellNetwork": "pose_cells", "PoseCellConfig": "pose_cells",
    "NO_ACTION": "pose_cells", "CREATE_NODE": "pose_cells", "CREATE_EDGE": "pose_cells", "SET_NODE": "pose_cells",
    "ExperienceMap": "experience_map", "ExperienceMapConfig": "experience_map", "poses_on_map": "map_poses",
    "LocalViewCells": "local_view", "LocalViewConfig": "local_view",
    "VisualOdometry": "visual_odometry", "VisualOdometryConfig": "visual_odometry",
    "YawBiasEstimator": "odometry_bias", "OdometryBiasConfig": "odometry_bias",
    "OdometryGate": "odometry_gate", "OdometryGateConfig": "odometry_gate",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
