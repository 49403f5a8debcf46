"""Saving and loading adapter state files, atomically and without pickle.

A state is a nested dict of plain values and numpy arrays (what ``StageAdapter.state_dict()``
returns). It is written as msgpack with the same array ext type as the wire codec, to a temporary
file that is then renamed over the target, so a crash mid-write never leaves a torn checkpoint.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import msgpack

from .messages import _default, _ext_hook

MAX_STATE_BYTES = 8 * 2**30


def save_state_file(path: str | Path, state: dict[str, Any]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(msgpack.packb(state, default=_default, use_bin_type=True))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_state_file(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if path.stat().st_size > MAX_STATE_BYTES:
        raise ValueError(f"state file {path} is larger than {MAX_STATE_BYTES} bytes")
    data = path.read_bytes()
    state = msgpack.unpackb(data, ext_hook=_ext_hook, raw=False, strict_map_key=False)
    if not isinstance(state, dict):
        raise ValueError(f"state file {path} does not hold a map")
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
