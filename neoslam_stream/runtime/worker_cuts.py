"""Checkpoint cuts of a worker's stages: consistent snapshots of the whole pipeline.

Every stage saves its state at the same frame numbers (multiples of ``checkpoint_every``), as it
is after every frame below the cut, so the files of one cut restore every stage to one moment. A
stage with several inputs running at different paces holds the messages at or beyond the next cut
until each input has reached it. At the end of a run each stateful stage's state goes to
RUN_DIR/state/ (the map ``neoslam map export`` packs). File formats: checkpoint.py.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from .files import describe_write_error
from .messages import Message
from .worker_stats import StageRuntime

log = logging.getLogger("neoslam.worker")


class CheckpointCuts:
    """The checkpoint part of :class:`~neoslam_stream.runtime.worker.Worker` (mixed into it: it
    reads the worker's spec and stages and hands released messages to its ``_process``)."""

    def _maybe_checkpoint(self, st: StageRuntime, frame: int) -> None:
        """Save the stage's state as it is after every frame below the cut ``m * checkpoint_every``.

        Every stage cuts at the same frame numbers, so the files of one cut form a consistent
        snapshot of the whole pipeline (see checkpoint.py).
        """
        n = self.spec.checkpoint_every
        if n <= 0 or frame // n <= st.checkpoint_index:
            return
        # one cut per message at most: frames jumping over several cuts save the newest one only
        st.checkpoint_index = frame // n
        self._save_cut(st, st.checkpoint_index * n)

    def _save_cut(self, st: StageRuntime, cut: int) -> None:
        """Save the stage's state for ``cut``; a failed write (disk full) is logged once, counted
        under the node's ``write_errors`` counter, and the stage goes on without that cut."""
        from .checkpoint import cut_dir, save_stage_state

        try:
            save_stage_state(self.spec.checkpoint_dir, cut, st.name, st.adapter.state_dict())
        except OSError as exc:
            self._write_failed(st, cut_dir(self.spec.checkpoint_dir, cut) / f"{st.name}.state", exc)

    def _write_failed(self, st: StageRuntime, path: Any, exc: OSError) -> None:
        counters = st.adapter.counters
        if not counters.get("write_errors"):
            log.error("stage %s: %s (further write errors of this stage are counted, not logged)",
                      st.name, describe_write_error(path, exc))
        counters["write_errors"] = counters.get("write_errors", 0) + 1

    #: a multi-input stage holds at most this many messages for a cut; beyond, it cuts anyway
    #: (an input that never reaches the cut, e.g. no odometry at all, must not stall the stage)
    MAX_DEFERRED = 512

    def _hold_for_cut(self, idx: int, topic: str, msgs: list[Message],
                      received: list[float]) -> tuple[list[Message], list[float]]:
        """Multi-input stages: the state saved for cut C must hold every frame < C of *every*
        input and nothing beyond, but inputs run at different paces (odometry is ahead of the
        templates). Messages of frames >= C wait until each input has reached C; then the state
        is saved and they are processed. Returns the messages that may be processed now."""
        st = self.stages[idx]
        n = self.spec.checkpoint_every
        cut = (st.checkpoint_index + 1) * n
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

    def _release_cut(self, idx: int, budget: int = 1) -> None:
        """Save the cut once every input has reached it (or too much is held), then process what
        was held. A loop, not a recursion: each round saves one cut and hands every held message
        below the next cut to the node; the cut saved is the newest one the held messages and the
        inputs' progress allow, so frames far ahead never make it save every multiple of N on the
        way (at most one cut per round, and a round ends with a held message processed or with
        the stage waiting for an input). At most ``budget`` rounds (the number of messages that
        came in): one message makes at most one cut folder, whatever its frame number; what is
        still held waits for the next message (each round processes at least the lowest held
        message, so the held list stays bounded)."""
        st = self.stages[idx]
        n = self.spec.checkpoint_every
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
            self._save_cut(st, cut)
            budget -= 1
            held, st.deferred = st.deferred, []
            for t, m, r in held:  # in arrival order; the next cut may hold some of them again
                ready_m, ready_r = self._hold_for_cut(idx, t, [m], [r])
                if ready_m:
                    self._process(idx, t, ready_m, ready_r)

    def _save_final_states(self) -> None:
        """Every stateful stage's state at the end of the run, in RUN_DIR/state/ (the map that
        ``neoslam map export`` packs), written atomically."""
        from .checkpoint import save_state_file

        for st in self.stages:
            if st.adapter.observer:  # what a watcher holds (rows of output files) is no learned map
                continue
            path = Path(self.spec.run_dir) / "state" / f"{st.name}.state"
            try:
                state = st.adapter.state_dict()
                if state:
                    save_state_file(path, state)
            except OSError as exc:  # disk full: the previous file (if any) is intact; say so
                self._write_failed(st, path, exc)
            except Exception as exc:  # never lose the flush over it; say so
                log.error("stage %s: final state not saved: %s", st.name, exc)
