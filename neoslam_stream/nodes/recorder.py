"""The recorder node: writes a run's outputs from the topics, so no algorithm node writes files.

It subscribes to ``visual_template`` (templates.csv: frame -> template id, loop closures),
``experience_map/pose`` (trajectory.tum: the experience-map pose per frame) and
``experience_map/map`` (map.json: nodes and links, published once at the end of the run), and with
``mcap`` the same outputs as ROS 2 messages in ``outputs.mcap`` (docs/ros2.md). It is an
observer: hosted in the experience map's worker, it does not keep those topics off the bus. Its
rows are its state, so checkpoints, ``--resume`` and crash restarts give the same files as an
uninterrupted run.

Writing, so that a crash or a full disk loses as little as possible and never tears a file:

* ``templates.csv`` and ``trajectory.tum`` grow row by row: each row is appended (and handed to the
  operating system) when it arrives, so a killed process loses none of the rows it got. The bytes
  are those the whole file would have been written with at the end.
* A journal next to them (``.recorder.journal``: the run id, then the kind and frame number of
  every row appended, written just before the row) lets a worker restarted after a crash tell its
  own rows from another run's files: it keeps the rows written before the crash (cutting a row
  torn by the crash), adds those of its restored state that had not reached the files, and skips
  rows of frames already written (an upstream stage replaying them), so no row is lost or doubled.
  A new run, or the in-process API, starts the files afresh.
* ``map.json`` is written at the end to a temporary file, fsynced and renamed over the old one.
* An ``OSError`` (disk full) is logged once per file with the path (``disk full writing
  RUN/map.json: ...``), counted (``counters["write_errors"]``); the rows not written wait and are
  tried again at most every ``RETRY_S`` seconds and at the end. What was written stays intact.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.files import AppendFile, complete_lines, describe_write_error, write_atomic
from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, VISUAL_TEMPLATE

log = logging.getLogger("neoslam.recorder")

TEMPLATES_HEADER = "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
#: the recorder's journal of the rows it appended (see the module docstring)
JOURNAL = ".recorder.journal"
TEMPLATES, TRAJECTORY = "templates.csv", "trajectory.tum"
#: the outputs as ROS 2 messages (docs/ros2.md)
MCAP = "outputs.mcap"


def template_line(r: tuple) -> str:
    """One row of templates.csv: frame, stamp, template id, loop closure 0/1, best interval, best
    score as the front end gave it (D's overlap count, the local view's match error)."""
    return f"{r[0]},{r[1]:.6f},{r[2]},{r[3]},{r[4]},{r[5]}\n"


def trajectory_line(r: tuple) -> str:
    """One row of trajectory.tum for a recorder row (frame, stamp, x, y, theta, exp id): exactly
    ``tum.write_tum``'s format (``t x y z qx qy qz qw``)."""
    t, x, y, yaw = r[1], r[2], r[3], r[4]
    return f"{t:.6f} {x:.6f} {y:.6f} 0 0 0 {np.sin(yaw / 2):.9f} {np.cos(yaw / 2):.9f}\n"


def write_templates_csv(path: str | Path, rows: list) -> None:
    """templates.csv with ``rows`` (written whole and atomically)."""
    write_atomic(path, (TEMPLATES_HEADER + "".join(template_line(r) for r in rows)).encode())


