"""The run folder: the one writer of a run's outputs, called by the recorder node and the API alike.

:class:`RunFolder` takes what the cores produce, frame by frame (a template, the map's pose, the
ground truth) and the final map, and writes templates.csv, closures.csv (:data:`CLOSURES_HEADER`),
trajectory.tum, map.json, trajectory_map.tum (every pose re-expressed on the final map:
:func:`poses_on_map`) and, with ``mcap``, ``outputs.mcap`` (docs/ros2.md). Its rows are its state,
so checkpoints, ``--resume`` and crash restarts give an uninterrupted run's files.

Why it writes as it does (docs/reliability.md, docs/evaluation.md): row files are appended row by
row, each noted first in a journal (:data:`JOURNAL`: a line ``<tag> <frame>`` per row, the tag
naming the file), so a killed worker loses no row and its restart neither loses nor doubles one;
map.json and trajectory_map.tum are replaced atomically at the end. A closure row waits for its
frame's ground truth (at most ``GT_WAIT_ROWS`` closures). With a run folder, a row is kept in
memory only until it is in its file (the files are the record; a day's rows as Python objects would
hold ~1 kB a frame, 100 MB an hour at 30 FPS): what the end needs of every frame is kept as numbers
(``run_numbers.py``), its pose in its experience's frame for trajectory_map.tum and, with an MCAP,
its template and pose for outputs.mcap, in scratch files of the run folder (removed at close) with
one block in memory; the first frame of each template and interval, and its true place, in sorted
arrays (40 bytes an interval). An ``OSError`` (disk full) is logged once
per file and counted; unwritten rows are retried at most every ``RETRY_S`` seconds and at the end,
and what was written stays intact.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from ..algorithms.ratslam.map_poses import export_node_poses, poses_on_map
from ..algorithms.records import MapPose, Template
from ..runtime.files import AppendFile, complete_lines, describe_write_error, write_atomic
from .run_numbers import KeyedNumbers, NumberRows
from .run_rows import (
    CLOSURES,
    ROW_FILES,
    TEMPLATES,
    TRAJECTORY,
    ClosureRow,
    PoseRow,
    RowFile,
    TemplateRow,
    WaitingClosure,
    rows_written_before,
    trajectory_line,
)

log = logging.getLogger("neoslam.recorder")

#: the journal of the rows appended (see the module docstring)
JOURNAL = ".recorder.journal"
#: the trajectory re-expressed on the final map (written at the end, see the module docstring)
TRAJECTORY_ON_MAP = "trajectory_map.tum"
#: closure rows that wait for ground truth before they are written without it when none has come
GT_WAIT_ROWS = 64
#: the outputs as ROS 2 messages (docs/ros2.md)
MCAP = "outputs.mcap"
#: true positions kept for frames whose template has not come yet, at most
GT_KEEP = 4096


def mcap_params(ros2_out: Any) -> dict[str, Any] | None:
    """outputs.mcap's ROS 2 message parameters from a run's ``ros2_out`` section (None: no MCAP)."""
    if not ros2_out.mcap:
        return None
    return {**ros2_out.message_params(), "map_period_s": ros2_out.mcap_map_period_s}


class RunFolder:
    """Writes templates.csv and trajectory.tum into ``run_dir`` row by row, closures.csv as each
    closure's ground truth settles, map.json and trajectory_map.tum at the end. Without a
    ``run_dir`` it keeps the rows in memory only. ``run_id`` (a pipeline run's): a restart of the
    same run keeps the rows its journal names; "" (in-process): no journal. ``counters`` is the
    host's counter dict (``rows_already_written``, ``write_errors``)."""

    #: seconds between two attempts to write rows that could not be written (disk full)
    RETRY_S = 1.0

    def __init__(self, run_dir: str = "", run_id: str = "", mcap: dict[str, Any] | None = None,
                 counters: dict[str, int] | None = None) -> None:
        self.run_dir, self.run_id = run_dir, run_id
        #: the ROS 2 message parameters of outputs.mcap (None: no MCAP; nodes.ros2_out)
        self.mcap = mcap
        self.counters = counters if counters is not None else {}
        #: with an MCAP and a run folder: (frame, stamp, template, closure) of each template row and
        #: (frame, stamp, x, y, theta, experience) of each pose row, what outputs.mcap is built from
        self._mcap_rows = {TEMPLATES: NumberRows(4), TRAJECTORY: NumberRows(6)} if mcap else None
        self.rows: dict[RowFile, deque] = {f: deque() for f in ROW_FILES}
        #: rows accepted per file (what info() reports)
        self.n_rows: dict[RowFile, int] = dict.fromkeys(ROW_FILES, 0)
        self.map_export: dict[str, Any] | None = None
        #: per pose: frame, stamp, experience id, dx, dy, dtheta in its frame (trajectory_map.tum)
        self._local = NumberRows(6)
        #: closure rows waiting for the ground truth of their frame
        self.closures_waiting: list[WaitingClosure] = []
        #: the frame that created each template / opened each of D's intervals
        self.template_first, self.interval_first = KeyedNumbers(1), KeyedNumbers(1)
        #: true (x, y) of those first frames
        self.places = KeyedNumbers(2)
        #: true (x, y) of frames whose template has not come yet
        self.gt: dict[int, tuple[float, float]] = {}
        self.gt_last_frame = -1
        self.last_template_frame = -1
        #: first frames whose true place has not come yet
        self._awaiting_place: set[int] = set()
        self._files: dict[RowFile, AppendFile] | None = None
        self._journal: AppendFile | None = None
        #: rows to append, in order: (file, frame, line)
        self._backlog: deque[tuple[RowFile, int, bytes]] = deque()
        #: after a restart, the frames each file held already (rows for them are not written again)
        self._written: dict[RowFile, set[int]] = {f: set() for f in ROW_FILES}
        #: rows in each file (what a checkpoint counts: a run resumed elsewhere begins with them)
        self._in_file: dict[RowFile, int] = dict.fromkeys(ROW_FILES, 0)
        #: from a checkpoint: (its run folder, rows in each file by tag), copied into new files
        self._carry: tuple[str, dict[str, int]] | None = None
        self._retry_at = 0.0
        self._logged: set[str] = set()

    @property
    def _keep(self) -> bool:
        """Whether every row is held: without a run folder (the host may set one after making this
        writer); with one, rows are dropped once written (the module docstring)."""
        return not self.run_dir

    @property
    def templates(self) -> list[TemplateRow]:
        """The template rows held (every one in memory and with an MCAP; else the unwritten ones)."""
        return list(self.rows[TEMPLATES])

    @property
    def trajectory(self) -> list[PoseRow]:
        return list(self.rows[TRAJECTORY])

    @property
    def closures(self) -> list[ClosureRow]:
        return list(self.rows[CLOSURES])

    @property
    def local_poses(self) -> np.ndarray:
        """(frame, stamp, experience id, dx, dy, dtheta) of every pose, the latest of each frame,
        in frame order."""
        return self._local.latest_by_frame()

    # ------------------------------------------------------------------ what the cores give
    def on_template(self, frame: int, stamp: float, t: Template) -> None:
        """A frame's visual template: its row, the first frame of its template (and interval),
        and a closure row when it closed a loop."""
        self._add(TEMPLATES, TemplateRow(frame, stamp, int(t["id"]), int(bool(t.get("is_loop_closure", False))),
                                         int(t.get("best_interval", -1)), t.get("best_score", -1)))
        tid = int(t["id"])
        interval = t.get("interval")
        first = False
        if tid not in self.template_first:
            self.template_first.set(tid, (frame,))
            first = True
        if interval is not None and int(interval) not in self.interval_first:
            self.interval_first.set(int(interval), (frame,))
            first = True
        if first:
            if frame in self.gt:
                self.places.set(frame, self.gt[frame])
            else:
                self._await_place(frame)
        self.last_template_frame = max(self.last_template_frame, frame)
        if t.get("is_loop_closure"):
            best = int(t.get("best_interval", -1))
            matched = _first(self.interval_first, best) if interval is not None and best >= 0 \
                else _first(self.template_first, tid)
            self.closures_waiting.append(WaitingClosure(frame, stamp, tid, matched, self.gt.get(frame),
                                                        t.get("best_score"), t.get("second_score"),
                                                        t.get("confidence")))
        # true positions of frames whose template has come are needed only as places
        for g in [g for g in self.gt if g < frame]:
            del self.gt[g]
        self._settle_closures()

    def on_pose(self, frame: int, stamp: float, p: MapPose) -> None:
        """The map's pose of the robot after a frame (and, for trajectory_map.tum, its pose in its
        experience's frame)."""
        x, y, th = (float(v) for v in p.pose)
        if p.local is not None:  # kept even for a frame written before a restart
            self._local.append((frame, stamp, int(p.exp_id), *(float(v) for v in p.local)))
        self._add(TRAJECTORY, PoseRow(frame, stamp, x, y, th, int(p.exp_id)))

    def on_groundtruth(self, frame: int, pose: Any) -> None:
        """The true pose of a frame: the places of template firsts and the closures' distances."""
        xy = (float(pose[0]), float(pose[1]))
        self.gt_last_frame = max(self.gt_last_frame, frame)
        if frame in self._awaiting_place:
            self._awaiting_place.discard(frame)
            self.places.set(frame, xy)
        if frame >= self.last_template_frame:
            self.gt[frame] = xy
            if len(self.gt) > GT_KEEP:  # no template for a long time (a stalled front end): bounded
                del self.gt[min(self.gt)]
        self.closures_waiting = [r._replace(true_xy=xy) if r.true_xy is None and r.frame == frame else r
                                 for r in self.closures_waiting]
        self._settle_closures()

    def on_map(self, export: dict[str, Any] | None) -> None:
        """The whole map (``ExperienceMap.export()``): map.json and trajectory_map.tum at the end."""
        self.map_export = export

    def _settle_closures(self, final: bool = False) -> None:
        """Write the waiting closure rows, in order, whose true distance is known or will never be."""
        while self.closures_waiting:
            r = self.closures_waiting[0]
            pos, place = r.true_xy, self.places.get(r.matched_frame)
            no_gt = (self.gt_last_frame > r.frame and pos is None) or \
                (self.gt_last_frame < 0 and len(self.closures_waiting) > GT_WAIT_ROWS)
            if not (final or no_gt or (pos is not None and place is not None)
                    or (pos is not None and r.matched_frame < self.gt_last_frame)):
                return
            self.closures_waiting.pop(0)
            dist = None if pos is None or place is None else float(np.hypot(pos[0] - place[0], pos[1] - place[1]))
            self._add(CLOSURES, ClosureRow(r.frame, r.stamp, r.template_id, r.matched_frame, dist, r.score,
                                           r.second_score, r.confidence))

    def _add(self, file: RowFile, row: Any) -> None:
        if self._mcap_rows is not None and self.run_dir and file in self._mcap_rows:
            self._mcap_rows[file].append(tuple(row[:4]) if file is TEMPLATES else tuple(row))
        if not self.run_dir:
            self.rows[file].append(row)
            self.n_rows[file] += 1
            return
        self._open()
        if row.frame in self._written[file]:  # written before this worker was restarted
            self.counters["rows_already_written"] = self.counters.get("rows_already_written", 0) + 1
            return
        self.rows[file].append(row)
        self.n_rows[file] += 1
        self._backlog.append((file, row.frame, file.line(row).encode()))
        if len(self._backlog) == 1 or time.monotonic() >= self._retry_at:
            self._write_backlog()

    # ------------------------------------------------------------------ files
    def _path(self, name: str) -> Path:
        return Path(self.run_dir) / name

    def _open(self) -> None:
        """Open the files at the first row (or at the end): afresh for a new run, as they are for a
        restart of this run's worker (see the module docstring)."""
        if self._files is not None or time.monotonic() < self._retry_at:
            return
        try:
            Path(self.run_dir).mkdir(parents=True, exist_ok=True)
            journal = complete_lines(self._path(JOURNAL)) if self.run_id else []
            if journal and journal[0] == f"run {self.run_id}\n".encode():
                self._reopen(journal)
            else:
                self._create()
        except OSError as exc:
            self._failed(Path(self.run_dir), exc)
            return
        # the rows held in memory (the restored state's, and any that came while the files could not
        # be opened) that are not in the files yet: all of them for new files
        self._backlog.clear()
        for f in ROW_FILES:
            if not self._keep:  # held rows are the unwritten ones, in the backlog's order
                self.rows[f] = deque(r for r in self.rows[f] if r.frame not in self._written[f])
            for r in self.rows[f]:
                if r.frame not in self._written[f]:
                    self._backlog.append((f, r.frame, f.line(r).encode()))
        self._write_backlog()
        self._spill()

    def _create(self) -> None:
        lines, entries = self._carried()  # read before the files are cut (the same folder, resumed)
        if self.run_id:
            self._journal = AppendFile(self._path(JOURNAL), truncate=True)
            self._journal.append(f"run {self.run_id}\n".encode())
            for tag, frame in entries:
                self._journal.append(f"{tag} {frame}\n".encode())
        files = {f: AppendFile(self._path(f.name), truncate=True) for f in ROW_FILES}
        for f in ROW_FILES:
            if f.header:
                files[f].append(f.header.encode())
            for line in lines.get(f.tag, []):
                files[f].append(line)
            self._in_file[f] = len(lines.get(f.tag, []))
        self._files = files

    def _carried(self) -> tuple[dict[str, list[bytes]], list[tuple[str, int]]]:
        """Resumed from a checkpoint: the rows its run folder held then, which begin this run's files."""
        if self._carry is None:
            return {}, []
        folder, counts = self._carry
        self._carry = None
        try:
            return rows_written_before(folder, counts, JOURNAL)
        except OSError as exc:
            log.error("recorder: the rows written before the checkpoint could not be read (%s); this run's "
                      "files begin at the checkpoint", exc)
            return {}, []

    def _reopen(self, journal: list[bytes]) -> None:
        """A restart of this run's worker: keep the complete rows the journal knows, cut the rest."""
        by_tag = {f.tag: f for f in ROW_FILES}
        entries: list[tuple[RowFile, int]] = []
        for raw in journal[1:]:
            parts = raw.split()
            if len(parts) == 2 and parts[0].decode(errors="replace") in by_tag and parts[1].isdigit():
                entries.append((by_tag[parts[0].decode()], int(parts[1])))
        files, keep = {}, {}
        for f in ROW_FILES:
            path, header = self._path(f.name), f.header.encode()
            lines = complete_lines(path) if path.exists() else []
            has_header = not header or (bool(lines) and lines[0] == header)
            rows = lines[1:] if header and has_header else (lines if not header else [])
            keep[f] = min(len(rows), sum(1 for e, _ in entries if e is f))
            files[f] = AppendFile(path)
            files[f].cut(len(header) + sum(map(len, rows[:keep[f]])) if has_header else 0)
            if not has_header:
                files[f].append(header)
            if f is TEMPLATES:
                # the templates' first frames, for the matched frames of later closures (a restart
                # without a checkpoint lost them; their true positions stay unknown: empty distances)
                for raw in rows[:keep[f]]:
                    cols = raw.split(b",")
                    if len(cols) >= 3 and cols[0].isdigit() and cols[2].lstrip(b"-").isdigit() \
                            and int(cols[2]) not in self.template_first:
                        self.template_first.set(int(cols[2]), (int(cols[0]),))
                        self._await_place(int(cols[0]))
        kept, seen = [], dict.fromkeys(ROW_FILES, 0)
        for f, frame in entries:
            if seen[f] < keep[f]:
                seen[f] += 1
                kept.append((f, frame))
                self._written[f].add(frame)
        self._in_file = dict(keep)
        write_atomic(self._path(JOURNAL),
                     (f"run {self.run_id}\n" + "".join(f"{f.tag} {n}\n" for f, n in kept)).encode())
        self._journal = AppendFile(self._path(JOURNAL))
        self._files = files
        log.warning("recorder: restarted; kept %d template rows, %d trajectory rows and %d closure rows "
                    "written before", keep[TEMPLATES], keep[TRAJECTORY], keep[CLOSURES])

    def _write_backlog(self) -> None:
        """Append the waiting rows in order (journal entry first, then the row); stop at a failure,
        leaving every file with complete rows only, and try again ``RETRY_S`` later."""
        if self._files is None:
            return
        while self._backlog:
            f, frame, line = self._backlog[0]
            target = self._files[f]
            try:
                if self._journal is not None:
                    before = self._journal.size
                    self._journal.append(f"{f.tag} {frame}\n".encode())
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
            self._in_file[f] += 1
            if not self._keep:  # in its file now: the row need not be held
                self.rows[f].popleft()

    def _failed(self, path: Path, exc: OSError) -> None:
        self.counters["write_errors"] = self.counters.get("write_errors", 0) + 1
        self._retry_at = time.monotonic() + self.RETRY_S
        if str(path) not in self._logged:
            self._logged.add(str(path))
            log.error("recorder: %s (rows wait and are tried again; further errors are counted)",
                      describe_write_error(path, exc))

    def finish(self) -> None:
        """The end of the run: the waiting closures, every row, map.json, trajectory_map.tum and
        outputs.mcap."""
        self._settle_closures(final=True)
        if not self.run_dir:
            return
        if self._files is None and not (any(self.rows.values()) or (self.map_export or {}).get("nodes")):
            self._no_outputs()  # a run that failed before its first frame leaves no empty results
            return
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
            self._write_whole("map.json", json.dumps(self.map_export).encode())
            if self._local.n:
                self._write_whole(TRAJECTORY_ON_MAP, self.trajectory_on_map().encode())
        if self.mcap is not None:
            self._write_mcap()

    def _write_whole(self, name: str, data: bytes) -> None:
        try:
            write_atomic(self._path(name), data)
        except OSError as exc:  # the previous file, if any, is intact
            self._failed(self._path(name), exc)

    def _no_outputs(self) -> None:
        """Nothing was recorded: no output file is created, and those an earlier run left in this
        folder go (a restart of this run's worker keeps its files, which its journal names)."""
        journal = complete_lines(self._path(JOURNAL)) if self.run_id else []
        if journal and journal[0] == f"run {self.run_id}\n".encode():
            return
        for name in (*(f.name for f in ROW_FILES), JOURNAL, "map.json", TRAJECTORY_ON_MAP, MCAP):
            try:
                self._path(name).unlink(missing_ok=True)
            except OSError as exc:
                self._failed(self._path(name), exc)

    def trajectory_on_map(self) -> str:
        """trajectory_map.tum's text: the frames' poses on the final map (``trajectory.tum``'s
        format, in frame order)."""
        nodes = export_node_poses(self.map_export or {})
        rows = self.local_poses
        poses = poses_on_map(nodes, rows[:, 2].astype(np.int64), rows[:, 3:])
        return "".join(trajectory_line(PoseRow(int(f), float(t), *p, -1))
                       for f, t, p in zip(rows[:, 0].tolist(), rows[:, 1].tolist(), poses.tolist(), strict=True))

    def _write_mcap(self) -> None:
        """outputs.mcap: the run's outputs as the ROS 2 messages of the live output, rebuilt from
        the rows (so a restarted worker's file is whole), written at the end, atomically."""
        from .ros2_out import Ros2Messages, mcap_bytes, replay

        conv = Ros2Messages(**self.mcap)
        self._write_whole(MCAP, mcap_bytes(conv, replay(conv, *self.mcap_rows(), self.map_export)))

    def mcap_rows(self) -> tuple[list[TemplateRow], list[PoseRow]]:
        """The template and pose rows outputs.mcap is made of: those held, or with a run folder the
        numbers kept of every row (the rows themselves were dropped once written)."""
        if self._mcap_rows is None or self._keep:
            return self.templates, self.trajectory
        return ([TemplateRow(int(f), t, int(i), int(c), -1, -1)
                 for f, t, i, c in self._mcap_rows[TEMPLATES].latest_by_frame().tolist()],
                [PoseRow(int(f), t, x, y, th, int(e))
                 for f, t, x, y, th, e in self._mcap_rows[TRAJECTORY].latest_by_frame().tolist()])

    def close(self) -> None:
        for f in [*(self._files or {}).values(), self._journal]:
            if f is not None:
                f.close()
        self._files, self._journal = None, None
        self._discard_numbers()

    # ------------------------------------------------------------------ numbers kept per frame
    def _numbers(self) -> dict[str, NumberRows]:
        """The per-frame number stores, by the name of their scratch file."""
        out = {"local_poses": self._local}
        if self._mcap_rows is not None:
            out.update(mcap_templates=self._mcap_rows[TEMPLATES], mcap_poses=self._mcap_rows[TRAJECTORY])
        return out

    def _spill(self) -> None:
        """With the files open, the per-frame numbers go to scratch files of the run folder."""
        if self._files is None or self._keep:
            return
        for name, rows in self._numbers().items():
            rows.spill_to(self._path(f".{name}.f64"))

    def _discard_numbers(self) -> None:
        for rows in self._numbers().values():
            rows.discard()

    def _await_place(self, frame: int) -> None:
        """A first frame whose true place may come later (the newest GT_KEEP wait: without ground
        truth none comes)."""
        self._awaiting_place.add(frame)
        if len(self._awaiting_place) > 2 * GT_KEEP:
            self._awaiting_place = set(sorted(self._awaiting_place)[-GT_KEEP:])

    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = {"template_rows": self.n_rows[TEMPLATES], "trajectory_rows": self.n_rows[TRAJECTORY],
                               "closure_rows": self.n_rows[CLOSURES]}
        if self._backlog:
            out["rows_not_written"] = len(self._backlog)
        return out

    def state_dict(self) -> dict[str, Any]:
        def where(d: dict[int, tuple[float, float]]) -> np.ndarray:
            return np.array([(k, *v) for k, v in sorted(d.items())], dtype=np.float64).reshape(-1, 3)

        return {"templates": [list(r) for r in self.templates], "trajectory": [list(r) for r in self.trajectory],
                "closures": [list(r) for r in self.closures],
                "closures_waiting": [[*r[:4], None if r.true_xy is None else list(r.true_xy), *r[5:]]
                                     for r in self.closures_waiting],
                "template_first": self.template_first.items().astype(np.int64),
                "interval_first": self.interval_first.items().astype(np.int64),
                "places": self.places.items(), "gt": where(self.gt), "gt_last_frame": self.gt_last_frame,
                "local_poses": self.local_poses.copy(),
                **({"mcap_rows": [self._mcap_rows[f].latest_by_frame() for f in (TEMPLATES, TRAJECTORY)]}
                   if self._mcap_rows is not None and not self._keep else {}),
                "last_template_frame": self.last_template_frame, "n_rows": {f.tag: self.n_rows[f] for f in ROW_FILES},
                **({"run_dir": str(Path(self.run_dir).resolve()),
                    "rows_in_files": {f.tag: self._in_file[f] for f in ROW_FILES}} if self.run_dir else {})}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.rows[TEMPLATES] = deque(TemplateRow(int(r[0]), float(r[1]), int(r[2]), int(r[3]), int(r[4]), r[5])
                                     for r in st["templates"])
        self.rows[TRAJECTORY] = deque(PoseRow(int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]), int(r[5]))
                                      for r in st["trajectory"])
        self.rows[CLOSURES] = deque(ClosureRow(int(r[0]), float(r[1]), int(r[2]), int(r[3]),
                                          None if r[4] is None else float(r[4]), r[5], r[6], r[7]) for r in st["closures"])
        self.closures_waiting = [WaitingClosure(int(r[0]), float(r[1]), int(r[2]), int(r[3]),
                                                None if r[4] is None else (float(r[4][0]), float(r[4][1])), r[5], r[6],
                                                r[7])
                                 for r in st["closures_waiting"]]
        self.template_first = KeyedNumbers(1, st["template_first"])
        self.interval_first = KeyedNumbers(1, st["interval_first"])
        self.places = KeyedNumbers(2, st["places"])
        self.gt = {int(r[0]): (float(r[1]), float(r[2])) for r in np.asarray(st["gt"], dtype=np.float64).reshape(-1, 3)}
        self._discard_numbers()
        self._local = NumberRows(6, st["local_poses"])
        if self._mcap_rows is not None and "mcap_rows" in st:
            self._mcap_rows = {f: NumberRows(w, a) for f, w, a in zip((TEMPLATES, TRAJECTORY), (4, 6), st["mcap_rows"],
                                                                         strict=True)}
        self._spill()
        self.n_rows = {f: int(st["n_rows"][f.tag]) for f in ROW_FILES}
        self._carry = (st["run_dir"], {k: int(v) for k, v in st["rows_in_files"].items()}) \
            if "rows_in_files" in st else None
        self.gt_last_frame = int(st["gt_last_frame"])
        self.last_template_frame = int(st["last_template_frame"])
        # first frames after the last ground truth may still get their place
        firsts = np.concatenate([self.template_first.items()[:, 1], self.interval_first.items()[:, 1]])
        self._awaiting_place = set()
        for f in np.unique(firsts[firsts > self.gt_last_frame]).astype(np.int64).tolist():
            if f not in self.places:
                self._await_place(f)

    def new_session(self) -> None:
        """A new session on an old map: this session's outputs only; an old session's templates may
        be matched again, but a new session's frame numbers start afresh, so its first frames are
        no places of this one."""
        for f in ROW_FILES:
            self.rows[f] = deque()
        self.n_rows = dict.fromkeys(ROW_FILES, 0)
        self.map_export, self.closures_waiting = None, []
        self._discard_numbers()
        self._local = NumberRows(6)
        if self._mcap_rows is not None:
            self._mcap_rows = {TEMPLATES: NumberRows(4), TRAJECTORY: NumberRows(6)}
        self._spill()
        self.template_first, self.interval_first, self.places = KeyedNumbers(1), KeyedNumbers(1), KeyedNumbers(2)
        self.gt, self._awaiting_place = {}, set()
        self.gt_last_frame = self.last_template_frame = -1
        self._carry = None  # an old session's rows are not this session's


def _first(store: KeyedNumbers, key: int) -> int:
    """The first frame a template / interval store holds for ``key``; -1 where none."""
    v = store.get(key)
    return -1 if v is None else int(v[0])
