"""Saving and loading node state files and exported maps, atomically and without pickle.

A state is a nested dict of plain values and numpy arrays (what ``Node.state_dict()`` returns). It
is written as msgpack with the same array ext type as the wire codec, to a temporary file that is
then renamed over the target, so a crash mid-write never leaves a torn checkpoint. Every file
written here begins with its ``format`` and ``version``: a state file is
``{"format": "neoslam-state", "version": STATE_VERSION, "state": {...}}``, a map file
``{"format": "neoslam-map", "version": MAP_VERSION, ..., "stages": {stage: state}}``. A file of
another version, or without one (written before files had one), is refused with one line
(:class:`StateFormatError`); nothing reads the formats of earlier versions.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgpack

from .files import write_atomic
from .messages import _default, _ext_hook

MAX_STATE_BYTES = 8 * 2**30

#: a state file's format and the one version of it this build reads
STATE_FORMAT = "neoslam-state"
STATE_VERSION = 1


class StateFormatError(ValueError):
    """A saved file of another format version than this build reads (or of none): the text is one
    line naming the file, the version it has and the one this build reads."""

    def __init__(self, path: str | Path, found: Any, supported: int) -> None:
        has = "no format version" if found is None else f"format version {found!r}"
        super().__init__(f"{path} has {has}; this build reads version {supported} "
                         f"(it was written by another version of neoslam)")
        self.path, self.found, self.supported = path, found, supported


def _write_msgpack(path: str | Path, data: dict[str, Any]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, msgpack.packb(data, default=_default, use_bin_type=True))


def _read_msgpack(path: str | Path) -> dict[str, Any]:
    """The map held by the file ``path`` (a state or map file), its arrays read-only."""
    path = Path(path)
    if path.stat().st_size > MAX_STATE_BYTES:
        raise ValueError(f"state file {path} is larger than {MAX_STATE_BYTES} bytes")
    data = msgpack.unpackb(path.read_bytes(), ext_hook=_ext_hook, raw=False, strict_map_key=False)
    if not isinstance(data, dict):
        raise ValueError(f"state file {path} does not hold a map")
    return data


def save_state_file(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` to ``path`` atomically (see files.write_atomic), after its format and
    version: on a failure such as a full disk the OSError is raised and the previous file, if any,
    is left as it was."""
    _write_msgpack(path, {"format": STATE_FORMAT, "version": STATE_VERSION, "state": state})


def state_file_version(path: str | Path) -> Any:
    """The format version of the state file ``path``, read from its first bytes only (a state
    file may be large); None when it has none (not a state file of any version)."""
    with open(path, "rb") as fh:
        unpacker = msgpack.Unpacker(fh, raw=False, strict_map_key=False)
        try:
            header: dict[Any, Any] = {}
            for _ in range(min(2, unpacker.read_map_header())):
                key = unpacker.unpack()
                if key not in ("format", "version"):
                    break
                header[key] = unpacker.unpack()
        except (ValueError, msgpack.UnpackException):
            return None
    return header.get("version") if header.get("format") == STATE_FORMAT else None


def check_state_file(path: str | Path) -> None:
    """Refuse (:class:`StateFormatError`) a state file of another version than this build's."""
    found = state_file_version(path)
    if found != STATE_VERSION:
        raise StateFormatError(path, found, STATE_VERSION)


def load_state_file(path: str | Path) -> dict[str, Any]:
    """The state saved in ``path`` (writable arrays); a file of another format version, or of
    none, is refused with :class:`StateFormatError`."""
    data = _read_msgpack(path)
    found = data.get("version") if data.get("format") == STATE_FORMAT else None
    if found != STATE_VERSION:
        raise StateFormatError(path, found, STATE_VERSION)
    state = data.get("state")
    if not isinstance(state, dict):
        raise ValueError(f"state file {path} holds no state")
    return _writable(state)