class RecorderNode(Node):
    """Writes templates.csv and trajectory.tum into ``run_dir`` row by row, map.json at the end."""

    inputs = (VISUAL_TEMPLATE, EXPERIENCE_POSE, EXPERIENCE_MAP)
    outputs = ()
    unordered_inputs = (EXPERIENCE_MAP,)
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
        #: the open output files by kind ("t": templates.csv, "p": trajectory.tum), the journal
        self._files: dict[str, AppendFile] | None = None
        self._journal: AppendFile | None = None
        #: rows to append, in order: (kind, frame, line)
        self._backlog: deque[tuple[str, int, bytes]] = deque()
        #: after a restart, the frames each file held already (rows for them are not written again)
        self._written: dict[str, set[int]] = {"t": set(), "p": set()}
        self._retry_at = 0.0
        self._logged: set[str] = set()

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if topic == VISUAL_TEMPLATE:
            row = (msg.frame, msg.stamp, int(d["id"]), int(bool(d.get("is_loop_closure", False))),
                   int(d.get("best_interval", -1)), d.get("best_score", -1))
            self._add("t", row, self.templates, template_line)
        elif topic == EXPERIENCE_POSE:
            x, y, th = (float(v) for v in d["pose"])
            self._add("p", (msg.frame, msg.stamp, x, y, th, int(d.get("exp_id", -1))), self.trajectory,
                      trajectory_line)
        else:
            self.map_export = d.get("export")
        return []

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
        return {"t": out / TEMPLATES, "p": out / TRAJECTORY, "j": out / JOURNAL}

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
        for kind, rows, line in (("t", self.templates, template_line), ("p", self.trajectory, trajectory_line)):
            for r in rows:
                if r[0] not in self._written[kind]:
                    self._backlog.append((kind, r[0], line(r).encode()))
        self._write_backlog()

    def _create(self, paths: dict[str, Path]) -> None:
        if self.run_id:
            self._journal = AppendFile(paths["j"], truncate=True)
            self._journal.append(f"run {self.run_id}\n".encode())
        files = {"t": AppendFile(paths["t"], truncate=True), "p": AppendFile(paths["p"], truncate=True)}
        files["t"].append(TEMPLATES_HEADER.encode())
        self._files = files

    def _reopen(self, paths: dict[str, Path], journal: list[bytes]) -> None:
        """A restart of this run's worker: keep the complete rows the journal knows, cut the rest."""
        entries: list[tuple[str, int]] = []
        for raw in journal[1:]:
            parts = raw.split()
            if len(parts) == 2 and parts[0] in (b"t", b"p") and parts[1].isdigit():
                entries.append((parts[0].decode(), int(parts[1])))
        lines = {"t": complete_lines(paths["t"]), "p": complete_lines(paths["p"])}
        header = TEMPLATES_HEADER.encode()
        has_header = bool(lines["t"]) and lines["t"][0] == header
        rows = {"t": lines["t"][1:] if has_header else [], "p": lines["p"]}
        keep = {k: min(len(rows[k]), sum(1 for e, _ in entries if e == k)) for k in ("t", "p")}
        files = {k: AppendFile(paths[k]) for k in ("t", "p")}
        files["t"].cut(len(header) + sum(map(len, rows["t"][:keep["t"]])) if has_header else 0)
        if not has_header:
            files["t"].append(header)
        files["p"].cut(sum(map(len, rows["p"][:keep["p"]])))
        kept, seen = [], {"t": 0, "p": 0}
        for kind, frame in entries:
            if seen[kind] < keep[kind]:
                seen[kind] += 1
                kept.append((kind, frame))
                self._written[kind].add(frame)
        write_atomic(paths["j"], (f"run {self.run_id}\n" + "".join(f"{k} {f}\n" for k, f in kept)).encode())
        self._journal = AppendFile(paths["j"])
        self._files = files
        log.warning("recorder: restarted; kept %d template rows and %d trajectory rows written before",
                    keep["t"], keep["p"])

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
        if not self.run_dir:
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
        if self.mcap is not None:
            self._write_mcap()
        return []

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
        out: dict[str, Any] = {"template_rows": len(self.templates), "trajectory_rows": len(self.trajectory)}
        if self._backlog:
            out["rows_not_written"] = len(self._backlog)
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"templates": [list(r) for r in self.templates], "trajectory": [list(r) for r in self.trajectory]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.templates = [(int(r[0]), float(r[1]), int(r[2]), int(r[3]), int(r[4]), r[5]) for r in st["templates"]]
        self.trajectory = [(int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]), int(r[5]))
                           for r in st["trajectory"]]

    def new_session(self) -> None:
        self.templates, self.trajectory, self.map_export = [], [], None  # this session's outputs only


def make_node(mcap: dict[str, Any] | None = None) -> RecorderNode:
    return RecorderNode(mcap)
