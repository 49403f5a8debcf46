"""Checkpoint cuts of a worker's stages: consistent snapshots of the whole pipeline.

Every stage saves its state at the same frame numbers (multiples of ``checkpoint_every``), as it
is after every frame below the cut, so the files of one cut restore every stage to one moment. A
stage with several inputs running at different paces holds the messages at or beyond the next cut
until each input has reached it. At the end of a run each stateful stage's state goes to
RUN_DIR/state/ (the map ``neoslam map export`` packs). File formats: checkpoint.py.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .checkpoint import cut_dir, save_stage_state, save_state_file
from .files import describe_write_error
from .messages import Message
from .worker_stats import StageRuntime

log = logging.getLogger("neoslam.worker")

#: how a held message is processed once its cut is saved: (topic, messages, arrival times)
Process = Callable[[str, list[Message], list[float]], None]


def count_write_error(st: StageRuntime, path: Any, exc: OSError) -> None:
    """A failed write of ``st``'s state (disk full): logged once per stage, then counted under its
    node's ``write_errors`` counter."""
    counters = st.node.counters
    if not counters.get("write_errors"):
        log.error("stage %s: %s (further write errors of this stage are counted, not logged)",
                  st.name, describe_write_error(path, exc))
    counters["write_errors"] = counters.get("write_errors", 0) + 1


class CheckpointCuts:
    """Where and when a worker's stages save their state (module docstring): every
    ``checkpoint_every`` frames into ``checkpoint_dir`` (0: never), and at the end into
    ``run_dir``/state. The worker owns one and calls it with the stage concerned; a multi-input
    stage's held messages go back to the worker through the ``process`` it is given."""

    #: a multi-input stage holds at most this many messages for a cut; beyond, it cuts anyway
    #: (an input that never reaches the cut, e.g. no odometry at all, must not stall the stage)
    MAX_DEFERRED = 512

    def __init__(self, checkpoint_every: int, checkpoint_dir: str, run_dir: str) -> None:
        self.every = checkpoint_every
        self.checkpoint_dir = checkpoint_dir
        self.run_dir = run_dir

    @property
    def enabled(self) -> bool:
        return self.every > 0

    def resumed(self, st: StageRuntime, path: str) -> None:
        """``st`` was loaded from the state file ``path``: when it is a cut's (its folder is the
        cut's frame number), the stage's next cut follows that one."""
        cut = Path(path).parent.name
        if cut.isdigit() and self.enabled:
            st.checkpoint_index = int(cut) // self.every

    def maybe_save(self, st: StageRuntime, frame: int) -> None:
        """Save the stage's state as it is after every frame below the cut ``m * checkpoint_every``.

        Every stage cuts at the same frame numbers, so the files of one cut form a consistent
        snapshot of the whole pipeline (see checkpoint.py).
        """
        n = self.every
        if n <= 0 or frame // n <= st.checkpoint_index:
            return
        # one cut per message at most: frames jumping over several cuts save the newest one only
        st.checkpoint_index = frame // n
        self.save(st, st.checkpoint_index * n)

    def save(self, st: StageRuntime, cut: int) -> None:
        """Save the stage's state for ``cut``; a failed write (disk full) is logged once, counted
        under the node's ``write_errors`` counter, and the stage goes on without that cut."""
        try:
            save_stage_state(self.checkpoint_dir, cut, st.name, st.node.state_dict())
        except OSError as exc:
            count_write_error(st, cut_dir(self.checkpoint_dir, cut) / f"{st.name}.state", exc)

    def hold(self, st: StageRuntime, topic: str, msgs: list[Message],
             received: list[float]) -> tuple[list[Message], list[float]]:
        """Multi-input stages: the state saved for cut C must hold every frame < C of *every*
        input and nothing beyond, but inputs run at different paces (odometry is ahead of the
        templates). Messages of frames >= C wait until each input has reached C; then the state
        is saved and they are processed. Returns the messages that may be processed now."""
        cut = (st.checkpoint_index + 1) * self.every
        ready_m, ready_r = [], []
        if topic not in st.ordered_inputs:  # a message at the end of the run, not a frame's
            return msgs, received
        for m, r in zip(msgs, received, strict=True):
            if m.frame >= cut:
                st.deferred.append((topic, m, r))
                st.reached[topic] = max(st.reached.get(topic, -1), m.frame)
            else:
                ready_m.append(m)
                ready_r.append(r)
        return ready_m, ready_r

    def release(self, st: StageRuntime, process: Process, budget: int = 1) -> None:
        """Save the cut once every input has reached it (or too much is held), then process what
        was held. A loop, not a recursion: each round saves one cut and hands every held message
        below the next cut to ``process``; the cut saved is the newest one the held messages and
        the inputs' progress allow, so frames far ahead never make it save every multiple of N on
        the way (at most one cut per round, and a round ends with a held message processed or
        with the stage waiting for an input). At most ``budget`` rounds (the number of messages
        that came in): one message makes at most one cut folder, whatever its frame number; what
        is still held waits for the next message (each round processes at least the lowest held
        message, so the held list stays bounded)."""
        n = self.every
        while st.deferred and budget > 0:
            cut = (st.checkpoint_index + 1) * n
            reached = all(st.reached.get(t, -1) >= cut for t in st.ordered_inputs)
            if not reached and len(st.deferred) < self.MAX_DEFERRED:
                return
            # nothing below the lowest held frame is still to come on an input that reached it:
            # the state now is that of every cut up to there (only empty cuts are skipped)
            bound = min(m.frame for _t, m, _r in st.deferred)
            if reached:
                bound = min(bound, *(st.reached.get(t, -1) for t in st.ordered_inputs))
            cut = max(cut, bound // n * n)
            st.checkpoint_index = cut // n
            self.save(st, cut)
            budget -= 1
            held, st.deferred = st.deferred, []
            for t, m, r in held:  # in arrival order; the next cut may hold some of them again
                ready_m, ready_r = self.hold(st, t, [m], [r])
                if ready_m:
                    process(t, ready_m, ready_r)

    def save_final_states(self, stages: list[StageRuntime], worker: str) -> None:
        """Every stateful stage's state at the end of the run, in RUN_DIR/state/ (the map that
        ``neoslam map export`` packs), written atomically; then ``<worker>.saved``, the names of
        the states written, which tells the export that this worker got as far (a worker the
        supervisor stopped by force before it did has none: its stages' states may be missing)."""
        saved = []
        for st in stages:
            if st.node.observer:  # what a watcher holds (rows of output files) is no learned map
                continue
            path = Path(self.run_dir) / "state" / f"{st.name}.state"
            try:
                state = st.node.state_dict()
                if state:
                    save_state_file(path, state)
                    saved.append(st.name)
            except OSError as exc:  # disk full: the previous file (if any) is intact; say so
                count_write_error(st, path, exc)
            except Exception as exc:  # never lose the flush over it; say so
                log.error("stage %s: final state not saved: %s", st.name, exc)
        marker = Path(self.run_dir) / "state" / f"{worker}.saved"
        try:
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.write_text(json.dumps(saved) + "\n")
        except OSError as exc:
            log.error("worker %s: %s not written: %s", worker, marker, exc)
