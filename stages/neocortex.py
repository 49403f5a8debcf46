"""Stage C: the neocortex — HTM Temporal Memory on the sLSBH bits, emitting winner cells.

NeoSLAM uses no spatial pooler: the 512 on-bits of the 2048-bit sLSBH code are the active columns
of a Temporal Memory with 2048 columns x 32 cells, learning always on and never reset. The output
is the set of winner cells (~512 indices of 65536) plus the raw anomaly for the monitor.

With htm.core's lowest-index tie rule (``tie_break: lowest``, the default, what the ROS 2 NeoSLAM
runs) nearly every winner is cell 0 of its column, so the SDR is in effect the input re-indexed.
``tie_break: random`` (NuPIC's rule, what the original NeoSLAM ran) puts a column's first segment
on a random cell, but with minThreshold 1 that segment goes on matching (one active presynaptic
cell of its ~20 is enough), so the column keeps that cell: >= 99 % of winners are the column's
usual cell in our benches, the input re-indexed by a fixed per-column permutation, and still no
sequence context. See docs/temporal_memory.md.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from neoslam_stream.messages import Message
from neoslam_stream.stage import Output, StageAdapter, StageInputError

from .temporal_memory import TemporalMemory


class NeocortexConfig(BaseModel):
    """NeoSLAM's TM parameters (identical in the original and the ROS 2 NeoSLAM)."""

    model_config = ConfigDict(extra="forbid")

    columns: int = Field(2048, ge=1)
    cells_per_column: int = Field(32, ge=1)
    activation_threshold: int = 4
    initial_permanence: float = 0.55
    connected_permanence: float = 0.5
    min_threshold: int = 1
    max_new_synapse_count: int = 20
    permanence_increment: float = 0.01
    permanence_decrement: float = 0.01
    predicted_segment_decrement: float = 0.0005
    max_segments_per_cell: int = 100
    max_synapses_per_segment: int = 100
    seed: int = 42
    tie_break: Literal["lowest", "random"] = "lowest"


class Neocortex:
    """Stage C: sLSBH bits (the active columns) -> winner cells of the Temporal Memory.

    ``Neocortex(**NeocortexConfig fields)``; ``compute(bits)`` runs one learning step (no reset,
    ever) and returns the winner cells; ``anomaly`` is the raw anomaly of that step.
    """

    def __init__(self, **params: Any) -> None:
        self.config = NeocortexConfig(**params)
        c = self.config
        self.tm = TemporalMemory(
            columnDimensions=(c.columns,), cellsPerColumn=c.cells_per_column,
            activationThreshold=c.activation_threshold, initialPermanence=c.initial_permanence,
            connectedPermanence=c.connected_permanence, minThreshold=c.min_threshold,
            maxNewSynapseCount=c.max_new_synapse_count, permanenceIncrement=c.permanence_increment,
            permanenceDecrement=c.permanence_decrement, predictedSegmentDecrement=c.predicted_segment_decrement,
            seed=c.seed, maxSegmentsPerCell=c.max_segments_per_cell,
            maxSynapsesPerSegment=c.max_synapses_per_segment, tie_break=c.tie_break)
        self.steps = 0
        self.anomaly_sum = 0.0

    @property
    def n_cells(self) -> int:
        return self.tm.n_cells

    def compute(self, bits: np.ndarray) -> np.ndarray:
        """One frame: the sLSBH on-bits (integer indices < ``columns``) are the active columns;
        returns the sorted uint32 winner cells (cell = column * cells_per_column + i)."""
        winners = self.tm.compute(bits, learn=True)
        self.steps += 1
        self.anomaly_sum += self.tm.anomaly
        return winners.astype(np.uint32)

    @property
    def anomaly(self) -> float:
        return self.tm.anomaly

    def state_dict(self) -> dict[str, Any]:
        return {"tm": self.tm.state_dict(), "steps": self.steps, "anomaly_sum": self.anomaly_sum}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.tm.load_state_dict(st["tm"])
        self.steps = int(st["steps"])
        self.anomaly_sum = float(st["anomaly_sum"])


class NeocortexStage(StageAdapter):
    """``bin_features`` -> ``sdr`` (winner cells, size 65536, anomaly)."""

    inputs = ("bin_features",)
    outputs = ("sdr",)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.neocortex = Neocortex(**params)

    def setup(self) -> None:
        # compile the numba kernels before the first frame arrives
        warm = Neocortex(**self.neocortex.config.model_dump())
        warm.compute(np.arange(0, warm.config.columns, max(1, warm.config.columns // 64)))
        warm.compute(np.arange(1, warm.config.columns, max(1, warm.config.columns // 64)))

    def process(self, topic: str, msg: Message) -> Output:
        bits = msg["bits"]
        if int(msg["size"]) != self.neocortex.config.columns:
            raise StageInputError(f"bin_features of size {msg['size']}, the neocortex has "
                                  f"{self.neocortex.config.columns} columns")
        try:
            cells = self.neocortex.compute(bits)
        except ValueError as exc:
            raise StageInputError(str(exc)) from None
        return [("sdr", msg.derive("sdr", {"cells": cells, "size": self.neocortex.n_cells,
                                           "anomaly": float(self.neocortex.anomaly)}))]

    def info(self) -> dict[str, Any]:
        n = self.neocortex
        return {"segments": n.tm.segments, "synapses": n.tm.synapses, "steps": n.steps,
                "mean_anomaly": n.anomaly_sum / n.steps if n.steps else None,
                "tie_break": n.config.tie_break}

    def state_dict(self) -> dict[str, Any]:
        return self.neocortex.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.neocortex.load_state_dict(state)


def make_stage(**params: Any) -> NeocortexStage:
    return NeocortexStage(**params)
