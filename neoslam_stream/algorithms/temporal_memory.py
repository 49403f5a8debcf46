"""HTM Temporal Memory with htm.core's behaviour (written from the algorithm's description).

One step, ``compute(active_columns, learn)``:

1. **activateDendrites** (predictions of the previous step): for every segment, the number of
   active presynaptic cells on connected synapses (``conn``) and on any synapse (``pot``);
   active segments have ``conn >= activationThreshold``, matching ones ``pot >= minThreshold``;
   both sorted by (cell, segment id). Predictive cells own an active segment.
2. **anomaly** (raw): fraction of active columns without a predictive cell.
3. **activateCells**, columns in ascending order:
   * predicted active column: every cell with an active segment becomes active and winner; each
     active segment is adapted (+inc active / -dec inactive synapses) and grows
     ``maxNewSynapseCount - pot`` synapses to the previous winners;
   * bursting column: all cells active; the winner is the cell of the best matching segment
     (most active potential synapses, first in order on ties), else the previous winner cell of
     this column if any (htm.core's static-input rule), else the least-used cell (fewest segments;
     ties by lowest index in htm.core, ``tie_break="random"`` picks uniformly among the tied as
     NuPIC did). Learning adapts/grows the best matching segment, or creates a segment on the
     winner with ``min(maxNewSynapseCount, |prev winners|)`` synapses;
   * inactive column with matching segments: those segments are punished by
     ``predictedSegmentDecrement`` on their active synapses.
   Synapses whose permanence would fall below 1e-6 are destroyed after the pass, in slot order;
   a segment left with fewer than ``minThreshold`` synapses is destroyed (its synapses from the
   last slot backwards). Growth first removes the lowest-permanence synapses not onto candidates
   when the segment would exceed ``maxSynapsesPerSegment`` (ties: lower synapse id), shuffles the
   candidates when fewer are wanted than exist, and skips candidates already present (raising
   their permanence to ``initialPermanence``). A cell at ``maxSegmentsPerCell`` loses the segment
   with the smallest float32 sum of squared permanences (ties: lower id). A destroyed synapse's
   slot is filled by the segment's last synapse. Destroyed segment and synapse ids are reused
   last-freed first. Together these keep every segment's synapses, their ids and slot order equal
   to htm.core's, so the run is bit-exact (checked against htm.core's C++ on the shared trace and
   on small runs that evict, destroy and hit the synapse cap constantly: tests/test_tm_parity.py).

Random numbers come from our own MT19937 (the same stream as ``std::mt19937(seed)``), drawn as
``raw % n`` exactly where htm.core draws them: the 32-cell shuffle of the least-used-cell choice and
the candidate shuffle in growth.

Data layout: struct-of-arrays. Segments are rows of fixed-capacity synapse tables
(presynaptic cell int32, permanence float32, synapse id int32, ``maxSynapsesPerSegment`` slots),
with per-cell segment lists, LIFO free lists of segment and synapse ids, and counts in
preallocated arrays; memory grows with segments only (never with steps). The hot
loops are numba-compiled. Instead of htm.core's presynaptic index, dendrite activity is one
sequential pass over the synapse table against a dense activity mask: with NeoSLAM's sizes (a few
thousand segments, thousands of active cells while bursting) a sequential pass beats walking an
index (docs/temporal_memory.md) and needs no bookkeeping when permanences cross the connected
threshold.

Differences from htm.core's Python API: inputs and outputs are sorted numpy index arrays, not
``SDR`` objects (``getActiveCells()`` returns the ``.sparse`` equivalent); no external predictive
inputs; anomaly mode RAW only. One behavioural difference, unreachable with a positive
``permanenceIncrement`` and ``initialPermanence``: htm.core still grows synapses on a segment that
its own adaptation has just destroyed (leaving synapses on a freed segment); we skip that growth.
A matching segment keeps its >= minThreshold active synapses (they are incremented), so it is never
destroyed by its own adaptation in practice.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .errors import InvalidInput

EPS = np.float32(1e-6)


class TemporalMemoryConfig(BaseModel):
    """htm.core's TemporalMemory parameters, with htm.core's defaults."""

    model_config = ConfigDict(extra="forbid")

    columnDimensions: tuple[int, ...] = (2048,)
    cellsPerColumn: int = Field(32, ge=1)
    activationThreshold: int = Field(13, ge=0)
    initialPermanence: float = Field(0.21, ge=0, le=1)
    connectedPermanence: float = Field(0.5, ge=0, le=1)
    minThreshold: int = Field(10, ge=0)
    maxNewSynapseCount: int = Field(20, ge=0)
    permanenceIncrement: float = Field(0.1, ge=0, le=1)
    permanenceDecrement: float = Field(0.1, ge=0, le=1)
    predictedSegmentDecrement: float = Field(0.0, ge=0, le=1)
    seed: int = 42
    maxSegmentsPerCell: int = Field(255, ge=1)
    maxSynapsesPerSegment: int = Field(255, ge=1)
    tie_break: Literal["lowest", "random"] = "lowest"


# --------------------------------------------------------------------------- MT19937

@njit(cache=True)
def _mt_seed(seed):  # pragma: no cover - compiled
    mt = np.zeros(624, dtype=np.uint32)
    mt[0] = np.uint32(seed & 0xFFFFFFFF)
    for i in range(1, 624):
        prev = np.uint64(mt[i - 1])
        mt[i] = np.uint32((np.uint64(1812433253) * (prev ^ (prev >> np.uint64(30))) + np.uint64(i))
                          & np.uint64(0xFFFFFFFF))
    return mt


@njit(cache=True)
def _mt_next(mt, idx):  # pragma: no cover - compiled
    """One raw 32-bit output; ``idx`` is a 1-element array holding the position."""
    if idx[0] >= 624:
        for i in range(624):
            y = (mt[i] & np.uint32(0x80000000)) | (mt[(i + 1) % 624] & np.uint32(0x7FFFFFFF))
            v = mt[(i + 397) % 624] ^ (y >> np.uint32(1))
            if y & np.uint32(1):
                v ^= np.uint32(0x9908B0DF)
            mt[i] = v
        idx[0] = 0
    y = mt[idx[0]]
    idx[0] += 1
    y ^= y >> np.uint32(11)
    y ^= (y << np.uint32(7)) & np.uint32(0x9D2C5680)
    y ^= (y << np.uint32(15)) & np.uint32(0xEFC60000)
    y ^= y >> np.uint32(18)
    return y


@njit(cache=True)
def _shuffle(arr, mt, idx):  # pragma: no cover - compiled
    """htm.core's Fisher-Yates from the back: swap i with raw % (i+1)."""
    for i in range(arr.shape[0] - 1, 0, -1):
        j = np.int64(_mt_next(mt, idx) % np.uint32(i + 1))
        t = arr[i]
        arr[i] = arr[j]
        arr[j] = t


