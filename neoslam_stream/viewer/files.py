"""A finished run's files, logged to a :class:`RunView`: templates.csv, the TUM files, map.json and
the per-stage rates of timeline.csv."""

from __future__ import annotations

import csv
import json
import logging
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .recording import RunView

log = logging.getLogger("neoslam.viewer")


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _read_tum(path: Path) -> np.ndarray:
    """(stamp, x, y, yaw) rows of a TUM file; an empty (0, 4) array when it is missing or
    unreadable (then logged with its cause: a damaged file must not stop the rest being shown)."""
    if not path.exists():
        return np.zeros((0, 4))
    from ..tum import read_tum

    try:
        return read_tum(path)
    except (OSError, ValueError) as exc:
        log.warning("%s not shown: %s", path, exc)
        return np.zeros((0, 4))


def log_run_folder(run_dir: str | Path, view: RunView) -> None:
    """Log what a run folder holds: templates.csv, trajectory.tum, groundtruth.tum, odometry.tum,
    map.json, the per-stage rates of timeline.csv, the thinned camera frames of camera.zip and the
    log lines of log.jsonl. Each pose is put on the ``frame`` timeline through the stamp -> frame
    map of templates.csv (the stamps the recorder wrote with the frame numbers), and on ``stamp``
    in any case."""
    run_dir = Path(run_dir)
    templates = _read_csv(run_dir / "templates.csv")
    frame_of = FrameOfStamp(templates)
    for stamp, x, y, th in _read_tum(run_dir / "trajectory.tum"):
        view.pose(frame_of(stamp, -1), stamp, np.array([x, y, th]))
    for row in templates:
        view.template(int(row["frame"]), float(row["stamp"]), int(row["template_id"]),
                      row.get("is_loop_closure", "0") not in ("0", "", "false", "False"))
    for stamp, x, y, th in _read_tum(run_dir / "groundtruth.tum"):
        view.groundtruth(frame_of(stamp), stamp, np.array([x, y, th]))
    for stamp, x, y, th in _read_tum(run_dir / "odometry.tum"):
        view.odometry_pose(frame_of(stamp), stamp, np.array([x, y, th]))
    log_timeline(run_dir / "timeline.csv", view)
    log_camera_and_log_lines(run_dir, view)
    map_path = run_dir / "map.json"
    if map_path.exists():
        try:
            view.experience_map(json.loads(map_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("map.json not shown: %s", exc)


class FrameOfStamp:
    """The frame number of a stamp, through templates.csv's (frame, stamp) rows: the recorder
    writes the same stamp to templates.csv and the TUM files (to the microsecond, as TUM's
    six decimals hold it), so a pose finds its frame by its stamp."""

    def __init__(self, templates: list[dict[str, str]]) -> None:
        self._frame = {round(float(r["stamp"]), 6): int(r["frame"]) for r in templates}

    def __call__(self, stamp: float, missing: int | None = None) -> int | None:
        return self._frame.get(round(float(stamp), 6), missing)


def read_camera(run_dir: Path) -> list[tuple[int, float, bytes]]:
    """camera.zip's (frame, stamp, JPEG) frames; none when it is missing, those before the damage
    when it is damaged (logged once: the rest of the run is shown)."""
    from ..runtime.camera_log import CAMERA_FILE, read_camera_zip

    out: list[tuple[int, float, bytes]] = []
    if (run_dir / CAMERA_FILE).exists():
        try:
            for frame, stamp, jpeg in read_camera_zip(run_dir / CAMERA_FILE):
                out.append((frame, stamp, jpeg))
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("%s not shown: %s", run_dir / CAMERA_FILE, exc)
    return out


def read_log_lines(path: Path) -> list[dict[str, Any]]:
    """log.jsonl's records with a ``t_s`` (lines that are no JSON object are skipped)."""
    out = []
    if path.exists():
        for line in path.read_text(errors="replace").splitlines():
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict) and row.get("t_s") is not None:
                out.append(row)
    return out


def log_camera_and_log_lines(run_dir: Path, view: RunView) -> None:
    """camera.zip's frames and log.jsonl's lines (either may be missing or damaged: skipped)."""
    for frame, stamp, jpeg in read_camera(run_dir):
        view.jpeg(frame, stamp, jpeg)
    for r in read_log_lines(run_dir / "log.jsonl"):
        try:
            view.log_line(float(r["t"]), str(r["level"]), str(r["process"]), str(r["name"]), str(r["message"]))
        except (ValueError, KeyError, TypeError):
            continue


def timeline_rates(path: Path) -> list[tuple[float, str, float, dict[str, str]]]:
    """(t_s, stage, rate_hz, row) from timeline.csv: each stage's processed count difference over
    the time between two of its rows, with the later row (its other figures)."""
    last: dict[str, tuple[float, int]] = {}
    out = []
    for row in _read_csv(path):
        try:
            t, stage, done = float(row["t_s"]), row["stage"], int(row["processed"])
        except (KeyError, ValueError):
            continue
        if stage in last and t > last[stage][0]:
            t0, n0 = last[stage]
            out.append((t, stage, (done - n0) / (t - t0), row))
        last[stage] = (t, done)
    return out


def log_timeline(path: Path, view: RunView) -> None:
    for t, stage, rate, _row in timeline_rates(path):
        view.stage_rate(t, stage, rate)
