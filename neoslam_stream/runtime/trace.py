"""A timeline of every frame (``neoslam run --trace FILE``) in Chrome's Trace Event Format, which
ui.perfetto.dev and chrome://tracing open.

Every message carries its frame's trace, one (stage, received, started, finished) entry per stage
it passed (messages.py), so the final topic's messages hold the whole path of each frame that
reached the end. The monitor hands each of them to a :class:`TraceWriter`, which appends to the file
as they come (memory stays bounded: a pending span per stage):

* one process (``pid``) per worker process of the run and one for the source, one thread (``tid``)
  per stage in its process, named by metadata events;
* a complete event (``"ph": "X"``) per stage and batch: ``ts`` its start of service, ``dur`` its
  service time (µs, since the run's start), ``args.frames`` the frames it served together (a
  micro-batch: its time divided among them is each frame's tau_i, as the monitor counts it);
* an async span (``"b"`` / ``"e"``, category ``queue``, id the frame) from the moment the stage took
  the frame to the start of its service (the queueing time), with ``transit_ms``: the time from
  the previous stage's end of service, when it published, to that moment;
* flow events (``"s"``, ``"t"``, ``"f"``, id the frame) linking one frame's stages, drawn as arrows;
* the source's process name carries ``args.origin_s``, the run's start (s since the epoch) that
  every ``ts`` counts from (viewers ignore it), so that :func:`trace_origin` puts the times back on
  the clock of the frames' stamps (a camera's capture times).

The file is a JSON array written event by event; its closing bracket comes at the end of the run,
and the viewers read a file cut short (a killed run) as well. :func:`read_trace` reads it back and
:func:`stage_figures` turns it into the monitor's per-stage figures (frames served, mean tau_i).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: the source's pseudo-stage in a frame's trace (its entry: the moment it published the frame)
SOURCE = "source"


class TraceWriter:
    """Appends the trace events of each frame that reached the end to ``path``. ``workers``: each
    worker process with the stages it hosts (a stage seen that no worker names gets a process of its
    own); ``origin``: the run's start (s, epoch), the zero of ``ts``. A file that already holds events
    (a restarted monitor) is continued, its last incomplete line dropped."""

    def __init__(self, path: str | Path, workers: dict[str, list[str]], origin: float) -> None:
        self.path = Path(path)
        self.origin = origin
        self.where: dict[str, tuple[int, int]] = {SOURCE: (1, 1)}
        self.process_names: dict[int, str] = {1: SOURCE}
        for pid, (worker, stages) in enumerate(workers.items(), start=2):
            self.process_names[pid] = worker
            for tid, stage in enumerate(stages, start=1):
                self.where[stage] = (pid, tid)
        #: per stage: the span being gathered (a batch's frames come one message each)
        self.pending: dict[str, dict[str, Any]] = {}
        self.named: set[tuple[int, int]] = set()
        self.frames = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        kept = self._complete_lines()
        self._fh = open(self.path, "w" if not kept else "a", encoding="utf-8")  # noqa: SIM115 (closed in close())
        if not kept:
            self._fh.write("[\n")

    def _complete_lines(self) -> bool:
        """Cut the file after its last complete line; True when events remain to continue."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            return False
        data = self.path.read_bytes()
        if data.rstrip().endswith(b"]"):  # closed by an earlier run: start afresh
            return False
        cut = data.rfind(b"\n") + 1
        with open(self.path, "r+b") as fh:
            fh.truncate(cut)
        return cut > 0

    def _us(self, t: float) -> float:
        return round((t - self.origin) * 1e6, 3)

    def _emit(self, event: dict[str, Any]) -> None:
        self._fh.write(json.dumps(event, separators=(",", ":")) + ",\n")

    def _place(self, stage: str) -> tuple[int, int]:
        """(pid, tid) of ``stage``, named by metadata events the first time."""
        if stage not in self.where:  # hosted elsewhere (a run split over hosts): a process of its own
            pid = max(self.process_names) + 1
            self.process_names[pid] = stage
            self.where[stage] = (pid, 1)
        pid, tid = self.where[stage]
        if (pid, 0) not in self.named:
            self.named.add((pid, 0))
            self._emit({"ph": "M", "name": "process_name", "pid": pid, "args": self._process_args(pid)})
            self._emit({"ph": "M", "name": "process_sort_index", "pid": pid, "args": {"sort_index": pid}})
        if (pid, tid) not in self.named:
            self.named.add((pid, tid))
            self._emit({"ph": "M", "name": "thread_name", "pid": pid, "tid": tid, "args": {"name": stage}})
        return pid, tid

    def _process_args(self, pid: int) -> dict[str, Any]:
        """The process name event's args: the source's carries the trace's origin too."""
        args: dict[str, Any] = {"name": self.process_names[pid]}
        if pid == 1:
            args["origin_s"] = self.origin
        return args

    def add(self, frame: int, trace: list[Any]) -> None:
        """One frame's trace: its spans, waits and flow."""
        self.frames += 1
        prev_finished = None
        for k, (stage, received, started, finished) in enumerate(trace):
            pid, tid = self._place(stage)
            key = (started, finished)
            span = self.pending.get(stage)
            if span is not None and span["key"] != key:
                self._flush(stage)
                span = None
            if span is None:
                self.pending[stage] = {"key": key, "pid": pid, "tid": tid, "frames": [frame]}
            else:
                span["frames"].append(frame)
            if started > received:
                wait = {"cat": "queue", "name": f"waits for {stage}", "id": frame, "pid": pid, "tid": tid}
                args = {"frame": frame}
                if prev_finished is not None:
                    args["transit_ms"] = round((received - prev_finished) * 1e3, 4)
                self._emit({**wait, "ph": "b", "ts": self._us(received), "args": args})
                self._emit({**wait, "ph": "e", "ts": self._us(started)})
            phase = "s" if k == 0 else ("f" if k == len(trace) - 1 else "t")
            flow = {"ph": phase, "cat": "frame", "name": "frame", "id": frame, "pid": pid, "tid": tid,
                    "ts": self._us(started)}
            self._emit({**flow, "bp": "e"} if phase == "f" else flow)
            prev_finished = finished

    def _flush(self, stage: str) -> None:
        span = self.pending.pop(stage)
        started, finished = span["key"]
        self._emit({"ph": "X", "cat": "service", "name": stage,
                    "pid": span["pid"], "tid": span["tid"], "ts": self._us(started),
                    "dur": round((finished - started) * 1e6, 3), "args": {"frames": span["frames"]}})

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        """Write the pending spans and close the array."""
        for stage in list(self.pending):
            self._flush(stage)
        # every event is followed by a comma; the last one, the source's name again, is not
        self._fh.write(json.dumps({"ph": "M", "name": "process_name", "pid": 1, "args": self._process_args(1)},
                                  separators=(",", ":")) + "\n]\n")
        self._fh.close()


