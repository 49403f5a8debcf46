"""Stage D's state (SpatialViewCells.state_dict / load_state_dict): what a checkpoint, ``--resume``
and ``neoslam map export`` keep of it. With merge_revisits only the intervals D keeps are saved (the
places and the recent ones), so a saved map grows with the places, not with the laps."""

from __future__ import annotations

from typing import Any

import numpy as np
from pyroaring import BitMap

from .revisit_merge import RevisitMerge, Stored
from .spatial_view import STATE_PARAMS


def state_of(d: Any) -> dict[str, Any]:
    """The intervals D keeps (``stored``: their numbers, of ``n_intervals`` made), their unions
    and templates, the sequence filter's history, and the parameters they were made with
    (``params``, in STATE_PARAMS order)."""
    keys = d._kept()
    return {"params": [getattr(d.config, name) for name in STATE_PARAMS],
            "n_intervals": d.n_intervals, "stored": np.asarray(keys, np.int64),
            "unions": [np.asarray(d.unions[k].to_array(), dtype=np.uint32) for k in keys],
            "start": np.asarray([d.interval_start[k] for k in keys], np.int64),
            "end": np.asarray([d.interval_end[k] for k in keys], np.int64),
            "template": np.asarray([d.interval_template[k] for k in keys], np.int64),
            "stamps": np.asarray([d.interval_stamps[k] for k in keys], np.float64),
            "n_templates": d.n_templates, "template_start": np.asarray(d.template_start, np.int64),
            "current_template": d.current_template, "t": d.t,
            "sequence": d.sequence.state_dict(), "calibration": d.calibration.state_dict(),
            "indexed": d.indexed.copy(), "all_closed": d._all_closed,
            "descriptors": d.descriptors.state_dict(),
            "merge": d.merge.state_dict() if d.merge is not None else None,
            "rows": [[k, r] for k, r in d._rows.items()]}


def load_into(d: Any, state: dict[str, Any]) -> None:
    """Restore a :meth:`state_dict`; a state made with other parameters (``params``) is
    refused, since its intervals would not be this config's, and so is one that forgot
    intervals (merge_revisits) when this config keeps every interval."""
    saved = state["params"]
    if len(saved) != len(STATE_PARAMS):
        raise ValueError(f"the state's params hold {len(saved)} values, expected {len(STATE_PARAMS)}: "
                         f"{', '.join(STATE_PARAMS)}")
    for name, value in zip(STATE_PARAMS, saved, strict=True):
        ours = getattr(d.config, name)
        if value != ours:
            raise ValueError(f"spatial_view.{name}: the state was made with {value}, the config has "
                             f"{ours}; resume with the checkpoint's value or start afresh")
    n = int(state.get("n_intervals", len(state["unions"])))
    keys = [int(k) for k in state.get("stored", range(n))]
    if d.merge is None and keys != list(range(n)):
        raise ValueError("spatial_view.merge_revisits: the state was made with it (it kept "
                         f"{len(keys)} of {n} intervals); resume with merge_revisits: true or start afresh")
    columns = {"unions": [BitMap(np.asarray(a, dtype=np.int32)) for a in state["unions"]],
               "interval_start": [int(x) for x in state["start"]], "interval_end": [int(x) for x in state["end"]],
               "interval_template": [int(x) for x in state["template"]],
               "interval_stamps": [float(x) for x in state["stamps"]]}
    for name, values in columns.items():
        setattr(d, name, Stored(dict(zip(keys, values, strict=True)), n) if d.merge is not None else values)
    d.index.clear()
    indexed = state["indexed"]
    d._indexed = np.zeros(max(1024, len(indexed)), dtype=np.int64)
    d._place_stamps = np.zeros(max(1024, len(indexed)), dtype=np.float64)
    d._n_indexed = 0
    d._rows = {int(k): (None if r is None else np.asarray(r, np.int8)) for k, r in state.get("rows", [])}
    for k in indexed:
        d._index_interval(int(k))
    d.index.compact()
    d._all_closed = bool(state["all_closed"])
    d.n_templates = int(state["n_templates"])
    if "template_start" in state:
        d.template_start = [int(x) for x in state["template_start"]]
    else:  # a template is made when its first interval opens
        d.template_start = [-1] * d.n_templates
        for start, template in zip(columns["interval_start"], columns["interval_template"], strict=True):
            if template >= 0 and d.template_start[template] < 0:
                d.template_start[template] = start
    d.current_template = int(state["current_template"])
    d.t = int(state["t"])
    d.sequence.load_state_dict(state["sequence"])
    d.calibration.load_state_dict(state["calibration"])
    d.descriptors.load_state_dict(state["descriptors"])
    if d.merge is not None:
        d.merge = RevisitMerge()
        if state.get("merge"):
            d.merge.load_state_dict(state["merge"])
