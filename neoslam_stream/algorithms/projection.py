"""Stage B's matrix and kernels: the random projection d = f P in each of its storages.

P (n x 1024) holds seeded i.i.d. N(0, 1) float32 draws, generated row chunk by row chunk (no
float64 or second full-size copy ever exists) and kept transposed, (n, 1024), as the ROS 2
NeoSLAM's ``randomMatrix.bin`` holds it. Storages: float32 (the reference); binary16 bit patterns
widened exactly where they are read (float32 sums); int8 q = rint(P / s_P) with features rounded
to 16-bit integers and summed exactly in integers, or to 7 bits per frame for torch's quantised
int8 kernels. Every kernel sums in an order fixed by n alone, so a frame's bits never depend on
its batch or the thread count. ``sparse_matrix`` is Li et al.'s very sparse projection.
Details and measurements: docs/frontend.md, docs/performance.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic, overload

N_PROJ = 1024
N_BITS = 2 * N_PROJ
_CHUNK_ROWS = 4096


def _chunks(n: int):
    """(start, stop) of P's row chunks of at most _CHUNK_ROWS rows."""
    for start in range(0, n, _CHUNK_ROWS):
        yield start, min(n, start + _CHUNK_ROWS)


def _gaussian_chunks(n: int, seed: int, m: int, into: np.ndarray | None = None):
    """P's seeded N(0, 1) float32 draws, row chunk by row chunk: (start, stop, chunk). The chunks
    are written into ``into`` (n, m) float32 when given, else into one reused buffer (no full-size
    float32 array exists then)."""
    rng = np.random.default_rng(seed)
    buf = np.empty((min(n, _CHUNK_ROWS), m), dtype=np.float32) if into is None else None
    for start, stop in _chunks(n):
        chunk = into[start:stop] if buf is None else buf[: stop - start]
        rng.standard_normal((stop - start, m), dtype=np.float32, out=chunk)
        yield start, stop, chunk


def gaussian_matrix(n: int, seed: int, m: int = N_PROJ, half: bool = False) -> np.ndarray:
    """(n, m) float32 N(0,1), filled row chunk by row chunk from one seeded stream.

    ``half``: the same draws rounded to binary16, returned as their uint16 bit patterns (see
    :func:`to_half_bits`), built chunk by chunk so no float32 copy of P ever exists.
    """
    if not half:
        out = np.empty((n, m), dtype=np.float32)
        for _ in _gaussian_chunks(n, seed, m, into=out):
            pass
        return out
    out = np.empty((n, m), dtype=np.uint16)
    for start, stop, chunk in _gaussian_chunks(n, seed, m):
        out[start:stop] = chunk.astype(np.float16).view(np.uint16)
    return out


#: features are rounded to integers of at most this magnitude for the int8 kernel (16 bits)
FEATURE_LEVELS = 32767
#: the int8 matrix's entries lie in [-MATRIX_LEVELS, MATRIX_LEVELS]
MATRIX_LEVELS = 127
#: rows of P summed in int32 before the int64 total: |x q| <= 32767 * 127 per row, so 256 rows
#: stay below 2^31 (1.07e9 < 2.15e9) whatever the data
_INT_BLOCK = 256


def _quantise_chunks(chunks: Any, shape: tuple[int, int]) -> tuple[np.ndarray, float]:
    """(q int8, s_P) with q = rint(P / s_P), s_P = max|P| / 127, from P's row chunks; ``chunks()``
    gives them (start, stop, rows) anew, and is called twice: once for max|P|, once to round."""
    peak = 0.0
    for _, _, rows in chunks():
        peak = max(peak, float(np.max(np.abs(rows), initial=0.0)))
    scale = peak / MATRIX_LEVELS if peak > 0 else 1.0
    out = np.empty(shape, dtype=np.int8)
    for start, stop, rows in chunks():
        out[start:stop] = np.rint(np.asarray(rows, dtype=np.float64) / scale)
    return out, scale


def quantise_int8(matrix: np.ndarray) -> tuple[np.ndarray, float]:
    """(q int8, s_P) of a float32 P (no full-size temporary; ``matrix`` may be a memory map of a
    ``.bin`` file)."""
    return _quantise_chunks(lambda: ((a, b, matrix[a:b]) for a, b in _chunks(matrix.shape[0])), matrix.shape)


def gaussian_matrix_int8(n: int, seed: int, m: int = N_PROJ) -> tuple[np.ndarray, float]:
    """:func:`gaussian_matrix`'s draws quantised like :func:`quantise_int8`, generated twice from
    the same seeded stream so no float32 copy of P ever exists."""
    return _quantise_chunks(lambda: _gaussian_chunks(n, seed, m), (n, m))


def quantise_features(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x int32 (b, n), s_f (b,) float64): x = rint(f / s_f), s_f = max|f| / 32767 per row (a zero
    row gives x = 0, s_f = 0). Row by row, so a frame's x does not depend on its batch."""
    f = np.asarray(rows, dtype=np.float64)
    peak = np.max(np.abs(f), axis=1)
    scale = peak / FEATURE_LEVELS
    safe = np.where(scale > 0, scale, 1.0)
    return np.rint(f / safe[:, None]).astype(np.int32), scale