# --------------------------------------------------------------------------- segments and synapses
#
# Synapses carry a global id (``sid``) drawn like htm.core's: the last freed id first, else a new
# one. The ids break ties when the synapse cap removes the weakest synapses, and the order in which
# synapses are destroyed (hence the free list, hence later ids and slot orders) follows htm.core's
# rules, so segments hold the same synapses in the same slot order as htm.core's.
# ``sst`` = [synapse id high-water mark, free synapse ids].

@njit(cache=True)
def _free_synapse_at(s, k, pre, perm, sid, seg_nsyn, syn_free, sst):  # pragma: no cover
    """Destroy the synapse in slot ``k`` of segment ``s``: the last slot moves into its place."""
    syn_free[sst[1]] = sid[s, k]
    sst[1] += 1
    last = seg_nsyn[s] - 1
    pre[s, k] = pre[s, last]
    perm[s, k] = perm[s, last]
    sid[s, k] = sid[s, last]
    seg_nsyn[s] = last


@njit(cache=True)
def _free_synapse_id(s, syn_id, pre, perm, sid, seg_nsyn, syn_free, sst):  # pragma: no cover
    for k in range(seg_nsyn[s]):
        if sid[s, k] == syn_id:
            _free_synapse_at(s, k, pre, perm, sid, seg_nsyn, syn_free, sst)
            return


