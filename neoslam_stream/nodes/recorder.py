"""The recorder node: writes a run's outputs from the topics, so no algorithm node writes files.

From ``visual_template``, ``experience_map/pose``, ``experience_map/map`` and ``groundtruth`` it
writes templates.csv, closures.csv (:data:`CLOSURES_HEADER`), trajectory.tum, map.json,
trajectory_map.tum (every pose re-expressed on the final map: :func:`poses_on_map`) and, with
``mcap``, ``outputs.mcap`` (docs/ros2.md). An observer in the experience map's worker; its rows
are its state, so checkpoints, ``--resume`` and crash restarts give an uninterrupted run's files.

Why it writes as it does (docs/reliability.md, docs/evaluation.md): row files are appended row by
row, each noted first in a journal (:data:`JOURNAL`), so a killed worker loses no row and its
restart neither loses nor doubles one; map.json and trajectory_map.tum are replaced atomically at
the end. A closure row waits for its frame's ground truth (at most ``GT_WAIT_ROWS`` closures). An
``OSError`` (disk full) is logged once per file and counted; unwritten rows are retried at most
every ``RETRY_S`` seconds and at the end, and what was written stays intact.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from ..algorithms.ratslam.experience_map import poses_on_map
from ..runtime.files import AppendFile, complete_lines, describe_write_error, write_atomic
from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, GROUNDTRUTH, VISUAL_TEMPLATE

log = logging.getLogger("neoslam.recorder")

TEMPLATES_HEADER = "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
#: one row per loop closure: the matched frame opened the matched interval (or created the matched
#: template); true_distance_m between the true positions of the two frames (empty without ground
#: truth); score and second_score are the front end's best and runner-up scores (D: overlaps;
#: the oracle: distances in metres; empty where the front end has no runner-up) and margin their
#: difference, how much the winner beat the runner-up (|score - second_score|: the best score is
#: the front end's best by definition, whichever way its scores run)
CLOSURES_HEADER = "frame,stamp,template_id,matched_frame,true_distance_m,score,second_score,margin\n"
#: the recorder's journal of the rows it appended (see the module docstring)
JOURNAL = ".recorder.journal"
TEMPLATES, TRAJECTORY, CLOSURES = "templates.csv", "trajectory.tum", "closures.csv"
#: the trajectory re-expressed on the final map (written at the end, see the module docstring)
TRAJECTORY_ON_MAP = "trajectory_map.tum"
#: closure rows that wait for ground truth before they are written without it when none has come
GT_WAIT_ROWS = 64
#: the outputs as ROS 2 messages (docs/ros2.md)
MCAP = "outputs.mcap"
#: true positions kept for frames whose template has not come yet, at most
GT_KEEP = 4096


def template_line(r: tuple) -> str:
    """One row of templates.csv: frame, stamp, template id, loop closure 0/1, best interval, best
    score as the front end gave it (D's overlap count, the local view's match error)."""
    return f"{r[0]},{r[1]:.6f},{r[2]},{r[3]},{r[4]},{r[5]}\n"


def trajectory_line(r: tuple) -> str:
    """One row of trajectory.tum for a recorder row (frame, stamp, x, y, theta, exp id): exactly
    ``tum.write_tum``'s format (``t x y z qx qy qz qw``)."""
    t, x, y, yaw = r[1], r[2], r[3], r[4]
    return f"{t:.6f} {x:.6f} {y:.6f} 0 0 0 {np.sin(yaw / 2):.9f} {np.cos(yaw / 2):.9f}\n"


def _num(v: Any) -> str:
    """A score as the front end gave it: an int as an int, a float with 6 significant digits."""
    if v is None:
        return ""
    if isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer() and abs(v) < 2**53):
        return str(int(v))
    return f"{float(v):.6g}"