def half_bits_to_float32(bits: np.ndarray) -> np.ndarray:
    """float32 values of binary16 bit patterns (exact: every half is a float32)."""
    return np.asarray(bits, dtype=np.uint16).view(np.float16).astype(np.float32)


def to_half_bits(matrix: np.ndarray) -> np.ndarray:
    """IEEE binary16 bit patterns (uint16) of a float32 matrix, round to nearest even, converted row
    chunk by row chunk (no full-size temporary). numba has no float16 type on the CPU, so the
    kernel reads these bits and widens them itself (:func:`_widen`)."""
    out = np.empty(matrix.shape, dtype=np.uint16)
    for start, stop in _chunks(matrix.shape[0]):
        out[start:stop] = np.asarray(matrix[start:stop], dtype=np.float32).astype(np.float16).view(np.uint16)
    return out



def sparse_matrix(n: int, seed: int, m: int = N_PROJ) -> Any:
    """Very sparse random projection (n, m): entries +-sqrt(1/density) with density 1/sqrt(n)."""
    import scipy.sparse as sp

    density = 1.0 / np.sqrt(n)
    rng = np.random.default_rng(seed)
    rows_l, cols_l = [], []
    for j in range(m):  # column by column: no (n, m) temporary
        k = rng.binomial(n, density)
        rows_l.append(rng.choice(n, size=k, replace=False))
        cols_l.append(np.full(k, j))
    rows, cols = np.concatenate(rows_l), np.concatenate(cols_l)
    nnz = rows.size
    vals = np.where(rng.random(nnz) < 0.5, -1.0, 1.0).astype(np.float32) * np.float32(np.sqrt(1.0 / density))
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, m), dtype=np.float32)


#: W's rows are summed in this many fixed halves (one per thread at most); a constant, not the
#: thread count, so the bits do not depend on how many threads a deployment gives B.
PROJECTION_CHUNKS = 2


@intrinsic
def _half_to_float(typingctx, h):  # pragma: no cover - compiled
    """float32 value of one binary16 bit pattern (uint16): LLVM's exact ``fpext half -> float``.

    numba has no float16 type on the CPU; this lowers to the F16C instruction ``vcvtph2ps`` where
    the CPU has it (vectorised with the loop), else to the compiler runtime's exact conversion.
    """
    if h != types.uint16:
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(types.uint16), codegen


def _widen(w):
    """The float32 value of one stored entry of P: float32 as it is, a binary16 bit pattern
    (uint16, ``projector.matrix_dtype: float16``) widened exactly. In compiled code the overload
    below picks the branch at compile time, so each storage gets its own specialisation of
    :func:`project_rows`."""
    if isinstance(w, np.uint16):
        return np.float32(np.array(w, np.uint16).view(np.float16))
    return np.float32(w)


@overload(_widen)
def _widen_compiled(w):  # pragma: no cover - compiled
    if isinstance(w, types.Float):
        return lambda w: w
    if w == types.uint16:
        return lambda w: _half_to_float(w)
    return None


@njit(cache=True)
def _sum_chunks(part, out):  # pragma: no cover - compiled
    """out[r, j] = the sum over chunks c of part[c, r, j], in chunk order (a fixed order)."""
    for r in range(part.shape[1]):
        for j in range(part.shape[2]):
            total = part[0, r, j]
            for c in range(1, part.shape[0]):
                total += part[c, r, j]
            out[r, j] = total