@njit(cache=True)
def _destroy_segment(s, seg_cell, seg_nsyn, seg_alive, cell_segs, cell_nseg, free, nfree,
                     pre, perm, sid, syn_free, sst):  # pragma: no cover
    c = seg_cell[s]
    n = cell_nseg[c]
    for i in range(n):
        if cell_segs[c, i] == s:
            for j in range(i, n - 1):  # keep the cell's list in creation order
                cell_segs[c, j] = cell_segs[c, j + 1]
            cell_nseg[c] = n - 1
            break
    while seg_nsyn[s] > 0:  # synapses go from the last slot backwards
        _free_synapse_at(s, seg_nsyn[s] - 1, pre, perm, sid, seg_nsyn, syn_free, sst)
    seg_alive[s] = False
    free[nfree[0]] = s
    nfree[0] += 1


@njit(cache=True)
def _adapt(s, active_mask, inc, dec, min_threshold, pre, perm, sid, seg_nsyn, seg_cell, seg_alive,
           cell_segs, cell_nseg, free, nfree, syn_free, sst, doomed):  # pragma: no cover
    """adaptSegment: +inc on active, -dec on inactive synapses (clamped to 1); a synapse that would
    fall below epsilon is destroyed after the pass, in slot order; a segment left with fewer than
    minThreshold synapses is destroyed. Returns True when the segment was destroyed.
    ``doomed`` is scratch space of maxSynapsesPerSegment ids (no allocation per call)."""
    n = seg_nsyn[s]
    nd = 0
    for i in range(n):
        if active_mask[pre[s, i]]:
            p = perm[s, i] + inc
        else:
            p = perm[s, i] - dec
        if p < EPS:
            doomed[nd] = sid[s, i]
            nd += 1
            continue
        if p > np.float32(1.0):
            p = np.float32(1.0)
        perm[s, i] = p
    for j in range(nd):
        _free_synapse_id(s, doomed[j], pre, perm, sid, seg_nsyn, syn_free, sst)
    if seg_nsyn[s] < min_threshold:
        _destroy_segment(s, seg_cell, seg_nsyn, seg_alive, cell_segs, cell_nseg, free, nfree,
                         pre, perm, sid, syn_free, sst)
        return True
    return False


@njit(cache=True)
def _grow(s, cands, cand_mask, max_new, max_syn, init_perm, pre, perm, sid, seg_nsyn, syn_free, sst,
          mt, idx):  # pragma: no cover
    """growSynapses towards ``cands`` (the previous winners, sorted)."""
    n_actual = min(max_new, cands.shape[0])
    overrun = seg_nsyn[s] + n_actual - max_syn
    if overrun > 0:
        # make room: the weakest synapses not onto a candidate, ties by lower synapse id
        n = seg_nsyn[s]
        keys = np.empty(n, dtype=np.float64)
        ids = np.empty(n, dtype=np.int32)
        m = 0
        for i in range(n):
            if not cand_mask[pre[s, i]]:
                keys[m] = perm[s, i]
                ids[m] = sid[s, i]
                m += 1
        order = np.arange(m)
        for a in range(1, m):  # insertion sort by (permanence, id); m <= maxSynapsesPerSegment
            b = a
            while b > 0 and (keys[order[b]] < keys[order[b - 1]]
                             or (keys[order[b]] == keys[order[b - 1]] and ids[order[b]] < ids[order[b - 1]])):
                t = order[b]
                order[b] = order[b - 1]
                order[b - 1] = t
                b -= 1
        for j in range(min(overrun, m)):
            _free_synapse_id(s, ids[order[j]], pre, perm, sid, seg_nsyn, syn_free, sst)
    n_actual = min(n_actual, max_syn - seg_nsyn[s])
    if n_actual <= 0:
        return
    picks = cands.copy()
    if max_new < cands.shape[0]:
        _shuffle(picks, mt, idx)
    target = seg_nsyn[s] + n_actual
    for c in picks:
        if seg_nsyn[s] >= target:
            break
        found = -1
        for i in range(seg_nsyn[s]):
            if pre[s, i] == c:
                found = i
                break
        if found >= 0:  # no duplicate synapse; the existing one is raised to initialPermanence
            if perm[s, found] < init_perm:
                perm[s, found] = init_perm
            continue
        k = seg_nsyn[s]
        pre[s, k] = c
        perm[s, k] = init_perm
        if sst[1] > 0:
            sst[1] -= 1
            sid[s, k] = syn_free[sst[1]]
        else:
            sid[s, k] = sst[0]
            sst[0] += 1
        seg_nsyn[s] = k + 1


