"""The rows of a run folder's row files: what each row holds, by name, and how it is written.

templates.csv (:class:`TemplateRow`), trajectory.tum (:class:`PoseRow`) and closures.csv
(:class:`ClosureRow`) are appended row by row by the run folder's writer (``nodes/run_folder.py``);
each :class:`RowFile` says its name, header, journal tag and line format.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..runtime.files import complete_lines

TEMPLATES_HEADER = "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
#: one row per match flagged as a loop closure (the evaluation tells loop closures from
#: re-recognitions, evaluation/closures.py): the matched frame opened the matched interval (or
#: created the matched template); true_distance_m between the true positions of the two frames (empty without ground
#: truth); score and second_score are the front end's best and runner-up scores (D: overlaps;
#: the oracle: distances in metres; empty where the front end has no runner-up) and margin their
#: difference, how much the winner beat the runner-up (|score - second_score|: the best score is
#: the front end's best by definition, whichever way its scores run); confidence what the decision
#: was sure of, higher is surer (records.Template.confidence; empty where the front end gave none)
CLOSURES_HEADER = "frame,stamp,template_id,matched_frame,true_distance_m,score,second_score,margin,confidence\n"


class TemplateRow(NamedTuple):
    """One row of templates.csv: the best score as the front end gave it (D's overlap count, the
    local view's match error)."""

    frame: int
    stamp: float
    template_id: int
    is_loop_closure: int
    best_interval: int
    best_score: Any


class PoseRow(NamedTuple):
    """One row of trajectory.tum: the map's pose of the robot after the frame, and its experience."""

    frame: int
    stamp: float
    x: float
    y: float
    theta: float
    exp_id: int


class ClosureRow(NamedTuple):
    """One row of closures.csv (see :data:`CLOSURES_HEADER`); distance, runner-up and confidence
    may be None."""

    frame: int
    stamp: float
    template_id: int
    matched_frame: int
    true_distance_m: float | None
    score: Any
    second_score: Any
    confidence: float | None = None


class WaitingClosure(NamedTuple):
    """A closure whose row waits for ground truth: its frame's true (x, y) instead of the distance."""

    frame: int
    stamp: float
    template_id: int
    matched_frame: int
    true_xy: tuple[float, float] | None
    score: Any
    second_score: Any
    confidence: float | None = None


def template_line(r: TemplateRow) -> str:
    return f"{r.frame},{r.stamp:.6f},{r.template_id},{r.is_loop_closure},{r.best_interval},{r.best_score}\n"


def trajectory_line(r: PoseRow) -> str:
    """Exactly ``tum.write_tum``'s format (``t x y z qx qy qz qw``)."""
    return f"{r.stamp:.6f} {r.x:.6f} {r.y:.6f} 0 0 0 {np.sin(r.theta / 2):.9f} {np.cos(r.theta / 2):.9f}\n"


def _num(v: Any) -> str:
    """A score as the front end gave it: an int as an int, a float with 6 significant digits."""
    if v is None:
        return ""
    if isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer() and abs(v) < 2**53):
        return str(int(v))
    return f"{float(v):.6g}"


def closure_line(r: ClosureRow) -> str:
    margin = None if r.second_score is None or r.score is None else abs(float(r.score) - float(r.second_score))
    dist = "" if r.true_distance_m is None else f"{r.true_distance_m:.3f}"
    return (f"{r.frame},{r.stamp:.6f},{r.template_id},{r.matched_frame},{dist},"
            f"{_num(r.score)},{_num(r.second_score)},{'' if margin is None else _num(margin)},"
            f"{_num(r.confidence)}\n")


@dataclass(frozen=True)
class RowFile:
    """A file written row by row: its name, header, journal tag and how a row is written."""

    name: str
    header: str
    tag: str
    line: Callable[[Any], str]


TEMPLATES = RowFile("templates.csv", TEMPLATES_HEADER, "t", template_line)
TRAJECTORY = RowFile("trajectory.tum", "", "p", trajectory_line)
CLOSURES = RowFile("closures.csv", CLOSURES_HEADER, "c", closure_line)
ROW_FILES = (TEMPLATES, TRAJECTORY, CLOSURES)


def rows_written_before(run_dir: str, counts: dict[str, int], journal: str
                        ) -> tuple[dict[str, list[bytes]], list[tuple[str, int]]]:
    """What a checkpoint's run folder held when the checkpoint was cut, for a run resumed from it
    into another folder (``--resume``): the first ``counts[tag]`` rows of each row file (without
    its header), and the journal entries ``(tag, frame)`` naming them, in their order. A checkpoint
    keeps no written row (the files are the record), so a resumed run's files begin with these."""
    folder = Path(run_dir)
    lines: dict[str, list[bytes]] = {}
    for f in ROW_FILES:
        path = folder / f.name
        rows = complete_lines(path) if path.exists() else []
        if f.header and rows and rows[0] == f.header.encode():
            rows = rows[1:]
        if len(rows) < counts.get(f.tag, 0):
            raise FileNotFoundError(f"{path} holds {len(rows)} rows, the checkpoint counted {counts[f.tag]}")
        lines[f.tag] = rows[:counts.get(f.tag, 0)]
    entries, seen = [], dict.fromkeys(counts, 0)
    path = folder / journal
    for raw in (complete_lines(path)[1:] if path.exists() else []):
        parts = raw.split()
        tag = parts[0].decode(errors="replace") if len(parts) == 2 else ""
        if tag in seen and parts[1].isdigit() and seen[tag] < counts[tag]:
            seen[tag] += 1
            entries.append((tag, int(parts[1])))
    return lines, entries
