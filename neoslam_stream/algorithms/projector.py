"""Stage B: binary projector — Gaussian random projection then sLSBH.

``d = P f`` with P of shape 1024 x n, i.i.d. N(0, 1) float32 entries generated deterministically from
``seed`` in row chunks (no float64 copy ever exists; 265 MB for n = 64896), or memory-mapped from the
ROS 2 NeoSLAM's raw ``.bin`` (row-major float32 (n, 1024), no header, exactly n*1024*4 bytes: that
file holds P transposed, so ``d = f @ P_bin``). We store P transposed too, (n, 1024), so both sources
share one code path and a single-frame product reads the matrix once, sequentially.

sLSBH with s = 25 % (Neubert's sparsified LSBH, as in the paper): bits [0, 1024) mark the 256 largest
components of d, bits [1024, 2048) the 256 smallest; exactly 512 bits; ties broken by the lower
index. Output: sorted uint16 bit indices.

Difference from the ROS 2 C++ on purpose: its two ``partial_sort`` calls mark the 256 smallest in
the first half and ranks 256..511 in the second, never the largest values; we follow the paper.

``matrix_dtype: float16`` stores P's entries rounded to IEEE binary16 (133 MB instead of 265 MB:
the product is bound by reading P, once per frame or micro-batch). Every entry is widened back to
float32 where it is read and the sums run in the same fixed order with float32 accumulators, so the
result is exactly the float32 projection with the rounded matrix (still a Gaussian projection: the
entries are N(0, 1) draws with 11 significant bits), independent of batch size and thread count.
The ``.bin`` file stays float32 (import rounds, :meth:`BinaryProjector.matrix_float32` exports).
Default float32: measured agreement and closures in docs/performance.md.

``matrix_dtype: int8`` stores P as q = rint(P / s_P), s_P = max|P| / 127 (66 MB: a quarter of the
bytes), and rounds each feature vector to 16-bit integers, x = rint(f / s_f) with
s_f = max|f| / 32767 (a relative error of 1.5e-5 of the largest feature, far below the matrix's
rounding). d = s_f s_P (x q) is then summed exactly in integers (int32 over blocks of rows, int64
across blocks): the bits do not depend on summation order, batch size, thread count or machine, and
the kernel's multiply-adds run on integer vector units instead of widening every entry to float.
It is still a Gaussian projection (N(0, 1) draws on a grid of max|P| / 127, about 0.04 standard
deviations); agreement with float32 and its effect on closures: docs/performance.md.

``feature_bits: 7`` (with ``matrix_dtype: int8``) rounds each feature vector much more coarsely, as
torch's dynamically quantised linear layer does, and lets that layer's int8 kernels (fbgemm /
oneDNN, VNNI dot-product instructions where the CPU has them) compute x q: per frame,
x = rint(f / s_f) + z on the 128 levels 0..127, s_f = (max(f, 0) - min(f, 0)) / 127, zero point z,
and d = s_f s_P (x q - z * sum(q)), summed exactly in int32 (|x q| <= 127 * 127 * n < 2^31 for
n <= 133 000) and scaled in float32. The 7-bit range ("reduce_range") is what keeps it exact on
every x86 CPU: AVX2's 8-bit multiply-add saturates at 2^15 on full 8-bit inputs. Each frame is
its own call, so its bits do not depend on the batch or the thread count. About half the 16-bit
kernel's time (0.29x float32's); it moves more bits (agreement and closures: docs/performance.md).

``projection: sparse`` is Li et al.'s very sparse random projection (entries +-sqrt(1/density) with
density 1/sqrt(n), zero otherwise), seeded, as a scipy.sparse matrix: ~1/255 of the work.

``centre_window`` W > 0 (off by default, i.e. the paper) subtracts a running mean of the features
before projecting: m_t = m_{t-1} + (f_t - m_{t-1}) / min(t, W), d = P (f_t - m_t). CNN feature
vectors share a large common component, so without it the sLSBH codes of *unrelated* images already
overlap in ~235 of 512 bits on Nordland (128 for independent codes) and a cross-season revisit
(~280) hardly stands out; centred, unrelated images overlap in ~128 bits and revisits in ~180. This
is the online form of the feature standardisation of Schubert, Neubert & Protzel (ICRA 2020). The
running mean is the projector's state (``state_dict``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numba
import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic, overload
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ._config import make_config
from .errors import InvalidInput

N_PROJ = 1024
N_BITS = 2 * N_PROJ
_CHUNK_ROWS = 4096


class ProjectorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    projection: Literal["gaussian", "sparse"] = "gaussian"
    #: input dimension n (set by the pipeline from the feature backbone)
    input_dim: int = Field(64896, ge=1)
    seed: int = 42
    #: ROS 2 NeoSLAM randomMatrix.bin to load instead of generating (gaussian only)
    matrix_path: str | None = None
    sparsity: float = Field(0.25, gt=0, lt=0.5)
    #: running-mean window W for feature centring; 0 = off (the paper)
    centre_window: int = Field(0, ge=0)
    threads: int = Field(1, ge=1)
    #: storage precision of the Gaussian matrix P: float32 (265 MB, the reference), float16
    #: (133 MB, half the memory traffic per frame; every product still accumulates in float32) or
    #: int8 (66 MB; 16-bit integer features, exact integer sums: see the module docstring)
    matrix_dtype: Literal["float32", "float16", "int8"] = "float32"
    #: with ``matrix_dtype: int8``: features rounded to 16-bit integers (exact numba kernel) or to
    #: 7 bits per frame (torch's quantised int8 kernels, ~2x faster; see the module docstring)
    feature_bits: Literal[16, 7] = 16
    #: where B computes: ``cpu`` = the fixed-order numba kernel (default); ``cuda``, ``cuda:N`` or
    #: ``auto`` (cuda when torch sees a GPU, else cpu) = torch on that device, fused with stage A
    #: in one node so that only the bits leave the device (see :class:`TorchProjection`)
    device: str = Field("cpu", pattern=r"^(cpu|auto|cuda(:[0-9]+)?)$")

    @model_validator(mode="after")
    def _seven_bit_features_need_the_int8_matrix(self) -> ProjectorConfig:
        if self.feature_bits == 7 and (self.projection != "gaussian" or self.matrix_dtype != "int8"):
            raise ValueError("feature_bits 7 is the int8 Gaussian matrix's fast kernel: it needs "
                             f"projection gaussian and matrix_dtype int8 (got {self.projection}, {self.matrix_dtype})")
        if self.feature_bits == 7 and self.input_dim * 127 * 127 >= 2**31:
            raise ValueError(f"feature_bits 7 sums in int32: input_dim {self.input_dim} could overflow "
                             f"(127 * 127 * n must stay below 2^31, n <= {(2**31 - 1) // (127 * 127)})")
        return self


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
    kernel reads these bits and widens them itself (:func:`_half_rows_to_float`)."""
    out = np.empty(matrix.shape, dtype=np.uint16)
    for start, stop in _chunks(matrix.shape[0]):
        out[start:stop] = np.asarray(matrix[start:stop], dtype=np.float32).astype(np.float16).view(np.uint16)
    return out


