"""The typed topics of the algorithms' nodes (names after the paper where it names them).

A declaration registers nothing by itself: a node's declared topics are registered when the node is
built, and each plan lists :data:`ALGORITHM_TOPICS`, which every process of a run (workers, source,
monitor, supervisor) registers at its start; a process that decodes them outside a run (the viewer)
registers them itself. The codec knows only the runtime's own types (``image``, ``odom``,
``groundtruth``, ``stats``, ``control``) and refuses a type nobody registered.
"""

from __future__ import annotations

from ..runtime.messages import CONTROL, GROUNDTRUTH, IMAGE, ODOM, Field, Topic

__all__ = ["ALGORITHM_TOPICS", "BIN_FEATURES", "CONTROL", "EXPERIENCE_MAP", "EXPERIENCE_POSE", "GROUNDTRUTH",
           "IMAGE", "ODOM", "POSE_CELL_ACTION", "SDR", "VISUAL_FEATURES", "VISUAL_TEMPLATE"]

_IDX = ("uint16", "uint32", "int32", "int64", "uint64")

#: A's output: the CNN feature vector of one frame (and the backbone that computed it)
VISUAL_FEATURES = Topic("visual_features", {
    "features": Field("array", ("float32",), (1,), finite=True),
    "backbone": Field("str", optional=True),
})
#: B's output: sorted indices of the on-bits of the sLSBH code (``size`` bits in all)
BIN_FEATURES = Topic("bin_features", {"bits": Field("array", _IDX, (1,)), "size": Field("int")})
#: C's output: the winner cells of the Temporal Memory, and its raw anomaly
SDR = Topic("sdr", {"cells": Field("array", _IDX, (1,)), "size": Field("int"),
                    "anomaly": Field("float", optional=True)})
#: D's (or RatSLAM's local-view cells') output: the visual template of the frame
VISUAL_TEMPLATE = Topic("visual_template", {
    "id": Field("int"),
    "relative_rad": Field("float", optional=True, finite=True),
    "is_loop_closure": Field("bool", optional=True),
    "best_interval": Field("int", optional=True),
    # the score of the best candidate (D: an overlap count, an int; local view: a match error, a
    # float, inf before the first comparison)
    "best_score": Field("float", optional=True),
    # the front end's runner-up, for the per-closure margin (closures.csv): D's second-best
    # interval and its overlap, the oracle's second-nearest template and its distance
    "second_interval": Field("int", optional=True),
    "second_score": Field("float", optional=True),
    # D's current interval (the recorder maps a matched interval to the frame that opened it)
    "interval": Field("int", optional=True),
})
#: The pose cells' output, one per odometry sample: the action for the experience map and the
#: odometry it integrates, so that the map needs no other topic and dead reckoning stays in the
#: same order as the actions; and the yaw-rate bias's measured wander (the map's bias_walk)
POSE_CELL_ACTION = Topic("pose_cells/action", {
    "action": Field("int"), "src_id": Field("int"), "dst_id": Field("int"),
    "relative_rad": Field("float", optional=True, finite=True),
    "vtrans": Field("float", finite=True), "vrot": Field("float", finite=True),
    "dt": Field("float", finite=True), "bias_wander": Field("float", optional=True, finite=True),
})
#: The experience map's pose of the robot after each action (x, y, theta), its experience, and the
#: pose in that experience's frame (dx, dy, dtheta: ExperienceMap.local_pose)
EXPERIENCE_POSE = Topic("experience_map/pose", {
    "pose": Field("array", ("float64", "float32"), (1,), (3,)),
    "exp_id": Field("int", optional=True),
    "local": Field("array", ("float64", "float32"), (1,), (3,), optional=True, finite=True),
})
#: The whole map at the end of a run: nodes (id, x, y, theta, stamp), links (from, to), and the
#: full export (``ExperienceMap.export()``: what map.json holds)
EXPERIENCE_MAP = Topic("experience_map/map", {
    "nodes": Field("array", ("float64",), (2,)),
    "links": Field("array", ("int64", "int32"), (2,), optional=True),
    "export": Field("map", optional=True),
})

#: every topic the algorithms' nodes publish, with its schema: what a plan registers in each process
ALGORITHM_TOPICS = (VISUAL_FEATURES, BIN_FEATURES, SDR, VISUAL_TEMPLATE, POSE_CELL_ACTION, EXPERIENCE_POSE,
                    EXPERIENCE_MAP)
