"""The contract between the runtime and the algorithms: a node.

A node turns messages into calls on one algorithm object (``neoslam_stream.algorithms``) and the
results back into messages; the nodes live in ``neoslam_stream.nodes``. The runtime hosts nodes:
one per process in the ``pipeline`` topology, several in sequence in one process in the
``monolithic`` topology, all in the caller's process for the in-process API (``runtime.local``).
It never looks inside them.

Nodes are built inside the worker process from a :class:`NodeSpec` (a dotted factory path and
plain parameters), because worker processes are started with ``spawn`` and only plain data crosses.

Rules for nodes:

* ``inputs``/``outputs`` name the topics, as :class:`~neoslam_stream.runtime.messages.Topic`
  declarations carrying their schemas (``neoslam_stream.nodes.topics``).
* ``process`` receives one decoded, validated :class:`~neoslam_stream.runtime.messages.Message` and returns
  the messages to publish as ``(topic, message)`` pairs; use ``msg.derive(type, data)`` so frame,
  stamp and trace carry over. The worker appends this stage's trace entry itself.
* Bad input (wrong shape, NaN, corrupt image...) raises :class:`StageInputError` (or
  :class:`~neoslam_stream.runtime.messages.MessageError`, or an algorithm's
  ``neoslam_stream.algorithms.errors.InvalidInput``): the worker counts it with its cause, logs the
  cause once, skips the message and carries on. Any other exception is a bug: the worker logs its
  traceback and counts it apart (``internal_errors``), never as bad input (see
  :func:`is_input_error`).
* Frames removed on purpose (``frame_stride``) return ``[]`` and increment ``self.counters["strided"]``,
  so the monitor does not count them as lost.
* A node that publishes outside the run's topics (the ROS 2 output) defines
  ``bind_session(session)``: its worker calls it with the run's zenoh session once connected.
* ``info()`` returns small JSON-able facts for ``stats/<stage>`` and ``report.json`` (backbone that
  ran, TM segment counts...). ``flush()`` is called once at shutdown.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .messages import Message, MessageError

Output = list[tuple[str, Message]]


class StageInputError(ValueError):
    """The message was valid on the wire but cannot be processed by this stage (the cause is the text)."""

    #: marks an input error (see :func:`is_input_error`)
    invalid_input = True


def is_input_error(exc: BaseException) -> bool:
    """Whether ``exc`` says that the *input* was bad (count it, skip the input) rather than that the
    code is wrong: :class:`StageInputError`, :class:`~neoslam_stream.runtime.messages.MessageError`,
    and the algorithms' ``InvalidInput``, which the runtime may not import and recognises by its
    class attribute ``invalid_input = True``. A plain ``ValueError`` is not one."""
    return isinstance(exc, (StageInputError, MessageError)) or getattr(type(exc), "invalid_input", False) is True


class Node:
    """Base class of all nodes; subclasses set ``name``, ``inputs``, ``outputs``."""

    name: str = "stage"
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    #: True when ``process_batch`` is cheaper per frame than repeated ``process`` (micro-batching).
    batchable: bool = False
    #: inputs that are not per-frame streams (a message at the end of the run, such as the whole
    #: map): checkpoint cuts do not wait for them to reach the cut frame
    unordered_inputs: tuple[str, ...] = ()
    #: folder for the files this node writes, set by its host ("" = the node writes no file)
    run_dir: str = ""
    #: the run's id, set by its host: a worker restarted after a crash gets the same one, so a node
    #: that writes files can tell its own earlier output from another run's ("" in-process)
    run_id: str = ""
    #: a node that only watches topics (the recorder): hosting it next to their producer does not
    #: keep them off the bus
    observer: bool = False

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
class NodeSpec:
    """How to build one node in a worker process: ``factory`` is ``"package.module:callable"``
    called as ``callable(**params)`` and returning a :class:`Node`."""

    name: str
    factory: str
    params: dict[str, Any] = field(default_factory=dict)
    #: torch / BLAS / numba threads for this worker (2 cores are shared by ~7 processes).
    threads: int = 1
    #: node topic -> bus topic, to run two copies of a stage side by side (e.g. ``neoslam compare``)
    remap: dict[str, str] = field(default_factory=dict)
    #: sub-folder of the run folder for the files this node writes ("" = the run folder itself)
    output_subdir: str = ""
    #: pipeline topology: host this node in the worker process of the node named here instead of
    #: a process of its own (a light node such as the recorder needs no process)
    host: str = ""
    #: input queue capacity per topic for this node, at least (a recorder must not lose rows)
    capacity: dict[str, int] = field(default_factory=dict)
    #: the node only watches topics (the recorder): its process is stopped after all others, so
    #: it sees everything they produced up to their end (see Node.observer)
    observer: bool = False
    #: zenoh endpoints the host worker also connects to (a ROS 2 router the node publishes to)
    connect: list[str] = field(default_factory=list)

    def build(self) -> Node:
        node = load_factory(self.factory)(**self.params)
        if not isinstance(node, Node):
            raise TypeError(f"{self.factory} returned {type(node).__name__}, not a Node")
        node.name = self.name
        node.observer = node.observer or self.observer
        return node
