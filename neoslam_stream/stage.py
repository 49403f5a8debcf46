"""The contract between the runtime and the algorithms: a stage adapter.

An adapter turns messages into calls on one algorithm object from ``stages/`` and the results back
into messages. The runtime hosts adapters: one per process in the ``pipeline`` topology, several in
sequence in one process in the ``monolithic`` topology. It never looks inside them.

Adapters are built inside the worker process from a :class:`StageSpec` (a dotted factory path and
plain parameters), because worker processes are started with ``spawn`` and only plain data crosses.

Rules for adapters:

* ``process`` receives one decoded, validated :class:`~neoslam_stream.messages.Message` and returns
  the messages to publish as ``(topic, message)`` pairs; use ``msg.derive(type, data)`` so frame,
  stamp and trace carry over. The worker appends this stage's trace entry itself.
* Bad input (wrong shape, NaN, corrupt image...) raises :class:`StageInputError` (or
  :class:`~neoslam_stream.messages.MessageError`): the worker counts it with its cause, logs the
  cause once, skips the message and carries on.
* Frames removed on purpose (``frame_stride``) return ``[]`` and increment ``self.counters["strided"]``,
  so the monitor does not count them as lost.
* ``info()`` returns small JSON-able facts for ``stats/<stage>`` and ``report.json`` (backbone that
  ran, TM segment counts...). ``flush()`` is called once at shutdown.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .messages import Message

Output = list[tuple[str, Message]]


class StageInputError(ValueError):
    """The message was valid on the wire but cannot be processed by this stage (the cause is the text)."""


class StageAdapter:
    """Base class of all stage adapters; subclasses set ``name``, ``inputs``, ``outputs``."""

    name: str = "stage"
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    #: True when ``process_batch`` is cheaper per frame than repeated ``process`` (micro-batching).
    batchable: bool = False

    def __init__(self) -> None:
        self.counters: dict[str, int] = {"strided": 0}

    def setup(self) -> None:
        """Heavy initialisation (model weights, numba compilation); called once in the worker process."""

    def process(self, topic: str, msg: Message) -> Output:
        raise NotImplementedError

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        """Process several waiting messages of one topic at once; default: one by one."""
        out: Output = []
        for m in msgs:
            out.extend(self.process(topic, m))
        return out

    def flush(self) -> Output:
        """Called once at shutdown; returns any final messages (e.g. the whole map)."""
        return []

    def info(self) -> dict[str, Any]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass

    def new_session(self) -> None:
        """Called after an imported map was loaded (``neoslam run --map``): forget what belongs to
        the previous data stream (frame numbers, waiting buffers, per-run outputs) and keep what
        was learned (templates, connections, experiences). Default: nothing to forget."""

    def close(self) -> None:
        pass


def load_factory(path: str) -> Any:
    """The callable named by ``"package.module:callable"``."""
    module_name, _, attr = path.partition(":")
    if not module_name or not attr:
        raise ValueError(f"factory {path!r} must look like 'package.module:callable'")
    return getattr(importlib.import_module(module_name), attr)


@dataclass
class StageSpec:
    """How to build one adapter in a worker process: ``factory`` is ``"package.module:callable"``
    called as ``callable(**params)`` and returning a :class:`StageAdapter`."""

    name: str
    factory: str
    params: dict[str, Any] = field(default_factory=dict)
    #: torch / BLAS / numba threads for this worker (2 cores are shared by ~7 processes).
    threads: int = 1
    #: adapter topic -> bus topic, to run two copies of a stage side by side (e.g. ``neoslam compare``)
    remap: dict[str, str] = field(default_factory=dict)
    #: sub-folder of the run folder for the files this stage writes ("" = the run folder itself)
    output_subdir: str = ""

    def build(self) -> StageAdapter:
        adapter = load_factory(self.factory)(**self.params)
        if not isinstance(adapter, StageAdapter):
            raise TypeError(f"{self.factory} returned {type(adapter).__name__}, not a StageAdapter")
        adapter.name = self.name
        return adapter
