"""The typed topics of the algorithms' nodes (names after the paper where it names them).

A topic that carries one of the cores' records (``algorithms.records``: the template, the pose
cells' action, the map's pose) takes its schema from the record's declaration (:func:`topic_of`),
and :func:`record_data` / :func:`record_of` turn a record into a message's data and back, so each
field is written once. A declaration registers nothing by itself: a node's declared topics are
registered when the node is built, and each plan lists :data:`ALGORITHM_TOPICS`, which every
process of a run (workers, source, monitor, supervisor) registers at its start; a process that
decodes them outside a run (the viewer) registers them itself. The codec knows only the runtime's
own types (``image``, ``odom``, ``groundtruth``, ``stats``, ``control``) and refuses a type nobody
registered.
"""

from __future__ import annotations

import dataclasses
import types
from typing import Annotated, Any, Union, get_args, get_origin

import numpy as np
from typing_extensions import NotRequired, get_type_hints, is_typeddict

from ..algorithms.records import Action, Array, BinaryCode, Finite, MapPose, Template, WinnerCells
from ..runtime.messages import CONTROL, GROUNDTRUTH, IMAGE, ODOM, Field, Topic

__all__ = ["ALGORITHM_TOPICS", "BIN_FEATURES", "CONTROL", "EXPERIENCE_MAP", "EXPERIENCE_POSE", "GROUNDTRUTH",
           "IMAGE", "ODOM", "POSE_CELL_ACTION", "SDR", "VISUAL_FEATURES", "VISUAL_TEMPLATE", "record_data",
           "record_of", "topic_of"]

_KINDS = {int: "int", float: "float", bool: "bool", str: "str", dict: "map"}


def _field(hint: Any, optional: bool) -> Field:
    """The wire field of one record field's type hint (``Annotated`` extras: Finite, Array)."""
    extras: tuple[Any, ...] = ()
    if get_origin(hint) is NotRequired:
        (hint,) = get_args(hint)
        optional = True
    if get_origin(hint) is Annotated:
        hint, *rest = get_args(hint)
        extras = tuple(rest)
    if get_origin(hint) in (Union, types.UnionType):  # X | None: the field may be left out
        (hint,) = [a for a in get_args(hint) if a is not type(None)]
        optional = True
    if hint is np.ndarray:
        (arr,) = [e for e in extras if isinstance(e, Array)]
        return Field("array", arr.dtypes, (arr.ndim,), arr.shape, optional=optional, finite=arr.finite)
    return Field(_KINDS[hint], optional=optional, finite=Finite in extras)


def topic_of(name: str, record: type) -> Topic:
    """The topic ``name`` carrying ``record`` (a dataclass or a TypedDict): one field per record
    field; a field with a default, ``NotRequired`` or ``| None`` may be left out."""
    hints = get_type_hints(record, include_extras=True)
    if is_typeddict(record):
        return Topic(name, {k: _field(h, k in record.__optional_keys__) for k, h in hints.items()})
    defaults = {f.name for f in dataclasses.fields(record)
                if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}
    return Topic(name, {k: _field(h, k in defaults) for k, h in hints.items()})


def record_data(record: Any) -> dict[str, Any]:
    """A dataclass record as a message's data: its fields, those that are None left out."""
    return {f.name: v for f in dataclasses.fields(record) if (v := getattr(record, f.name)) is not None}


def record_of(record: type, data: dict[str, Any]) -> Any:
    """A message's data as the dataclass ``record`` (fields left out take their defaults)."""
    return record(**{f.name: data[f.name] for f in dataclasses.fields(record) if f.name in data})


#: A's output: the CNN feature vector of one frame (and the backbone that computed it)
VISUAL_FEATURES = Topic("visual_features", {
    "features": Field("array", ("float32",), (1,), finite=True),
    "backbone": Field("str", optional=True),
})
#: B's output: sorted indices of the on-bits of the sLSBH code (``size`` bits in all), and the
#: frame's descriptor (:class:`~neoslam_stream.algorithms.records.BinaryCode`)
BIN_FEATURES = topic_of("bin_features", BinaryCode)
#: C's output: the winner cells of the Temporal Memory, its raw anomaly, B's descriptor passed on
#: (:class:`~neoslam_stream.algorithms.records.WinnerCells`)
SDR = topic_of("sdr", WinnerCells)
#: D's (or RatSLAM's local-view cells', or the oracle's) output: the visual template of the frame
VISUAL_TEMPLATE = topic_of("visual_template", Template)
#: The pose cells' output, one per odometry sample: the action for the experience map with the
#: odometry it integrates (see :class:`~neoslam_stream.algorithms.records.Action`)
POSE_CELL_ACTION = topic_of("pose_cells/action", Action)
#: The experience map's pose of the robot after each action, its experience, and the pose in that
#: experience's frame (:class:`~neoslam_stream.algorithms.records.MapPose`)
EXPERIENCE_POSE = topic_of("experience_map/pose", MapPose)
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