def load_bin(path: str | Path, n: int, m: int = N_PROJ) -> np.ndarray:
    """Memory-map a ROS 2 NeoSLAM ``randomMatrix.bin`` (row-major float32 (n, m), no header)."""
    p = Path(path)
    expected = n * m * 4
    size = p.stat().st_size
    if size != expected:
        raise ValueError(f"{p} has {size} bytes; a float32 ({n}, {m}) matrix has {expected}")
    return np.memmap(p, dtype="<f4", mode="r", shape=(n, m))


def save_bin(matrix: np.ndarray, path: str | Path) -> None:
    """Write (n, m) float32 row-major without header (the ROS 2 NeoSLAM format)."""
    np.ascontiguousarray(matrix, dtype="<f4").tofile(str(path))


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
    :func:`_project_rows`."""
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
def _project_rows(F, W, out):  # pragma: no cover - compiled
    """out[r] = F[r] @ W with a summation order that depends on nothing but n.

    BLAS rounds a matrix-vector product differently from a matrix-matrix one, so a frame's bits
    would depend on how many frames were batched with it; here every output element is the sum of
    PROJECTION_CHUNKS partial sums over fixed row ranges of W, each accumulated four rows at a time
    in order, so results are identical for any batch size and thread count (lossless runs are
    repeatable). The product is bound by memory bandwidth (265 MB of W per pass): each block of four
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
def _project_rows_int8(X, Q, out):  # pragma: no cover - compiled
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
def _slsbh_rows(D, k, out):  # pragma: no cover - compiled
    """sLSBH of every row of D into out (b, 2k), the same rule as :func:`slsbh`."""
    m = D.shape[1]
    for r in range(D.shape[0]):
        desc = np.argsort(-D[r], kind="mergesort")[:k]
        asc = np.argsort(D[r], kind="mergesort")[:k]
        out[r, :k] = np.sort(desc)
        out[r, k:] = np.sort(asc) + m