@njit(cache=True)
def _create_segment(cell, max_seg, seg_cell, seg_nsyn, seg_alive, cell_segs, cell_nseg, free, nfree,
                    hw, pre, perm, sid, syn_free, sst):  # pragma: no cover
    while cell_nseg[cell] >= max_seg:
        # evict the least useful segment: smallest float32 sum of squared permanences, ties by lower id
        victim = -1
        best = np.float32(0.0)
        for i in range(cell_nseg[cell]):
            s = cell_segs[cell, i]
            acc = np.float32(0.0)
            for j in range(seg_nsyn[s]):
                acc += perm[s, j] * perm[s, j]
            if victim == -1 or acc < best or (acc == best and s < victim):
                victim = s
                best = acc
        _destroy_segment(victim, seg_cell, seg_nsyn, seg_alive, cell_segs, cell_nseg, free, nfree,
                         pre, perm, sid, syn_free, sst)
    if nfree[0] > 0:
        nfree[0] -= 1
        s = free[nfree[0]]
    else:
        s = hw[0]
        hw[0] += 1
    seg_cell[s] = cell
    seg_nsyn[s] = 0
    seg_alive[s] = True
    cell_segs[cell, cell_nseg[cell]] = s
    cell_nseg[cell] += 1
    return s


# --------------------------------------------------------------------------- one step

@njit(cache=True)
def _activate_dendrites(active_mask, pre, perm, seg_nsyn, seg_alive, seg_cell, hw, conn_thr,
                        act_thr, min_thr, n_cells_total):  # pragma: no cover
    n = hw[0]
    pot = np.zeros(n, dtype=np.int32)
    nact = 0
    nmatch = 0
    act_buf = np.empty(n, dtype=np.int64)
    match_buf = np.empty(n, dtype=np.int64)
    for s in range(n):
        if not seg_alive[s]:
            continue
        c_conn = 0
        c_pot = 0
        for i in range(seg_nsyn[s]):
            if active_mask[pre[s, i]]:
                c_pot += 1
                if perm[s, i] >= conn_thr:
                    c_conn += 1
        pot[s] = c_pot
        key = np.int64(seg_cell[s]) * np.int64(n + 1) + s  # sort by (cell, segment id)
        if c_conn >= act_thr:
            act_buf[nact] = key
            nact += 1
        if c_pot >= min_thr:
            match_buf[nmatch] = key
            nmatch += 1
    act_keys = np.sort(act_buf[:nact])
    match_keys = np.sort(match_buf[:nmatch])
    act = act_keys % np.int64(n + 1)
    match = match_keys % np.int64(n + 1)
    return act, match, pot


