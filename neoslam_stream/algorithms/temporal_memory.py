"""HTM Temporal Memory with htm.core's behaviour, written from the algorithm's description.

One step, ``compute(active_columns, learn)``, is htm.core's: activateDendrites (the predictions
of the previous step), the raw anomaly, then activateCells column by column (predicted columns
activate their predicted cells, the others burst; learning adapts, grows, creates and punishes
segments). Every segment keeps the same synapses, synapse ids and slot order as htm.core's, and
random numbers come from our own MT19937 (the stream of ``std::mt19937(seed)``, drawn where
htm.core draws them), so a run is bit-exact against htm.core (tests/test_tm_parity.py). Inputs
and outputs are sorted numpy index arrays, not ``SDR`` objects; the parameters are htm.core's
under snake_case names (:class:`TemporalMemoryConfig`). Data layout: struct-of-arrays (segments
are rows of fixed-capacity synapse tables, with free lists), numba-compiled loops, dendrite
activity as one sequential pass over the synapse table. Behaviour, the two corners where we
knowingly differ, the API and speed: docs/temporal_memory.md.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from . import temporal_memory_kernels as kern
from ._config import make_config
from .errors import InvalidInput
from .temporal_memory_kernels import EPS

#: the value types of the parameters, with their bounds (a subclass restates only defaults)
Positive = Annotated[int, Field(ge=1)]
Count = Annotated[int, Field(ge=0)]
Permanence = Annotated[float, Field(ge=0, le=1)]


class TemporalMemoryConfig(BaseModel):
    """htm.core's TemporalMemory parameters under snake_case names, with htm.core's defaults
    (``columns`` is htm.core's one-dimensional ``columnDimensions``)."""

    model_config = ConfigDict(extra="forbid")

    columns: Positive = 2048
    cells_per_column: Positive = 32
    activation_threshold: Count = 13
    initial_permanence: Permanence = 0.21
    connected_permanence: Permanence = 0.5
    min_threshold: Count = 10
    max_new_synapse_count: Count = 20
    permanence_increment: Permanence = 0.1
    permanence_decrement: Permanence = 0.1
    predicted_segment_decrement: Permanence = 0.0
    max_segments_per_cell: Positive = 255
    max_synapses_per_segment: Positive = 255
    seed: int = 42
    #: which least-used cell a bursting column without a matching segment picks: htm.core's
    #: lowest index, or NuPIC's uniform random choice among them (docs/temporal_memory.md)
    tie_break: Literal["lowest", "random"] = "lowest"

    @model_validator(mode="after")
    def _min_threshold_at_most_activation_threshold(self) -> TemporalMemoryConfig:
        if self.min_threshold > self.activation_threshold:
            raise ValueError(f"min_threshold ({self.min_threshold}) must be <= activation_threshold "
                             f"({self.activation_threshold}), as htm.core requires")
        return self


# --------------------------------------------------------------------------- the class

class TemporalMemory:
    """htm.core-compatible Temporal Memory (see the module docstring)."""

    def __init__(self, config: TemporalMemoryConfig | None = None, **overrides: Any) -> None:
        """``TemporalMemory(config)``, or keyword overrides of its fields
        (``TemporalMemory(columns=2048, cells_per_column=32, ...)``); the parameters and their
        defaults (htm.core's) are :class:`TemporalMemoryConfig`'s."""
        self.config = make_config(TemporalMemoryConfig, config, overrides)
        self._alloc(1024)
        self._mt = kern.mt_seed(np.uint32(self.config.seed))
        self._mt_idx = np.array([624], dtype=np.int64)
        self.reset()
        self._dendrites_valid = False
        self._act = np.zeros(0, np.int64)
        self._match = np.zeros(0, np.int64)
        self._pot = np.zeros(0, np.int32)
        self.anomaly = -1.0

    @property
    def n_cells(self) -> int:
        return self.config.columns * self.config.cells_per_column

    def _f32(self, name: str) -> np.float32:
        """A permanence parameter as the kernels take it (float32)."""
        return np.float32(getattr(self.config, name))

    # ---------------------------------------------------------------- storage
    def _alloc(self, cap: int) -> None:
        S = self.config.max_synapses_per_segment
        self._pre = np.zeros((cap, S), dtype=np.int32)
        self._perm = np.zeros((cap, S), dtype=np.float32)
        self._sid = np.zeros((cap, S), dtype=np.int32)  # global synapse ids (htm.core's Synapse)
        # free synapse ids never outnumber the slots: the id high-water mark is the peak synapse count
        self._syn_free = np.zeros(cap * S, dtype=np.int32)
        self._sst = np.zeros(2, dtype=np.int64)  # [synapse id high-water mark, free synapse ids]
        self._seg_cell = np.zeros(cap, dtype=np.int32)
        self._seg_nsyn = np.zeros(cap, dtype=np.int32)
        self._seg_alive = np.zeros(cap, dtype=np.bool_)
        self._free = np.zeros(cap, dtype=np.int32)
        self._nfree = np.zeros(1, dtype=np.int64)
        self._hw = np.zeros(1, dtype=np.int64)
        self._cell_segs = np.zeros((self.n_cells, self.config.max_segments_per_cell), dtype=np.int32)
        self._cell_nseg = np.zeros(self.n_cells, dtype=np.int32)

    def _ensure_capacity(self, extra: int) -> None:
        cap = self._seg_cell.shape[0]
        if self._hw[0] + extra <= cap:
            return
        new = max(2 * cap, int(self._hw[0]) + extra)

        def grow(a: np.ndarray, fill: Any = 0) -> np.ndarray:
            b = np.full((new,) + a.shape[1:], fill, dtype=a.dtype)
            b[:cap] = a
            return b

        self._pre, self._perm, self._sid = grow(self._pre), grow(self._perm), grow(self._sid)
        syn_free = np.zeros(new * self.config.max_synapses_per_segment, dtype=np.int32)
        syn_free[: self._syn_free.size] = self._syn_free
        self._syn_free = syn_free
        self._seg_cell, self._seg_nsyn = grow(self._seg_cell), grow(self._seg_nsyn)
        self._seg_alive, self._free = grow(self._seg_alive, False), grow(self._free)

    # ---------------------------------------------------------------- API
    def reset(self) -> None:
        """Forget the sequence context (active/winner cells, segment lists); keep what was learned."""
        self.active_cells = np.zeros(0, np.int64)
        self.winner_cells = np.zeros(0, np.int64)
        self.predictive_cells = np.zeros(0, np.int64)
        self._dendrites_valid = False
        self.anomaly = -1.0

    def activateDendrites(self, learn: bool = True) -> None:
        """Compute the predictions made by the current active cells (once per step)."""
        if self._dendrites_valid:
            return
        mask = np.zeros(self.n_cells, dtype=np.bool_)
        mask[self.active_cells] = True
        cfg = self.config
        conn_thr = np.float32(self._f32("connected_permanence") - EPS)
        self._act, self._match, self._pot = kern.activate_dendrites(
            mask, self._pre, self._perm, self._seg_nsyn, self._seg_alive, self._seg_cell, self._hw,
            conn_thr, cfg.activation_threshold, cfg.min_threshold, self.n_cells)
        self.predictive_cells = np.unique(self._seg_cell[self._act].astype(np.int64))
        self._dendrites_valid = True

    def compute(self, active_columns: np.ndarray, learn: bool = True) -> np.ndarray:
        """One time step; returns the winner cells (sorted int64 indices).

        1. activateDendrites: per segment, the active presynaptic cells on connected synapses
           (``conn``) and on any synapse (``pot``); active segments have conn >=
           activation_threshold, matching ones pot >= min_threshold. Predictive cells own an
           active segment. 2. The raw anomaly: the share of active columns without a predictive
           cell. 3. activateCells, columns in ascending order:

        * a predicted active column: every cell with an active segment becomes active and winner;
          each active segment is adapted (+increment on active, -decrement on inactive synapses)
          and grows ``max_new_synapse_count - pot`` synapses to the previous winners;
        * a bursting column: all cells active; the winner is the cell of the best matching segment
          (most active potential synapses, first on ties), else the column's previous winner (a
          static input), else a least-used cell (``tie_break``). Learning adapts and grows the best
          matching segment, or creates a segment on the winner with ``min(max_new_synapse_count,
          |previous winners|)`` synapses;
        * an inactive column's matching segments lose ``predicted_segment_decrement`` on their
          active synapses.

        Synapses below 1e-6 are destroyed after the pass, in slot order, and a segment left with
        fewer than min_threshold synapses is destroyed; growth beyond max_synapses_per_segment
        first removes the weakest synapses not onto a candidate (ties: lower synapse id); a cell
        at max_segments_per_cell loses the segment with the smallest float32 sum of squared
        permanences (ties: lower id). Destroyed ids are reused last-freed first.
        """
        cols = np.asarray(active_columns)
        if cols.ndim != 1:
            raise InvalidInput(f"active_columns must be a 1-D index array, got shape {cols.shape}")
        if cols.size and not np.issubdtype(cols.dtype, np.integer):
            # a float array (NaN included) is not an index list: casting would invent columns
            raise InvalidInput(f"active_columns must hold integer indices, got dtype {cols.dtype}")
        cfg = self.config
        cols = np.unique(cols.astype(np.int64))
        if cols.size and (cols[0] < 0 or cols[-1] >= cfg.columns):
            raise InvalidInput(f"column indices must lie in [0, {cfg.columns})")
        self.activateDendrites(learn)
        pred_cols = np.unique(self.predictive_cells // cfg.cells_per_column)
        self.anomaly = (float(cols.size - np.intersect1d(cols, pred_cols, assume_unique=True).size) / cols.size
                        if cols.size else 0.0)
        self._ensure_capacity(cols.size + 1)
        prev_active_mask = np.zeros(self.n_cells, dtype=np.bool_)
        prev_active_mask[self.active_cells] = True
        prev_winner_mask = np.zeros(self.n_cells, dtype=np.bool_)
        prev_winner_mask[self.winner_cells] = True
        f = self._f32
        self.active_cells, self.winner_cells = kern.activate_cells(
            cols, cfg.columns, cfg.cells_per_column, self._act, self._match, self._pot, prev_active_mask,
            self.winner_cells.astype(np.int64), prev_winner_mask, bool(learn), f("permanence_increment"),
            f("permanence_decrement"), f("predicted_segment_decrement"), cfg.activation_threshold,
            cfg.min_threshold, cfg.max_new_synapse_count, cfg.max_synapses_per_segment, f("initial_permanence"),
            cfg.max_segments_per_cell, cfg.tie_break == "random", self._pre, self._perm, self._seg_cell,
            self._seg_nsyn, self._seg_alive, self._cell_segs, self._cell_nseg, self._free, self._nfree,
            self._hw, self._sid, self._syn_free, self._sst, self._mt, self._mt_idx)
        self._dendrites_valid = False
        return self.winner_cells

    # ---------------------------------------------------------------- introspection
    @property
    def segments(self) -> int:
        """Segments alive."""
        return int(self._seg_alive[: self._hw[0]].sum())

    @property
    def synapses(self) -> int:
        """Synapses on the segments alive."""
        n = int(self._hw[0])
        return int(self._seg_nsyn[:n][self._seg_alive[:n]].sum())

    def segments_of_cell(self, cell: int) -> list[int]:
        return [int(s) for s in self._cell_segs[cell, : self._cell_nseg[cell]]]

    def synapses_of_segment(self, seg: int) -> tuple[np.ndarray, np.ndarray]:
        """(presynaptic cells, permanences) of a segment, in slot order."""
        n = self._seg_nsyn[seg]
        return self._pre[seg, :n].copy(), self._perm[seg, :n].copy()

    def predicted_cells(self) -> np.ndarray:
        """Cells predicted for the next step (activates the dendrites first if needed, as htm.core's
        getPredictiveCells requires)."""
        self.activateDendrites()
        return self.predictive_cells

    def createSegment(self, cell: int) -> int:
        self._ensure_capacity(1)
        return int(kern.create_segment(cell, self.config.max_segments_per_cell, self._seg_cell, self._seg_nsyn,
                                   self._seg_alive, self._cell_segs, self._cell_nseg, self._free, self._nfree,
                                   self._hw, self._pre, self._perm, self._sid, self._syn_free, self._sst))

    def add_synapse(self, seg: int, presynaptic_cell: int, permanence: float) -> None:
        """Test/inspection helper: append one synapse to a segment."""
        n = self._seg_nsyn[seg]
        if n >= self.config.max_synapses_per_segment:
            raise ValueError("segment is full")
        self._pre[seg, n] = presynaptic_cell
        self._perm[seg, n] = np.float32(permanence)
        if self._sst[1] > 0:  # the id htm.core's createSynapse would give it
            self._sst[1] -= 1
            self._sid[seg, n] = self._syn_free[self._sst[1]]
        else:
            self._sid[seg, n] = self._sst[0]
            self._sst[0] += 1
        self._seg_nsyn[seg] = n + 1
        self._dendrites_valid = False

    # ---------------------------------------------------------------- state
    def _parameters(self) -> dict[str, Any]:
        """The Temporal Memory's parameters (a subclass's extra fields left out), as a state holds them."""
        return self.config.model_dump(mode="json", include=set(TemporalMemoryConfig.model_fields))

    def state_dict(self) -> dict[str, Any]:
        """The learned segments and synapses, the sequence context, the random stream, and the
        parameters they were made with (``config``)."""
        n = int(self._hw[0])
        return {"config": self._parameters(), "hw": n,
                "pre": self._pre[:n].copy(), "perm": self._perm[:n].copy(), "sid": self._sid[:n].copy(),
                "syn_free": self._syn_free[: int(self._sst[1])].copy(), "syn_hw": int(self._sst[0]),
                "seg_cell": self._seg_cell[:n].copy(),
                "seg_nsyn": self._seg_nsyn[:n].copy(), "seg_alive": self._seg_alive[:n].copy(),
                "free": self._free[: int(self._nfree[0])].copy(), "cell_segs": self._cell_segs.copy(),
                "cell_nseg": self._cell_nseg.copy(), "mt": self._mt.copy(), "mt_idx": int(self._mt_idx[0]),
                "active": self.active_cells.copy(), "winners": self.winner_cells.copy(),
                "anomaly": float(self.anomaly)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` taken from a TM with the same parameters; a state made with
        other parameters is refused (one ValueError naming every differing one)."""
        saved, ours = st["config"], self._parameters()
        diff = [name for name, value in ours.items() if name not in saved or saved[name] != value]
        if diff:
            raise ValueError("temporal memory state made with other parameters: " + "; ".join(
                f"{name}: the state was made with {saved.get(name, '(none)')}, the config has {ours[name]}"
                for name in diff))
        n = int(st["hw"])
        self._alloc(max(1024, n))
        self._pre[:n], self._perm[:n], self._sid[:n] = st["pre"], st["perm"], st["sid"]
        syn_free = np.asarray(st["syn_free"], dtype=np.int32)
        self._syn_free[: syn_free.size] = syn_free
        self._sst[:] = (int(st["syn_hw"]), syn_free.size)
        self._seg_cell[:n], self._seg_nsyn[:n], self._seg_alive[:n] = st["seg_cell"], st["seg_nsyn"], st["seg_alive"]
        free = np.asarray(st["free"], dtype=np.int32)
        self._free[: free.size] = free
        self._nfree[0] = free.size
        self._hw[0] = n
        self._cell_segs[:] = st["cell_segs"]
        self._cell_nseg[:] = st["cell_nseg"]
        self._mt = np.asarray(st["mt"], dtype=np.uint32).copy()
        self._mt_idx = np.array([int(st["mt_idx"])], dtype=np.int64)
        self.active_cells = np.asarray(st["active"], dtype=np.int64).copy()
        self.winner_cells = np.asarray(st["winners"], dtype=np.int64).copy()
        self.anomaly = float(st["anomaly"])
        self._dendrites_valid = False
