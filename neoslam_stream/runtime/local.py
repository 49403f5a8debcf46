"""Nodes hosted in the caller's process, called in sequence: the in-process API's engine.

The same nodes as a run, routed like the monolithic worker routes its chain (an output goes to the
later nodes that consume it), without processes, zenoh or encoding. Messages pushed from outside
are validated against their topic's schema, as a decoded message would be.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Sequence
from typing import Any

from .messages import Message, validate_data
from .node import Node, NodeSpec, Output


class LocalChain:
    """Builds the nodes of ``specs`` (``setup`` included) and routes messages between them.

    ``push(topic, msg)`` returns every ``(topic, message)`` the chain produced for it, in order;
    ``finish()`` flushes the nodes (the recorder writes its files when ``run_dir`` is given).
    """

    def __init__(self, specs: Sequence[NodeSpec], run_dir: str | os.PathLike | None = None) -> None:
        self.nodes: list[Node] = []
        self.consumers: dict[str, list[int]] = defaultdict(list)
        for i, spec in enumerate(specs):
            if spec.remap:
                raise ValueError(f"node {spec.name!r}: remapped topics are for multi-branch runs, "
                                 "not for an in-process chain")
            node = spec.build()
            if run_dir is not None:
                out = os.path.join(os.fspath(run_dir), spec.output_subdir)
                os.makedirs(out, exist_ok=True)
                node.run_dir = out
            node.setup()
            self.nodes.append(node)
            for t in node.inputs:
                self.consumers[str(t)].append(i)
        self.finished = False

    def node(self, name: str) -> Node:
        for n in self.nodes:
            if n.name == name:
                return n
        raise KeyError(f"no node named {name!r}; nodes: {[n.name for n in self.nodes]}")

    def push(self, topic: str, msg: Message) -> Output:
        """Feed one message from outside (a camera frame, odometry) to every node that reads it."""
        if self.finished:
            raise RuntimeError("the chain has finished; build a new one")
        validate_data(msg.type, msg.data)
        out: Output = []
        for i in self.consumers.get(topic, []):
            self._run(i, topic, msg, out)
        return out

    def _run(self, idx: int, topic: str, msg: Message, out: Output) -> None:
        self._route(idx, self.nodes[idx].process(topic, msg), out)

    def _route(self, idx: int, produced: Output, out: Output) -> None:
        for t, m in produced:
            out.append((str(t), m))
            for j in self.consumers.get(str(t), []):
                if j > idx:
                    self._run(j, str(t), m, out)

    def finish(self) -> Output:
        """Flush every node in order (waiting events are processed, the map is published, files
        are written); returns what that produced."""
        out: Output = []
        if self.finished:
            return out
        for i, node in enumerate(self.nodes):
            self._route(i, node.flush(), out)
        for node in self.nodes:
            node.close()
        self.finished = True
        return out

    def info(self) -> dict[str, Any]:
        return {n.name: n.info() for n in self.nodes}
