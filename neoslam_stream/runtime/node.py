"""The contract between the runtime and the algorithms: a node.

A node turns typed topic messages into calls on one algorithm object and the results back into
messages (the nodes live in ``neoslam_stream.nodes``). The runtime hosts nodes, one per process
(``pipeline``) or several in sequence in one process (``monolithic``), and never looks inside
them. Nodes are built where they run from a :class:`NodeSpec` (a dotted factory path and plain
parameters: only plain data crosses a ``spawn``).

A node declares ``inputs``/``outputs`` as ``Topic`` declarations (``runtime.messages``), which
are registered with the codec when it is built; ``process`` gets one decoded, validated message
and returns ``(topic, message)`` pairs made with ``msg.derive``; bad input raises
:class:`StageInputError` (counted and skipped: :func:`is_input_error`), any other exception is a
bug. The rules in full: docs/runtime.md, "Writing a node".
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from .messages import Message, MessageError, Topic, register_topics

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
        register_declared_topics(self)

    def setup(self) -> None:
        """Heavy initialisation (model weights, numba compilation); called once in the worker process."""

    def warm_up(self, max_batch: int) -> None:
        """Pay one-time costs of the first calls before the first frame (a real-time worker calls
        it after ``setup`` with the most messages it may hand ``process_batch`` at once), so that
        they do not stall a live stream; default: nothing."""

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


def register_declared_topics(node: Node) -> None:
    """Register the schemas of the :class:`Topic` declarations among ``node``'s inputs and outputs
    (plain names are the types a plan registers, such as the emulated stages')."""
    register_topics(t for t in (*node.inputs, *node.outputs) if isinstance(t, Topic))


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
    #: torch / BLAS / numba threads for this worker (the stages of a run share the cores)
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
        register_declared_topics(node)  # also those a node declares after Node.__init__
        return node