@njit(cache=True)
def _activate_cells(active_cols, n_cols, K, act, match, pot, prev_active_mask, prev_winners,
                    prev_winner_mask, learn, inc, dec, psd, act_thr, min_thr, max_new, max_syn,
                    init_perm, max_seg, tie_random, pre, perm, seg_cell, seg_nsyn, seg_alive, cell_segs,
                    cell_nseg, free, nfree, hw, sid, syn_free, sst, mt, idx):  # pragma: no cover
    col_active = np.zeros(n_cols, dtype=np.bool_)
    for c in active_cols:
        col_active[c] = True
    out_active = np.empty(active_cols.shape[0] * K, dtype=np.int64)
    out_winner = np.empty(active_cols.shape[0] * K, dtype=np.int64)
    na = 0
    nw = 0
    ia = 0
    im = 0
    n_act = act.shape[0]
    n_match = match.shape[0]
    order = np.arange(K, dtype=np.int64)
    doomed = np.empty(max_syn, dtype=np.int32)
    for col in range(n_cols):
        a0 = ia
        while ia < n_act and seg_cell[act[ia]] // K == col:
            ia += 1
        m0 = im
        while im < n_match and seg_cell[match[im]] // K == col:
            im += 1
        if col_active[col]:
            if ia > a0:  # predicted column
                last_cell = -1
                for j in range(a0, ia):
                    s = act[j]
                    cell = seg_cell[s]
                    if cell != last_cell:
                        out_active[na] = cell
                        na += 1
                        out_winner[nw] = cell
                        nw += 1
                        last_cell = cell
                    if learn:
                        n_grow = max_new - pot[s]
                        gone = _adapt(s, prev_active_mask, inc, dec, min_thr, pre, perm, sid, seg_nsyn,
                                      seg_cell, seg_alive, cell_segs, cell_nseg, free, nfree, syn_free, sst,
                                      doomed)
                        if n_grow > 0 and not gone:
                            _grow(s, prev_winners, prev_winner_mask, n_grow, max_syn, init_perm, pre, perm,
                                  sid, seg_nsyn, syn_free, sst, mt, idx)
            else:  # burst
                for k in range(K):
                    out_active[na] = col * K + k
                    na += 1
                best = -1
                if im > m0:
                    for j in range(m0, im):
                        if best == -1 or pot[match[j]] > pot[best]:
                            best = match[j]
                    winner = seg_cell[best]
                else:
                    winner = -1
                    for k in range(K):  # htm.core: keep the previous winner of a static input
                        if prev_winner_mask[col * K + k]:
                            winner = col * K + k
                            break
                    if winner == -1:
                        if K > 1:
                            _shuffle(order, mt, idx)  # htm.core draws these even though ties go to the lowest
                        fewest = 1 << 30
                        for k in range(K):
                            if cell_nseg[col * K + k] < fewest:
                                fewest = cell_nseg[col * K + k]
                        if tie_random:
                            nt = 0
                            for k in range(K):
                                if cell_nseg[col * K + k] == fewest:
                                    nt += 1
                            pick = np.int64(_mt_next(mt, idx) % np.uint32(nt))
                            for k in range(K):
                                if cell_nseg[col * K + k] == fewest:
                                    if pick == 0:
                                        winner = col * K + k
                                        break
                                    pick -= 1
                        else:
                            for k in range(K):
                                if cell_nseg[col * K + k] == fewest:
                                    winner = col * K + k
                                    break
                out_winner[nw] = winner
                nw += 1
                if learn:
                    if best >= 0:
                        n_grow = max_new - pot[best]
                        gone = _adapt(best, prev_active_mask, inc, dec, min_thr, pre, perm, sid, seg_nsyn,
                                      seg_cell, seg_alive, cell_segs, cell_nseg, free, nfree, syn_free, sst,
                                      doomed)
                        if n_grow > 0 and not gone:
                            _grow(best, prev_winners, prev_winner_mask, n_grow, max_syn, init_perm, pre, perm,
                                  sid, seg_nsyn, syn_free, sst, mt, idx)
                    else:
                        n_new = min(max_new, prev_winners.shape[0])
                        if n_new > 0:
                            s = _create_segment(winner, max_seg, seg_cell, seg_nsyn, seg_alive, cell_segs,
                                                cell_nseg, free, nfree, hw, pre, perm, sid, syn_free, sst)
                            _grow(s, prev_winners, prev_winner_mask, n_new, max_syn, init_perm, pre, perm,
                                  sid, seg_nsyn, syn_free, sst, mt, idx)
        elif learn and psd > 0:
            for j in range(m0, im):
                s = match[j]
                if seg_alive[s]:
                    _adapt(s, prev_active_mask, -psd, np.float32(0.0), min_thr, pre, perm, sid, seg_nsyn,
                           seg_cell, seg_alive, cell_segs, cell_nseg, free, nfree, syn_free, sst, doomed)
    return out_active[:na], out_winner[:nw]


# --------------------------------------------------------------------------- the class