class QuantisedLinear:
    """x q with torch's dynamically quantised int8 linear layer (``feature_bits: 7``), one frame per
    call: the per-frame feature quantisation (7 bits, zero point) is then a function of that frame
    alone. fbgemm packs q (its own copy, 66 MB at full size) for its int8 kernels."""

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


class TorchProjection:
    """B in torch on any device: d = P f and sLSBH there, only the bit indices come back.

    Used by the fused A+B node when ``device`` is a GPU, so a frame's 64896 features never cross
    the PCIe bus; P moves to the device once (float32 values; with ``matrix_dtype: float16`` the
    rounded ones, so both precisions give the same values as on the CPU). sLSBH uses stable sorts
    (ties: lower index), like :func:`slsbh`. Each frame is one matrix-vector product, so a frame's
    bits do not depend on how many frames were batched with it. The summation order is torch's
    (BLAS / cuBLAS), not the numba kernel's: a projected value within a rounding error of the
    256th largest or smallest can flip one bit pair (measured agreement: docs/performance.md).
    Centring (``centre_window``) runs on the device in float64, the same rule as
    :meth:`BinaryProjector.centre`; the running mean stays there (:meth:`state_dict` fetches it).
    """

    def __init__(self, projector: BinaryProjector, device: Any) -> None:
        import torch

        if projector.projection != "gaussian":
            raise ValueError("the torch path implements the gaussian projection only")
        self.projector = projector
        self.device = torch.device(device)
        self.k = int(round(N_PROJ * projector.sparsity))
        self.matrix = torch.from_numpy(np.ascontiguousarray(projector.matrix_float32())).to(self.device)
        self.mean = torch.from_numpy(projector.mean).to(self.device)

    def bits_batch(self, feats: Any) -> list[np.ndarray]:
        """(b, n) features (a torch tensor on any device, or numpy) -> b sorted uint16 bit arrays."""
        import torch

        f = torch.as_tensor(feats).to(self.device, torch.float32)
        if f.ndim != 2 or f.shape[1] != self.projector.input_dim:
            raise InvalidInput(f"features of shape {tuple(f.shape)}, projector expects (b, {self.projector.input_dim})")
        if not bool(torch.isfinite(f).all()):
            raise InvalidInput("features contain NaN or infinite values")
        pr = self.projector
        out = []
        with torch.inference_mode():
            for row in f:
                if pr.centre_window:
                    pr.n_seen += 1
                    self.mean += (row.double() - self.mean) / min(pr.n_seen, pr.centre_window)
                    row = (row.double() - self.mean).float()
                d = row @ self.matrix
                desc = torch.sort(d, descending=True, stable=True).indices[: self.k]
                asc = torch.sort(d, stable=True).indices[: self.k]
                bits = torch.cat([torch.sort(desc).values, torch.sort(asc).values + d.shape[0]])
                out.append(bits.to(torch.int32).cpu().numpy().astype(np.uint16))
        return out

    def state_dict(self) -> dict[str, Any]:
        """The running mean, fetched from the device (only here: per frame only bits leave it)."""
        self.projector.mean = self.mean.cpu().numpy().astype(np.float64)
        return self.projector.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        import torch

        self.projector.load_state_dict(state)
        self.mean = torch.from_numpy(self.projector.mean).to(self.device)


