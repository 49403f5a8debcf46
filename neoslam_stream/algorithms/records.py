"""The records the cores hand from one stage to the next, declared once with what their values are.

A stage's result that has named fields is one of these types: B's :class:`BinaryCode`, C's
:class:`WinnerCells`, D's (or the local view's) :class:`Template`, the pose cells' :class:`Action`,
the experience map's :class:`MapPose`. Each
field says its type and, with ``Annotated``, what its values always are (:data:`Finite`, an
:class:`Array`'s dtypes and shape), so that a host that carries the records elsewhere (the topics
of ``neoslam_stream.nodes``) derives its checks from here instead of writing the fields again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from typing_extensions import NotRequired, TypedDict


class _Finite:
    """Marks a float that is never NaN or infinite."""

    def __repr__(self) -> str:
        return "Finite"


#: ``Annotated[float, Finite]``: a float that is never NaN or infinite
Finite = _Finite()


@dataclass(frozen=True)
class Array:
    """An array field's dtypes, number of dimensions and exact shape (None: any length)."""

    dtypes: tuple[str, ...]
    ndim: int = 1
    shape: tuple[int | None, ...] | None = None
    finite: bool = False


#: the integer dtypes an array of indices (bits, cells) may have
INDEX_DTYPES = ("uint16", "uint32", "int32", "int64", "uint64")


@dataclass
class BinaryCode:
    """B's result for one frame: the sorted on-bits of its sLSBH code (``size`` bits in all) and,
    when B keeps one, its descriptor: the centred features as int8, from which D re-ranks the
    candidates the bits shortlisted."""

    bits: Annotated[np.ndarray, Array(INDEX_DTYPES)]
    size: int
    descriptor: Annotated[np.ndarray | None, Array(("int8",))] = None


@dataclass
class WinnerCells:
    """C's result for one frame: the Temporal Memory's winner cells (of ``size``), the step's raw
    anomaly, and B's descriptor of the frame, passed on to D."""

    cells: Annotated[np.ndarray, Array(INDEX_DTYPES)]
    size: int
    anomaly: float | None = None
    descriptor: Annotated[np.ndarray | None, Array(("int8",))] = None


class Template(TypedDict):
    """One frame's visual template: the template id, whether it closed a loop, the best candidate
    (D: an interval, its overlap with the frame; the local view: -1 and its match error) and D's
    runner-up and current interval. A dict, so that every key reads as before; the optional keys
    are absent where a front end has no such thing."""

    id: int
    is_loop_closure: NotRequired[bool]
    best_interval: NotRequired[int]
    relative_rad: NotRequired[Annotated[float, Finite]]
    #: D: an overlap count (an int, a float when union-normalised); the local view: a match error
    #: (inf before the first comparison)
    best_score: NotRequired[float]
    #: the runner-up, for the per-closure margin (closures.csv): D's second-best interval and its
    #: overlap, the oracle's second-nearest template and its distance
    second_interval: NotRequired[int]
    second_score: NotRequired[float]
    #: D's current interval (a matched interval is mapped to the frame that opened it)
    interval: NotRequired[int]
    #: a loop closure's confidence, higher is surer and 0 at the decision's threshold, for the
    #: precision-recall curve (closures.csv): the calibrated decision's mean confidence over its
    #: stretch of evidence (in standard deviations of unrelated places' scores); D's paper rule
    #: its score less theta_sigma; the local view's OpenRatSLAM rule vt_match_threshold less its
    #: error; the oracle its radius less the distance
    confidence: NotRequired[Annotated[float, Finite]]


@dataclass
class Action:
    """One pose-cell update: the experience-map action (0 none, 1 new node, 2 edge, 3 set node),
    its source and destination experiences, the odometry it integrated (vrot corrected), the
    heading relative to the matched view, and the yaw-rate bias's wander measured so far
    (rad^2/s^3, 0: none; the map's ``bias_walk``). It carries its odometry so that the map needs
    nothing else and dead reckoning stays in the order of the actions."""

    action: int
    src_id: int
    dst_id: int
    vtrans: Annotated[float, Finite]
    vrot: Annotated[float, Finite]
    dt: Annotated[float, Finite]
    relative_rad: Annotated[float, Finite] = 0.0
    bias_wander: Annotated[float, Finite] = 0.0


@dataclass
class MapPose:
    """The experience map's pose of the robot (x, y, theta), its experience and the pose in that
    experience's frame (dx, dy, dtheta), from which the final map re-expresses it."""

    pose: Annotated[np.ndarray, Array(("float64", "float32"), 1, (3,))]
    exp_id: int = -1
    local: Annotated[np.ndarray | None, Array(("float64", "float32"), 1, (3,), finite=True)] = None