def read_trace(path: str | Path) -> list[dict[str, Any]]:
    """The events of a trace file, whether its array was closed or cut short (in the middle of an
    event, too: that event is left out)."""
    text = Path(path).read_text(encoding="utf-8").rstrip()
    if not text.endswith("]"):
        text = text[: text.rfind("\n") + 1] if not text.endswith(",") else text
        text = text.rstrip().rstrip(",") + "]"
    return json.loads(text)


def trace_origin(path: str | Path) -> float | None:
    """The run's start (s since the epoch) that the ``ts`` of the trace at ``path`` count from, read
    from its first events (None: a trace written before it was recorded)."""
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if '"origin_s"' in line:
                return float(json.loads(line.rstrip().rstrip(","))["args"]["origin_s"])
    return None


def stage_figures(events: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per stage, the monitor's figures from the trace: the frames it served (``frames``), its mean
    service time per frame (``tau_mean_ms``: each batch's time divided among the frames served in
    it, as the worker measures tau_i; spans of one batch written apart count as one) and its
    queueing time's percentiles (``queue_p50_ms``, ``queue_p95_ms``: from taking a frame to serving
    it, 0 where no wait was written)."""
    import numpy as np

    batches: dict[tuple[str, float, float], int] = {}
    began: dict[tuple[str, int], float] = {}
    waits: dict[str, list[float]] = {}
    for e in events:
        if e.get("ph") == "X" and e.get("cat") == "service":
            key = (e["name"], e["ts"], e["dur"])
            batches[key] = batches.get(key, 0) + len(e["args"]["frames"])
        elif e.get("cat") == "queue" and e.get("ph") in ("b", "e"):
            stage = e["name"].removeprefix("waits for ")
            if e["ph"] == "b":
                began[(stage, e["id"])] = e["ts"]
            elif (stage, e["id"]) in began:
                waits.setdefault(stage, []).append(e["ts"] - began.pop((stage, e["id"])))
    out: dict[str, dict[str, float]] = {}
    for (stage, _ts, dur), n in batches.items():
        row = out.setdefault(stage, {"frames": 0, "busy_us": 0.0})
        row["frames"] += n
        row["busy_us"] += dur
    figures = {}
    for stage, r in out.items():
        w = np.zeros(int(r["frames"]))
        got = waits.get(stage, [])[: len(w)]
        w[: len(got)] = got
        p50, p95 = np.percentile(w, [50, 95]) / 1e3
        figures[stage] = {"frames": r["frames"], "tau_mean_ms": r["busy_us"] / r["frames"] / 1e3,
                          "queue_p50_ms": float(p50), "queue_p95_ms": float(p95)}
    return figures