def slsbh(d: np.ndarray, sparsity: float = 0.25) -> np.ndarray:
    """sLSBH bits of one projected vector: sorted uint16 indices, exactly 2*round(m*sparsity).

    Bit j (j < m) marks d_j among the k largest, bit m+j marks d_j among the k smallest; ties are
    broken by the lower index (stable sorts).
    """
    d = np.asarray(d)
    if d.ndim != 1:
        raise InvalidInput(f"expected a 1-D vector, got shape {d.shape}")
    m = d.shape[0]
    k = int(round(m * sparsity))
    order_desc = np.argsort(-d, kind="stable")[:k]
    order_asc = np.argsort(d, kind="stable")[:k]
    bits = np.concatenate([np.sort(order_desc), np.sort(order_asc) + m]).astype(np.uint16)
    return bits


class BinaryProjector:
    """float32[n] -> 512 sorted bit indices of 2048 (see module docstring)."""

    def __init__(self, config: ProjectorConfig | None = None, **overrides: Any) -> None:
        cfg = self.config = make_config(ProjectorConfig, config, overrides)
        self.threads = cfg.threads
        self.input_dim = cfg.input_dim
        self.projection = projection = cfg.projection
        self.sparsity = cfg.sparsity
        self.seed = seed = cfg.seed
        self.centre_window = cfg.centre_window
        self.mean = np.zeros(cfg.input_dim, dtype=np.float64)
        self.n_seen = 0
        input_dim, matrix_path = cfg.input_dim, cfg.matrix_path
        self.matrix_dtype = cfg.matrix_dtype
        #: s_P of ``matrix_dtype: int8`` (P ~ s_P q); 1.0 for the float storages
        self.matrix_scale = 1.0
        self.feature_bits = cfg.feature_bits
        self._quantised_linear: QuantisedLinear | None = None
        if projection == "gaussian" and cfg.matrix_dtype == "int8":
            if matrix_path:
                self.matrix, self.matrix_scale = quantise_int8(load_bin(matrix_path, input_dim))
            else:
                self.matrix, self.matrix_scale = gaussian_matrix_int8(input_dim, seed)
        elif projection == "gaussian":
            half = cfg.matrix_dtype == "float16"
            if matrix_path:
                self.matrix = to_half_bits(load_bin(matrix_path, input_dim)) if half else load_bin(matrix_path, input_dim)
            else:
                self.matrix = gaussian_matrix(input_dim, seed, half=half)
        elif projection == "sparse":
            if matrix_path:
                raise ValueError("matrix_path is only for the gaussian projection")
            self.matrix = sparse_matrix(input_dim, seed)
            # P as CSR (m, n): one pass over its rows per frame is cheaper than P^T's columns
            self._sparse_rows = self.matrix.T.tocsr()
        else:
            raise ValueError(f"unknown projection {projection!r} (gaussian or sparse)")
        if cfg.feature_bits == 7:
            self._quantised_linear = QuantisedLinear(self.matrix, self.matrix_scale)

    def matrix_float32(self) -> np.ndarray:
        """P as float32 (n, m), e.g. for :func:`save_bin`; with ``matrix_dtype: float16`` the values
        it uses, i.e. the binary16-rounded ones; with ``int8`` s_P q (a new array: 265 MB at full size)."""
        if self.projection != "gaussian":
            raise ValueError("only the gaussian projection has a dense matrix")
        if self.matrix_dtype == "int8":
            out = np.empty(self.matrix.shape, dtype=np.float32)
            for start, stop in _chunks(self.matrix.shape[0]):
                out[start:stop] = self.matrix[start:stop].astype(np.float64) * self.matrix_scale
            return out
        return half_bits_to_float32(self.matrix) if self.matrix_dtype == "float16" else np.asarray(self.matrix)

    def _check(self, feats: np.ndarray) -> np.ndarray:
        f = np.asarray(feats, dtype=np.float32)
        if f.ndim not in (1, 2) or f.shape[-1] != self.input_dim:
            raise InvalidInput(f"features of shape {f.shape}, projector expects ({self.input_dim},) or (b, {self.input_dim})")
        if not np.all(np.isfinite(f)):
            raise InvalidInput("features contain NaN or infinite values")
        return f

    def centre(self, feats: np.ndarray) -> np.ndarray:
        """Subtract the running mean m_t (updated with each row, in order) when ``centre_window`` > 0.

        Frame by frame, so the result does not depend on how frames were batched.
        """
        f = self._check(feats)
        if not self.centre_window:
            return f
        rows = np.atleast_2d(f)
        out = np.empty_like(rows)
        for r, row in enumerate(rows):
            self.n_seen += 1
            self.mean += (row - self.mean) / min(self.n_seen, self.centre_window)
            out[r] = row - self.mean
        return out[0] if f.ndim == 1 else out

    def project(self, feats: np.ndarray) -> np.ndarray:
        """d = P f: (n,) or (b, n) features -> (1024,) or (b, 1024) float32 (no centring)."""
        f = self._check(feats)
        out = self._project(np.atleast_2d(f)).astype(np.float32, copy=False)
        return out[0] if f.ndim == 1 else out

    def _project(self, rows: np.ndarray) -> np.ndarray:
        """(b, n) -> (b, 1024): float32, or float64 for int8 storage (s_f s_P times an exact integer
        sum < 2^53, so no two different sums round to the same value before sLSBH ranks them)."""
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        if self.projection == "sparse":
            return np.asarray((self._sparse_rows @ rows.T).T, dtype=np.float32)
        if self._quantised_linear is not None:
            return self._quantised_linear(rows, self.threads)
        numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        if self.matrix_dtype == "int8":
            x, scale = quantise_features(rows)
            sums = np.empty((rows.shape[0], self.matrix.shape[1]), dtype=np.int64)
            _project_rows_int8(x, self.matrix, sums)
            return sums * (scale * self.matrix_scale)[:, None]
        out = np.empty((rows.shape[0], self.matrix.shape[1]), dtype=np.float32)
        _project_rows(rows, self.matrix, out)  # float32 or binary16 storage (_widen)
        return out

    def bits(self, feats: np.ndarray) -> np.ndarray:
        """One feature vector (n,) -> its sLSBH bits (centring first when enabled); its values are
        checked once, by :meth:`bits_batch`'s centring."""
        f = np.asarray(feats)
        if f.ndim != 1:
            raise InvalidInput(f"bits() takes one feature vector ({self.input_dim},), got shape {f.shape}: "
                               "use bits_batch for several")
        return self.bits_batch(f[None, :])[0]

    def bits_batch(self, feats: np.ndarray) -> list[np.ndarray]:
        """(b, n) features -> b arrays of sorted uint16 bit indices; one pass over P."""
        d = np.ascontiguousarray(self._project(self.centre(np.atleast_2d(feats))))
        k = int(round(d.shape[1] * self.sparsity))
        out = np.empty((d.shape[0], 2 * k), dtype=np.int64)
        _slsbh_rows(d, k, out)
        return list(out.astype(np.uint16))

    def warm_up(self) -> None:
        """Compile the numba kernels now (not on the first frame), without touching the running mean."""
        d = self._project(np.zeros((1, self.input_dim), np.float32))
        k = int(round(N_PROJ * self.sparsity))
        _slsbh_rows(d, k, np.empty((1, 2 * k), np.int64))

    def state_dict(self) -> dict[str, Any]:
        """The running mean (the matrix is not state: it is regenerated from the seed or file)."""
        return {"centre_window": self.centre_window, "mean": self.mean.copy(), "n_seen": self.n_seen}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        mean = np.asarray(state["mean"], dtype=np.float64)
        if mean.shape != (self.input_dim,):
            raise ValueError(f"saved running mean has shape {mean.shape}, expected ({self.input_dim},)")
        self.centre_window = int(state["centre_window"])
        self.mean = mean.copy()
        self.n_seen = int(state["n_seen"])
