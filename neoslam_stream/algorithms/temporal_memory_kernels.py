"""The numba kernels of the Temporal Memory (:mod:`.temporal_memory`), on arrays it owns.

Our own MT19937 (the stream of ``std::mt19937(seed)``); segment and synapse bookkeeping with
htm.core's rules (synapse ids, destruction order, eviction, growth); and one step's
activateDendrites and activateCells.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: permanences below this are destroyed (htm.core's epsilon)
EPS = np.float32(1e-6)


# --------------------------------------------------------------------------- MT19937

@njit(cache=True)
def mt_seed(seed):  # pragma: no cover - compiled
    mt = np.zeros(624, dtype=np.uint32)
    mt[0] = np.uint32(seed & 0xFFFFFFFF)
    for i in range(1, 624):
        prev = np.uint64(mt[i - 1])
        mt[i] = np.uint32((np.uint64(1812433253) * (prev ^ (prev >> np.uint64(30))) + np.uint64(i))
                          & np.uint64(0xFFFFFFFF))
    return mt


@njit(cache=True)
def mt_next(mt, idx):  # pragma: no cover - compiled
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
        j = np.int64(mt_next(mt, idx) % np.uint32(i + 1))
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
    min_threshold synapses is destroyed. Returns True when the segment was destroyed.
    ``doomed`` is scratch space of max_synapses_per_segment ids (no allocation per call)."""
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
        for a in range(1, m):  # insertion sort by (permanence, id); m <= max_synapses_per_segment
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
        if found >= 0:  # no duplicate synapse; the existing one is raised to initial_permanence
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
def create_segment(cell, max_seg, seg_cell, seg_nsyn, seg_alive, cell_segs, cell_nseg, free, nfree,
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
def activate_dendrites(active_mask, pre, perm, seg_nsyn, seg_alive, seg_cell, hw, conn_thr,
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
def activate_cells(active_cols, n_cols, K, act, match, pot, prev_active_mask, prev_winners,
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
                            pick = np.int64(mt_next(mt, idx) % np.uint32(nt))
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
                            s = create_segment(winner, max_seg, seg_cell, seg_nsyn, seg_alive, cell_segs,
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