def _writable(obj: Any) -> Any:
    """Arrays decoded from a buffer are read-only views; algorithms mutate their state."""
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.copy()
    if isinstance(obj, dict):
        return {k: _writable(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_writable(v) for v in obj]
    return obj


def cut_dir(checkpoint_dir: str | Path, cut: int) -> Path:
    return Path(checkpoint_dir) / f"{cut:09d}"


def save_stage_state(checkpoint_dir: str | Path, cut: int, stage: str, state: dict[str, Any]) -> None:
    """State of ``stage`` after every frame below ``cut``, in the cut's own folder."""
    save_state_file(cut_dir(checkpoint_dir, cut) / f"{stage}.state", state)


def latest_complete_cut(checkpoint_dir: str | Path, stages: list[str]) -> int | None:
    """The newest cut for which every stage wrote its state, or None."""
    root = Path(checkpoint_dir)
    if not root.is_dir():
        return None
    cuts = sorted((int(p.name) for p in root.iterdir() if p.is_dir() and p.name.isdigit()), reverse=True)
    for cut in cuts:
        if all((cut_dir(root, cut) / f"{s}.state").exists() for s in stages):
            return cut
    return None


def latest_stage_state(checkpoint_dir: str | Path, stage: str) -> Path | None:
    """The newest state file of one stage (used to restart a crashed worker), or None."""
    root = Path(checkpoint_dir)
    if not root.is_dir():
        return None
    for d in sorted((p for p in root.iterdir() if p.is_dir() and p.name.isdigit()), reverse=True):
        f = d / f"{stage}.state"
        if f.exists():
            return f
    return None


# ------------------------------------------------------------------------------ map files
MAP_FORMAT = "neoslam-map"
MAP_VERSION = 1


def run_states(run_dir: str | Path) -> tuple[dict[str, dict[str, Any]], str]:
    """Every stage's newest state in a run folder: the end-of-run states (``state/``), else the
    newest complete checkpoint cut. Returns (stage -> state, where it came from)."""
    run_dir = Path(run_dir)
    final = run_dir / "state"
    if final.is_dir() and any(final.glob("*.state")):
        return {p.stem: load_state_file(p) for p in sorted(final.glob("*.state"))}, str(final)
    root = run_dir / "checkpoint"
    if root.is_dir():
        for d in sorted((p for p in root.iterdir() if p.is_dir() and p.name.isdigit()), reverse=True):
            files = sorted(d.glob("*.state"))
            if files:
                return {p.stem: load_state_file(p) for p in files}, str(d)
    raise FileNotFoundError(f"{run_dir} holds no saved state (neither state/ nor checkpoint/)")


def _check_final_states(run_dir: Path, states: dict[str, Any], origin: str) -> None:
    """A run's end-of-run states are whole unless a worker the supervisor stopped by force (its
    report's ``stopped_by_force``) had not written them yet (no ``state/<worker>.saved``): packed
    as they are, the map would lack that worker's stages, and a later session would start them
    afresh beside the others' learned state. Raises ValueError naming them."""
    if Path(origin) != run_dir / "state":
        return
    try:
        report = json.loads((run_dir / "report.json").read_text())
    except (OSError, ValueError):
        return
    workers = report.get("workers") or {}
    missing = {w: [s for s in workers.get(w, []) if s not in states]
               for w in report.get("stopped_by_force") or [] if not (run_dir / "state" / f"{w}.saved").exists()}
    if missing:
        said = "; ".join(f"worker {w} (stages {', '.join(s) or 'none saved'})" for w, s in missing.items())
        raise ValueError(f"{run_dir}: the supervisor stopped {said} by force at the end of the run, before it "
                         f"saved its final state (report.json stopped_by_force), so state/ lacks it and the map "
                         f"would be incomplete; export from a run that ended in time")


def export_map(run_dir: str | Path, out: str | Path) -> dict[str, Any]:
    """Pack a run's learned state (templates, TM connections, intervals, pose cells, experience
    map) into one portable file (msgpack, no pickle) for ``neoslam run --map``."""
    states, origin = run_states(run_dir)
    _check_final_states(Path(run_dir), states, origin)
    cfg_path = Path(run_dir) / "config.yaml"
    meta = {"format": MAP_FORMAT, "version": MAP_VERSION, "from_run": str(Path(run_dir).resolve()),
            "from_states": origin, "config_yaml": cfg_path.read_text() if cfg_path.exists() else ""}
    report = Path(run_dir) / "report.json"
    if report.exists():
        try:
            rep = json.loads(report.read_text())
            meta["pipeline"] = rep.get("pipeline")
            meta["frames"] = rep.get("frames_out")
        except (OSError, ValueError):
            pass
    _write_msgpack(out, {**meta, "stages": states})
    return {**meta, "stages": sorted(states)}


def load_map_file(path: str | Path) -> dict[str, Any]:
    """A map file written by :func:`export_map`, checked for its format and version."""
    data = _read_msgpack(path)
    if data.get("format") != MAP_FORMAT:
        raise ValueError(f"{path} is not a neoslam map file (format {data.get('format')!r})")
    if data.get("version") != MAP_VERSION:
        raise ValueError(f"{path}: map version {data.get('version')!r}, this build reads {MAP_VERSION}")
    if not isinstance(data.get("stages"), dict):
        raise ValueError(f"{path}: no stage states in the map file")
    return _writable(data)