@njit(parallel=True, cache=True)
def project_rows(F, W, out):  # pragma: no cover - compiled
    """out[r] = F[r] @ W with a summation order that depends on nothing but n.

    BLAS rounds a matrix-vector product differently from a matrix-matrix one, so a frame's bits
    would depend on how many frames were batched with it; here every output element is the sum of
    PROJECTION_CHUNKS partial sums over fixed row ranges of W, each accumulated four rows at a time
    in order, so results are identical for any batch size and thread count (lossless runs are
    repeatable). The product is bound by memory bandwidth (all of W per pass): each block of four
    rows of W is read once for the whole batch (micro-batching amortises it), and the two halves
    run on two threads when B has them. W is float32, or binary16 bit patterns (uint16,
    ``matrix_dtype: float16``) widened exactly where they are read (:func:`_widen`): the output is
    then that of the float32 matrix ``W as float16 -> float32`` bit for bit, from half the bytes.
    """
    n, m = W.shape
    b = F.shape[0]
    nchunk = PROJECTION_CHUNKS
    step = ((n + nchunk - 1) // nchunk + 3) // 4 * 4
    part = np.zeros((nchunk, b, m), np.float32)
    for c in prange(nchunk):
        lo = c * step
        hi = min(n, (c + 1) * step)
        i = lo
        while i + 4 <= hi:
            w0 = W[i]
            w1 = W[i + 1]
            w2 = W[i + 2]
            w3 = W[i + 3]
            for r in range(b):
                acc = part[c, r]
                a0 = F[r, i]
                a1 = F[r, i + 1]
                a2 = F[r, i + 2]
                a3 = F[r, i + 3]
                for j in range(m):
                    acc[j] += ((a0 * _widen(w0[j]) + a1 * _widen(w1[j]))
                               + (a2 * _widen(w2[j]) + a3 * _widen(w3[j])))
            i += 4
        while i < hi:
            w0 = W[i]
            for r in range(b):
                acc = part[c, r]
                a0 = F[r, i]
                for j in range(m):
                    acc[j] += a0 * _widen(w0[j])
            i += 1
    _sum_chunks(part, out)


@njit(parallel=True, cache=True)
def project_rows_int8(X, Q, out):  # pragma: no cover - compiled
    """out[r] = X[r] @ Q exactly (int64), for X int32 with |x| <= 32767 and Q int8 with |q| <= 127.

    Each of PROJECTION_CHUNKS row ranges (one per thread at most) accumulates two rows of Q at a
    time in int32 over blocks of _INT_BLOCK rows (no overflow: see _INT_BLOCK), then adds the block
    to an int64 total. Integer sums are exact, so the result is the same for any order, batch
    size and thread count.
    """
    n, m = Q.shape
    b = X.shape[0]
    nchunk = PROJECTION_CHUNKS
    step = (n + nchunk - 1) // nchunk
    part = np.zeros((nchunk, b, m), np.int64)
    for c in prange(nchunk):
        lo = c * step
        hi = min(n, (c + 1) * step)
        acc = np.zeros((b, m), np.int32)
        i = lo
        while i < hi:
            top = min(hi, i + _INT_BLOCK)
            while i + 2 <= top:
                q0 = Q[i]
                q1 = Q[i + 1]
                for r in range(b):  # each pair of rows of Q is read once for the whole batch
                    a = acc[r]
                    x0 = X[r, i]
                    x1 = X[r, i + 1]
                    for j in range(m):
                        a[j] += x0 * np.int32(q0[j]) + x1 * np.int32(q1[j])
                i += 2
            if i < top:
                q0 = Q[i]
                for r in range(b):
                    a = acc[r]
                    x0 = X[r, i]
                    for j in range(m):
                        a[j] += x0 * np.int32(q0[j])
                i += 1
            for r in range(b):
                total = part[c, r]
                a = acc[r]
                for j in range(m):
                    total[j] += a[j]
                    a[j] = 0
    _sum_chunks(part, out)


@njit(cache=True)
def slsbh_rows(D, k, out):  # pragma: no cover - compiled
    """sLSBH of every row of D into out (b, 2k), the same rule as :func:`.projector.slsbh`."""
    m = D.shape[1]
    for r in range(D.shape[0]):
        desc = np.argsort(-D[r], kind="mergesort")[:k]
        asc = np.argsort(D[r], kind="mergesort")[:k]
        out[r, :k] = np.sort(desc)
        out[r, k:] = np.sort(asc) + m


class QuantisedLinear:
    """x q with torch's dynamically quantised int8 linear layer (``feature_bits: 7``), one frame per
    call: the per-frame feature quantisation (7 bits, zero point) is then a function of that frame
    alone. fbgemm packs its own copy of q for its int8 kernels."""

    def __init__(self, q: np.ndarray, scale: float) -> None:
        import warnings

        import torch

        if not hasattr(torch.ops.quantized, "linear_dynamic"):
            raise RuntimeError(f"torch {torch.__version__} has no quantised linear kernels (needed by "
                               "projector.feature_bits 7); use feature_bits 16")
        with warnings.catch_warnings():
            # torch 2.13 marks quantised-tensor constructors deprecated; the pinned torch has them
            warnings.simplefilter("ignore", UserWarning)
            weight = torch._make_per_tensor_quantized_tensor(torch.from_numpy(np.ascontiguousarray(q.T)), float(scale), 0)
            self.packed = torch.ops.quantized.linear_prepack(weight, None)

    def __call__(self, rows: np.ndarray, threads: int) -> np.ndarray:
        """(b, n) float32 -> (b, m) float32 = s_f s_P (x q - z sum q) per row."""
        import torch

        before = torch.get_num_threads()
        torch.set_num_threads(threads)  # the monolithic topology shares torch's pool with stage A
        try:
            with torch.inference_mode():
                x = torch.from_numpy(rows)
                return np.concatenate([torch.ops.quantized.linear_dynamic(x[r:r + 1], self.packed, True).numpy()
                                       for r in range(x.shape[0])])
        finally:
            torch.set_num_threads(before)


def int8_to_float32(q: np.ndarray, scale: float) -> np.ndarray:
    """s_P q as a new float32 (n, m) array, row chunk by row chunk (no float64 copy of P)."""
    out = np.empty(q.shape, dtype=np.float32)
    for start, stop in _chunks(q.shape[0]):
        out[start:stop] = q[start:stop].astype(np.float64) * scale
    return out
