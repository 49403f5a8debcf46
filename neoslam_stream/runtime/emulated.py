"""Emulated stages and source: a known service time tau instead of an algorithm.

They reproduce the paper's worked example (Part I) through the real runtime: stages of given
service times fed at a fixed rate, so that the measured rate and loss can be set against eq. 2
(docs/runtime.md, "The paper's worked example"). Service time is slept by default (on few cores,
busy-waiting stages would measure the CPU scheduler instead of the architecture); ``busy=True``
spins, for machines with a core per stage.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from .messages import Field, Message, Topic
from .node import Node, NodeSpec, Output
from .source import SourceFrame

#: what an emulated stage publishes (on ``emulated/<i>``): an optional payload of fixed size
EMULATED = Topic("emulated", {"payload": Field("array", optional=True)})


class EmulatedStage(Node):
    """Consumes ``input`` and publishes ``output`` after ``tau_ms`` of (slept or busy) service time."""

    def __init__(self, input: str, output: str, tau_ms: float, busy: bool = False,
                 payload_bytes: int = 0) -> None:
        super().__init__()
        if tau_ms < 0:
            raise ValueError(f"tau_ms must be >= 0, got {tau_ms}")
        self.inputs = (input,)
        self.outputs = (output,)
        self.tau = tau_ms / 1e3
        self.busy = busy
        self.payload = np.zeros(payload_bytes, dtype=np.uint8) if payload_bytes else None

    def process(self, topic: str, msg: Message) -> Output:
        if self.busy:
            end = time.perf_counter() + self.tau
            while time.perf_counter() < end:
                pass
        elif self.tau > 0:
            time.sleep(self.tau)
        data = {} if self.payload is None else {"payload": self.payload}
        return [(self.outputs[0], msg.derive(EMULATED, data))]

    def info(self) -> dict:
        return {"emulated_tau_ms": self.tau * 1e3, "busy": self.busy}


def make_emulated_stage(**params: object) -> EmulatedStage:
    return EmulatedStage(**params)  # type: ignore[arg-type]


class EmulatedSource:
    """Small random frames (seeded), ``frames`` of them or endless when ``frames`` is None (a
    :class:`~neoslam_stream.runtime.source.Source`)."""

    def __init__(self, frames: int | None = None, height: int = 32, width: int = 32, rate_hz: float = 10.0,
                 seed: int = 0, with_odom: bool = False) -> None:
        self.length = frames
        self.rate_hz = rate_hz
        self.shape = (height, width, 3)
        self.seed = seed
        self.with_odom = with_odom

    def __iter__(self) -> Iterator[SourceFrame]:
        rng = np.random.default_rng(self.seed)
        i = 0
        while self.length is None or i < self.length:
            img = rng.integers(0, 256, self.shape, dtype=np.uint8)
            odom = (0.1, 0.0, 1.0 / self.rate_hz) if self.with_odom else None
            yield SourceFrame(frame=i, stamp=i / self.rate_hz, image=img, encoding="rgb8", odom=odom)
            i += 1

    def info(self) -> dict:
        return {"kind": "emulated", "frames": self.length, "shape": list(self.shape)}

    def close(self) -> None:
        pass


def emulated_pipeline(taus_ms: list[float], busy: bool = False) -> list:
    """NodeSpecs of a chain of emulated stages: image -> s1 -> s2 -> ... (topic ``emulated/<i>``)."""
    specs = []
    prev = "image"
    for i, tau in enumerate(taus_ms, start=1):
        out = f"emulated/{i}"
        specs.append(NodeSpec(name=f"stage{i}", factory="neoslam_stream.runtime.emulated:make_emulated_stage",
                               params={"input": prev, "output": out, "tau_ms": float(tau), "busy": busy}))
        prev = out
    return specs
