"""Stage C: the neocortex — HTM Temporal Memory on the sLSBH bits, emitting winner cells.

NeoSLAM uses no spatial pooler: the 512 on-bits of the 2048-bit sLSBH code are the active columns
of a Temporal Memory with 2048 columns x 32 cells, learning always on and never reset. The output
is the set of winner cells (~512 indices of 65536) plus the raw anomaly for the monitor.

With htm.core's lowest-index tie rule (``tie_break: lowest``, the default, what the ROS 2 NeoSLAM
runs) nearly every winner is cell 0 of its column, so the SDR is in effect the input re-indexed.
``tie_break: random`` (NuPIC's rule, what the original NeoSLAM ran) puts a column's first segment
on a random cell, but with min_threshold 1 that segment goes on matching (one active presynaptic
cell of its ~20 is enough), so the column keeps that cell: nearly every winner is the column's
usual cell, the input re-indexed by a fixed per-column permutation, and still no sequence
context. Measurements: docs/temporal_memory.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._config import make_config
from .temporal_memory import Count, Permanence, Positive, TemporalMemory, TemporalMemoryConfig


class NeocortexConfig(TemporalMemoryConfig):
    """The Temporal Memory's parameters with NeoSLAM's values as defaults (identical in the
    original and the ROS 2 NeoSLAM; the others are htm.core's defaults)."""

    activation_threshold: Count = 4
    initial_permanence: Permanence = 0.55
    min_threshold: Count = 1
    permanence_increment: Permanence = 0.01
    permanence_decrement: Permanence = 0.01
    predicted_segment_decrement: Permanence = 0.0005
    max_segments_per_cell: Positive = 100
    max_synapses_per_segment: Positive = 100


class Neocortex:
    """Stage C: sLSBH bits (the active columns) -> winner cells of the Temporal Memory.

    ``Neocortex(config)`` with a :class:`NeocortexConfig` (or keyword overrides of its fields);
    ``compute(bits)`` runs one learning step (no reset, ever) and returns the winner cells;
    ``anomaly`` is the raw anomaly of that step.
    """

    def __init__(self, config: NeocortexConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(NeocortexConfig, config, overrides)
        self.tm = TemporalMemory(self.config)
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

    def warm_up(self) -> None:
        """Compile the numba kernels now, on a throw-away copy (this one's state is untouched)."""
        warm = Neocortex(self.config)
        step = max(1, self.config.columns // 64)
        warm.compute(np.arange(0, self.config.columns, step))
        warm.compute(np.arange(1, self.config.columns, step))

    def state_dict(self) -> dict[str, Any]:
        return {"tm": self.tm.state_dict(), "steps": self.steps, "anomaly_sum": self.anomaly_sum}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict`; the Temporal Memory refuses a state made with other
        parameters."""
        self.tm.load_state_dict(st["tm"])
        self.steps = int(st["steps"])
        self.anomaly_sum = float(st["anomaly_sum"])