class TemporalMemory:
    """htm.core-compatible Temporal Memory (see the module docstring)."""

    def __init__(self, config: TemporalMemoryConfig | None = None, **overrides: Any) -> None:
        """``TemporalMemory(config)``, or htm.core's keyword arguments
        (``TemporalMemory(columnDimensions=(2048,), cellsPerColumn=32, ...)``); the parameters
        and their defaults (htm.core's) are :class:`TemporalMemoryConfig`'s."""
        if isinstance(overrides.get("columnDimensions"), int):
            overrides["columnDimensions"] = (overrides["columnDimensions"],)
        cfg = make_config(TemporalMemoryConfig, config, overrides)
        dims = tuple(cfg.columnDimensions)
        if cfg.minThreshold > cfg.activationThreshold:
            raise ValueError("minThreshold must be <= activationThreshold (as htm.core requires)")
        self.config = cfg
        self.n_cols = int(np.prod(dims))
        self.K = cfg.cellsPerColumn
        self.n_cells = self.n_cols * self.K
        self._f32 = {k: np.float32(getattr(cfg, k)) for k in (
            "initialPermanence", "connectedPermanence", "permanenceIncrement", "permanenceDecrement",
            "predictedSegmentDecrement")}
        self._conn_thr = np.float32(self._f32["connectedPermanence"] - EPS)
        self._alloc(1024)
        self._mt = _mt_seed(np.uint32(cfg.seed))
        self._mt_idx = np.array([624], dtype=np.int64)
        self.reset()
        self._dendrites_valid = False
        self._act = np.zeros(0, np.int64)
        self._match = np.zeros(0, np.int64)
        self._pot = np.zeros(0, np.int32)
        self.anomaly = -1.0

    # ---------------------------------------------------------------- storage
    def _alloc(self, cap: int) -> None:
        S = self.config.maxSynapsesPerSegment
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
        self._cell_segs = np.zeros((self.n_cells, self.config.maxSegmentsPerCell), dtype=np.int32)
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
        syn_free = np.zeros(new * self.config.maxSynapsesPerSegment, dtype=np.int32)
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
        self._act, self._match, self._pot = _activate_dendrites(
            mask, self._pre, self._perm, self._seg_nsyn, self._seg_alive, self._seg_cell, self._hw,
            self._conn_thr, cfg.activationThreshold, cfg.minThreshold, self.n_cells)
        self.predictive_cells = np.unique(self._seg_cell[self._act].astype(np.int64))
        self._dendrites_valid = True

    def compute(self, active_columns: np.ndarray, learn: bool = True) -> np.ndarray:
        """One time step; returns the winner cells (sorted int64 indices)."""
        cols = np.asarray(active_columns)
        if cols.ndim != 1:
            raise InvalidInput(f"active_columns must be a 1-D index array, got shape {cols.shape}")
        if cols.size and not np.issubdtype(cols.dtype, np.integer):
            # a float array (NaN included) is not an index list: casting would invent columns
            raise InvalidInput(f"active_columns must hold integer indices, got dtype {cols.dtype}")
        cols = np.unique(cols.astype(np.int64))
        if cols.size and (cols[0] < 0 or cols[-1] >= self.n_cols):
            raise InvalidInput(f"column indices must lie in [0, {self.n_cols})")
        self.activateDendrites(learn)
        pred_cols = np.unique(self.predictive_cells // self.K)
        self.anomaly = (float(cols.size - np.intersect1d(cols, pred_cols, assume_unique=True).size) / cols.size
                        if cols.size else 0.0)
        self._ensure_capacity(cols.size + 1)
        prev_active_mask = np.zeros(self.n_cells, dtype=np.bool_)
        prev_active_mask[self.active_cells] = True
        prev_winner_mask = np.zeros(self.n_cells, dtype=np.bool_)
        prev_winner_mask[self.winner_cells] = True
        cfg = self.config
        f = self._f32
        self.active_cells, self.winner_cells = _activate_cells(
            cols, self.n_cols, self.K, self._act, self._match, self._pot, prev_active_mask,
            self.winner_cells.astype(np.int64), prev_winner_mask, bool(learn), f["permanenceIncrement"],
            f["permanenceDecrement"], f["predictedSegmentDecrement"], cfg.activationThreshold,
            cfg.minThreshold, cfg.maxNewSynapseCount, cfg.maxSynapsesPerSegment, f["initialPermanence"],
            cfg.maxSegmentsPerCell, cfg.tie_break == "random", self._pre, self._perm, self._seg_cell,
            self._seg_nsyn, self._seg_alive, self._cell_segs, self._cell_nseg, self._free, self._nfree,
            self._hw, self._sid, self._syn_free, self._sst, self._mt, self._mt_idx)
        self._dendrites_valid = False
        return self.winner_cells

    # ---------------------------------------------------------------- introspection
    def numberOfSegments(self) -> int:
        return int(self._seg_alive[: self._hw[0]].sum())

    def numberOfSynapses(self) -> int:
        n = int(self._hw[0])
        return int(self._seg_nsyn[:n][self._seg_alive[:n]].sum())

    @property
    def segments(self) -> int:
        return self.numberOfSegments()

    @property
    def synapses(self) -> int:
        return self.numberOfSynapses()

    def segments_of_cell(self, cell: int) -> list[int]:
        return [int(s) for s in self._cell_segs[cell, : self._cell_nseg[cell]]]

    def synapses_of_segment(self, seg: int) -> tuple[np.ndarray, np.ndarray]:
        """(presynaptic cells, permanences) of a segment, in slot order."""
        n = self._seg_nsyn[seg]
        return self._pre[seg, :n].copy(), self._perm[seg, :n].copy()

    # htm.core-style names
    def getActiveCells(self) -> np.ndarray:
        return self.active_cells

    def getWinnerCells(self) -> np.ndarray:
        return self.winner_cells

    def getPredictiveCells(self) -> np.ndarray:
        """Cells predicted for the next step (runs activateDendrites if needed, as htm.core requires)."""
        self.activateDendrites()
        return self.predictive_cells

    def numberOfCells(self) -> int:
        return self.n_cells

    def numberOfColumns(self) -> int:
        return self.n_cols

    def getCellsPerColumn(self) -> int:
        return self.K

    def columnForCell(self, cell: int) -> int:
        return int(cell) // self.K

    def cellsForColumn(self, col: int) -> np.ndarray:
        return np.arange(col * self.K, (col + 1) * self.K, dtype=np.uint32)

    def createSegment(self, cell: int) -> int:
        self._ensure_capacity(1)
        return int(_create_segment(cell, self.config.maxSegmentsPerCell, self._seg_cell, self._seg_nsyn,
                                   self._seg_alive, self._cell_segs, self._cell_nseg, self._free, self._nfree,
                                   self._hw, self._pre, self._perm, self._sid, self._syn_free, self._sst))

    def add_synapse(self, seg: int, presynaptic_cell: int, permanence: float) -> None:
        """Test/inspection helper: append one synapse to a segment."""
        n = self._seg_nsyn[seg]
        if n >= self.config.maxSynapsesPerSegment:
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
    def state_dict(self) -> dict[str, Any]:
        n = int(self._hw[0])
        return {"config": self.config.model_dump(mode="json"), "hw": n,
                "pre": self._pre[:n].copy(), "perm": self._perm[:n].copy(), "sid": self._sid[:n].copy(),
                "syn_free": self._syn_free[: int(self._sst[1])].copy(), "syn_hw": int(self._sst[0]),
                "seg_cell": self._seg_cell[:n].copy(),
                "seg_nsyn": self._seg_nsyn[:n].copy(), "seg_alive": self._seg_alive[:n].copy(),
                "free": self._free[: int(self._nfree[0])].copy(), "cell_segs": self._cell_segs.copy(),
                "cell_nseg": self._cell_nseg.copy(), "mt": self._mt.copy(), "mt_idx": int(self._mt_idx[0]),
                "active": self.active_cells.copy(), "winners": self.winner_cells.copy(),
                "anomaly": float(self.anomaly)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` taken from a TM with the same configuration."""
        saved = TemporalMemoryConfig(**st["config"])
        if saved != self.config:
            diff = {k: (v, getattr(self.config, k)) for k, v in saved if v != getattr(self.config, k)}
            raise ValueError(f"state was saved with another configuration (saved, ours): {diff}")
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