def closure_line(r: tuple) -> str:
    """One row of closures.csv for a recorder closure row (frame, stamp, template id, matched frame,
    true distance or None, score, runner-up's score or None)."""
    frame, stamp, tid, matched, dist, score, second = r
    margin = None if second is None or score is None else abs(float(score) - float(second))
    return (f"{frame},{stamp:.6f},{tid},{matched},{'' if dist is None else f'{dist:.3f}'},"
            f"{_num(score)},{_num(second)},{'' if margin is None else _num(margin)}\n")


def write_templates_csv(path: str | Path, rows: list) -> None:
    """templates.csv with ``rows`` (written whole and atomically)."""
    write_atomic(path, (TEMPLATES_HEADER + "".join(template_line(r) for r in rows)).encode())


class RecorderNode(Node):
    """Writes templates.csv and trajectory.tum into ``run_dir`` row by row, map.json at the end."""

    inputs = (VISUAL_TEMPLATE, EXPERIENCE_POSE, EXPERIENCE_MAP, GROUNDTRUTH)
    outputs = ()
    unordered_inputs = (EXPERIENCE_MAP, GROUNDTRUTH)
    observer = True
    #: seconds between two attempts to write rows that could not be written (disk full)
    RETRY_S = 1.0

    def __init__(self, mcap: dict[str, Any] | None = None) -> None:
        super().__init__()
        #: the ROS 2 message parameters of outputs.mcap (None: no MCAP; nodes.ros2_out)
        self.mcap = mcap
        self.templates: list[tuple[int, float, int, int, int, Any]] = []
        self.trajectory: list[tuple[int, float, float, float, float, int]] = []
        self.map_export: dict[str, Any] | None = None
        #: frame -> (stamp, experience id, dx, dy, dtheta in its frame) for trajectory_map.tum
        self.local_poses: dict[int, tuple[float, int, float, float, float]] = {}
        #: closures.csv rows written (frame, stamp, template, matched frame, distance, score, second)
        self.closures: list[tuple] = []
        #: closure rows waiting for the ground truth of their frame
        self.closures_waiting: list[tuple] = []
        #: the frame that created each template / opened each of D's intervals
        self.template_first: dict[int, int] = {}
        self.interval_first: dict[int, int] = {}
        #: true (x, y) of those first frames, and of frames whose template has not come yet
        self.places: dict[int, tuple[float, float]] = {}
        self.gt: dict[int, tuple[float, float]] = {}
        self.gt_last_frame = -1
        self.last_template_frame = -1
        self._first_frames: set[int] = set()
        #: the open output files by kind ("t": templates.csv, "p": trajectory.tum, "c": closures.csv)
        self._files: dict[str, AppendFile] | None = None
        self._journal: AppendFile | None = None
        #: rows to append, in order: (kind, frame, line)
        self._backlog: deque[tuple[str, int, bytes]] = deque()
        #: after a restart, the frames each file held already (rows for them are not written again)
        self._written: dict[str, set[int]] = {"t": set(), "p": set(), "c": set()}
        self._retry_at = 0.0
        self._logged: set[str] = set()

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if topic == VISUAL_TEMPLATE:
            row = (msg.frame, msg.stamp, int(d["id"]), int(bool(d.get("is_loop_closure", False))),
                   int(d.get("best_interval", -1)), d.get("best_score", -1))
            self._add("t", row, self.templates, template_line)
            self._closure(msg)
        elif topic == GROUNDTRUTH:
            self._groundtruth(msg.frame, d["pose"])
        elif topic == EXPERIENCE_POSE:
            x, y, th = (float(v) for v in d["pose"])
            exp_id = int(d.get("exp_id", -1))
            if d.get("local") is not None:  # kept even for a frame written before a restart
                dx, dy, dth = (float(v) for v in d["local"])
                self.local_poses[msg.frame] = (msg.stamp, exp_id, dx, dy, dth)
            self._add("p", (msg.frame, msg.stamp, x, y, th, exp_id), self.trajectory, trajectory_line)
        else:
            self.map_export = d.get("export")
        return []

    # ------------------------------------------------------------------ closures.csv
    def _closure(self, msg: Message) -> None:
        """Note the first frame of the template (and interval), queue a closure row, write those
        whose ground truth is settled."""
        d, f = msg.data, msg.frame
        tid = int(d["id"])
        interval = d.get("interval")
        firsts = []
        if tid not in self.template_first:
            self.template_first[tid] = f
            firsts.append(f)
        if interval is not None and int(interval) not in self.interval_first:
            self.interval_first[int(interval)] = f
            firsts.append(f)
        if firsts:
            self._first_frames.add(f)
            if f in self.gt:
                self.places[f] = self.gt[f]
        self.last_template_frame = max(self.last_template_frame, f)
        if d.get("is_loop_closure"):
            best = int(d.get("best_interval", -1))
            matched = self.interval_first.get(best, -1) if interval is not None and best >= 0 \
                else self.template_first.get(tid, -1)
            self.closures_waiting.append((f, msg.stamp, tid, matched, self.gt.get(f), d.get("best_score"),
                                          d.get("second_score")))
        # true positions of frames whose template has come are needed only as places
        for g in [g for g in self.gt if g < f]:
            del self.gt[g]
        self._settle_closures()

    def _groundtruth(self, frame: int, pose: Any) -> None:
        xy = (float(pose[0]), float(pose[1]))
        self.gt_last_frame = max(self.gt_last_frame, frame)
        if frame in self._first_frames:
            self.places[frame] = xy
        if frame >= self.last_template_frame:
            self.gt[frame] = xy
            if len(self.gt) > GT_KEEP:  # no template for a long time (a stalled front end): bounded
                del self.gt[min(self.gt)]
        self.closures_waiting = [r if r[4] is not None or r[0] != frame else (*r[:4], xy, *r[5:])
                                 for r in self.closures_waiting]
        self._settle_closures()

    def _settle_closures(self, final: bool = False) -> None:
        """Write the waiting closure rows, in order, whose true distance is known or will never be."""
        while self.closures_waiting:
            f, stamp, tid, matched, pos, score, second = self.closures_waiting[0]
            place = self.places.get(matched)
            no_gt = (self.gt_last_frame > f and pos is None) or \
                (self.gt_last_frame < 0 and len(self.closures_waiting) > GT_WAIT_ROWS)
            if not (final or no_gt or (pos is not None and place is not None)
                    or (pos is not None and matched < self.gt_last_frame)):
                return
            self.closures_waiting.pop(0)
            dist = None if pos is None or place is None else float(np.hypot(pos[0] - place[0], pos[1] - place[1]))
            self._add("c", (f, stamp, tid, matched, dist, score, second), self.closures, closure_line)

    def _add(self, kind: str, row: tuple, rows: list, line: Any) -> None:
        if not self.run_dir:
            rows.append(row)
            return
        self._open()
        if row[0] in self._written[kind]:  # written before this worker was restarted
            self.counters["rows_already_written"] = self.counters.get("rows_already_written", 0) + 1
            return
        rows.append(row)
        self._backlog.append((kind, row[0], line(row).encode()))
        if len(self._backlog) == 1 or time.monotonic() >= self._retry_at:
            self._write_backlog()

    # ------------------------------------------------------------------ files
    def _paths(self) -> dict[str, Path]:
        out = Path(self.run_dir)
        return {"t": out / TEMPLATES, "p": out / TRAJECTORY, "c": out / CLOSURES, "j": out / JOURNAL}

    def _open(self) -> None:
        """Open the files at the first row (or at the end): afresh for a new run, as they are for a
        restart of this run's worker (see the module docstring)."""
        if self._files is not None or time.monotonic() < self._retry_at:
            return
        paths = self._paths()
        try:
            paths["t"].parent.mkdir(parents=True, exist_ok=True)
            journal = complete_lines(paths["j"]) if self.run_id else []
            if journal and journal[0] == f"run {self.run_id}\n".encode():
                self._reopen(paths, journal)
            else:
                self._create(paths)
        except OSError as exc:
            self._failed(paths["t"].parent, exc)
            return
        # the rows held in memory (the restored state's, and any that came while the files could not
        # be opened) that are not in the files yet: all of them for new files
        self._backlog.clear()
        for kind, rows, line in (("t", self.templates, template_line), ("p", self.trajectory, trajectory_line),
                                 ("c", self.closures, closure_line)):
            for r in rows:
                if r[0] not in self._written[kind]:
                    self._backlog.append((kind, r[0], line(r).encode()))
        self._write_backlog()

    def _create(self, paths: dict[str, Path]) -> None:
        if self.run_id:
            self._journal = AppendFile(paths["j"], truncate=True)
            self._journal.append(f"run {self.run_id}\n".encode())
        files = {k: AppendFile(paths[k], truncate=True) for k in ("t", "p", "c")}
        files["t"].append(TEMPLATES_HEADER.encode())
        files["c"].append(CLOSURES_HEADER.encode())
        self._files = files

    def _reopen(self, paths: dict[str, Path], journal: list[bytes]) -> None:
        """A restart of this run's worker: keep the complete rows the journal knows, cut the rest."""
        kinds = ("t", "p", "c")
        headers = {"t": TEMPLATES_HEADER.encode(), "p": b"", "c": CLOSURES_HEADER.encode()}
        entries: list[tuple[str, int]] = []
        for raw in journal[1:]:
            parts = raw.split()
            if len(parts) == 2 and parts[0].decode(errors="replace") in kinds and parts[1].isdigit():
                entries.append((parts[0].decode(), int(parts[1])))
        files = {}
        keep = {}
        for k in kinds:
            lines = complete_lines(paths[k]) if paths[k].exists() else []
            header = headers[k]
            has_header = not header or (bool(lines) and lines[0] == header)
            rows = lines[1:] if header and has_header else (lines if not header else [])
            keep[k] = min(len(rows), sum(1 for e, _ in entries if e == k))
            files[k] = AppendFile(paths[k])
            files[k].cut(len(header) + sum(map(len, rows[:keep[k]])) if has_header else 0)
            if not has_header:
                files[k].append(header)
            if k == "t":
                # the templates' first frames, for the matched frames of later closures (a restart
                # without a checkpoint lost them; their true positions stay unknown: empty distances)
                for raw in rows[:keep[k]]:
                    parts = raw.split(b",")
                    if len(parts) >= 3 and parts[0].isdigit() and parts[2].lstrip(b"-").isdigit():
                        self.template_first.setdefault(int(parts[2]), int(parts[0]))
        self._first_frames |= set(self.template_first.values())
        kept, seen = [], dict.fromkeys(kinds, 0)
        for kind, frame in entries:
            if seen[kind] < keep[kind]:
                seen[kind] += 1
                kept.append((kind, frame))
                self._written[kind].add(frame)
        write_atomic(paths["j"], (f"run {self.run_id}\n" + "".join(f"{k} {f}\n" for k, f in kept)).encode())
        self._journal = AppendFile(paths["j"])
        self._files = files
        log.warning("recorder: restarted; kept %d template rows, %d trajectory rows and %d closure rows "
                    "written before", keep["t"], keep["p"], keep["c"])

    def _write_backlog(self) -> None:
        """Append the waiting rows in order (journal entry first, then the row); stop at a failure,
        leaving every file with complete rows only, and try again ``RETRY_S`` later."""
        if self._files is None:
            return
        while self._backlog:
            kind, frame, line = self._backlog[0]
            target = self._files[kind]
            try:
                if self._journal is not None:
                    before = self._journal.size
                    self._journal.append(f"{kind} {frame}\n".encode())
                try:
                    target.append(line)
                except OSError:
                    if self._journal is not None:
                        self._journal.cut(before)
                    raise
            except OSError as exc:
                self._failed(target.path, exc)
                return
            self._backlog.popleft()

    def _failed(self, path: Path, exc: OSError) -> None:
        self.counters["write_errors"] = self.counters.get("write_errors", 0) + 1
        self._retry_at = time.monotonic() + self.RETRY_S
        if str(path) not in self._logged:
            self._logged.add(str(path))
            log.error("recorder: %s (rows wait and are tried again; further errors are counted)",
                      describe_write_error(path, exc))

    def flush(self) -> Output:
        self._settle_closures(final=True)
        if not self.run_dir:
            return []
        if self._files is None and not (self.templates or self.trajectory or self.closures
                                        or (self.map_export or {}).get("nodes")):
            self._no_outputs()  # a run that failed before its first frame leaves no empty results
            return []
        self._retry_at = 0.0  # the end: one more attempt at whatever is waiting
        self._open()
        self._write_backlog()
        if self._backlog:
            log.error("recorder: %d rows could not be written to %s", len(self._backlog), self.run_dir)
        for f in (self._files or {}).values():
            try:
                f.sync()
            except OSError as exc:
                self._failed(f.path, exc)
        if self.map_export is not None:
            path = Path(self.run_dir) / "map.json"
            try:
                write_atomic(path, json.dumps(self.map_export).encode())
            except OSError as exc:  # the previous map.json, if any, is intact
                self._failed(path, exc)
            if self.local_poses:
                path = Path(self.run_dir) / TRAJECTORY_ON_MAP
                try:
                    write_atomic(path, self.trajectory_on_map().encode())
                except OSError as exc:
                    self._failed(path, exc)
        if self.mcap is not None:
            self._write_mcap()
        return []

    def _no_outputs(self) -> None:
        """Nothing was recorded: no output file is created, and those an earlier run left in this
        folder go (a restart of this run's worker keeps its files, which its journal names)."""
        out = Path(self.run_dir)
        journal = complete_lines(out / JOURNAL) if self.run_id else []
        if journal and journal[0] == f"run {self.run_id}\n".encode():
            return
        for name in (TEMPLATES, TRAJECTORY, CLOSURES, JOURNAL, "map.json", TRAJECTORY_ON_MAP, MCAP):
            try:
                (out / name).unlink(missing_ok=True)
            except OSError as exc:
                self._failed(out / name, exc)

    def trajectory_on_map(self) -> str:
        """trajectory_map.tum's text: the frames' poses on the final map (``trajectory.tum``'s
        format, in frame order)."""
        nodes = {int(n["id"]): (float(n["x"]), float(n["y"]), float(n["theta"]))
                 for n in (self.map_export or {}).get("nodes", [])}
        frames = sorted(self.local_poses)
        rows = [self.local_poses[f] for f in frames]
        poses = poses_on_map(nodes, np.array([r[1] for r in rows], dtype=np.int64),
                             np.array([r[2:] for r in rows], dtype=np.float64))
        return "".join(trajectory_line((f, r[0], *p)) for f, r, p in zip(frames, rows, poses.tolist(), strict=True))

    def _write_mcap(self) -> None:
        """outputs.mcap: the run's outputs as the ROS 2 messages of the live output, rebuilt from
        the rows (so a restarted worker's file is whole), written at the end, atomically."""
        from .ros2_out import Ros2Messages, mcap_bytes, replay

        conv = Ros2Messages(**self.mcap)
        data = mcap_bytes(conv, replay(conv, self.templates, self.trajectory, self.map_export))
        path = Path(self.run_dir) / MCAP
        try:
            write_atomic(path, data)
        except OSError as exc:
            self._failed(path, exc)

    def close(self) -> None:
        for f in [*(self._files or {}).values(), self._journal]:
            if f is not None:
                f.close()
        self._files, self._journal = None, None

    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = {"template_rows": len(self.templates), "trajectory_rows": len(self.trajectory),
                               "closure_rows": len(self.closures)}
        if self._backlog:
            out["rows_not_written"] = len(self._backlog)
        return out

    def state_dict(self) -> dict[str, Any]:
        def ints(d: dict[int, int]) -> np.ndarray:
            return np.array(sorted(d.items()), dtype=np.int64).reshape(-1, 2)

        def where(d: dict[int, tuple[float, float]]) -> np.ndarray:
            return np.array([(k, *v) for k, v in sorted(d.items())], dtype=np.float64).reshape(-1, 3)

        return {"templates": [list(r) for r in self.templates], "trajectory": [list(r) for r in self.trajectory],
                "closures": [list(r) for r in self.closures],
                "closures_waiting": [[*r[:4], None if r[4] is None else list(r[4]), r[5], r[6]]
                                     for r in self.closures_waiting],
                "template_first": ints(self.template_first), "interval_first": ints(self.interval_first),
                "places": where(self.places), "gt": where(self.gt), "gt_last_frame": self.gt_last_frame,
                "local_poses": np.array([(f, *r) for f, r in sorted(self.local_poses.items())],
                                        dtype=np.float64).reshape(-1, 6),
                "last_template_frame": self.last_template_frame}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.templates = [(int(r[0]), float(r[1]), int(r[2]), int(r[3]), int(r[4]), r[5]) for r in st["templates"]]
        self.trajectory = [(int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]), int(r[5]))
                           for r in st["trajectory"]]
        # closures: a state saved before closures.csv existed has none of these keys
        self.closures = [(int(r[0]), float(r[1]), int(r[2]), int(r[3]), None if r[4] is None else float(r[4]),
                          r[5], r[6]) for r in st.get("closures", [])]
        self.closures_waiting = [(int(r[0]), float(r[1]), int(r[2]), int(r[3]),
                                  None if r[4] is None else (float(r[4][0]), float(r[4][1])), r[5], r[6])
                                 for r in st.get("closures_waiting", [])]
        self.template_first = {int(k): int(v) for k, v in np.asarray(st.get("template_first", []),
                                                                     dtype=np.int64).reshape(-1, 2)}
        self.interval_first = {int(k): int(v) for k, v in np.asarray(st.get("interval_first", []),
                                                                     dtype=np.int64).reshape(-1, 2)}
        self.places = {int(r[0]): (float(r[1]), float(r[2]))
                       for r in np.asarray(st.get("places", []), dtype=np.float64).reshape(-1, 3)}
        self.gt = {int(r[0]): (float(r[1]), float(r[2]))
                   for r in np.asarray(st.get("gt", []), dtype=np.float64).reshape(-1, 3)}
        self.local_poses = {int(r[0]): (float(r[1]), int(r[2]), float(r[3]), float(r[4]), float(r[5]))
                            for r in np.asarray(st.get("local_poses", []), dtype=np.float64).reshape(-1, 6)}
        self.gt_last_frame = int(st.get("gt_last_frame", -1))
        self.last_template_frame = int(st.get("last_template_frame", -1))
        self._first_frames = set(self.template_first.values()) | set(self.interval_first.values())

    def new_session(self) -> None:
        self.templates, self.trajectory, self.map_export = [], [], None  # this session's outputs only
        self.local_poses = {}
        self.closures, self.closures_waiting = [], []
        # an old session's templates may be matched again: keep where they were first seen, but a
        # new session's frame numbers start afresh, so its first frames are no places of this one
        self.template_first, self.interval_first, self.places, self.gt = {}, {}, {}, {}
        self._first_frames = set()
        self.gt_last_frame = self.last_template_frame = -1


def make_node(mcap: dict[str, Any] | None = None) -> RecorderNode:
    return RecorderNode(mcap)
