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

``projection: sparse`` is Li et al.'s very sparse random projection (entries +-sqrt(1/density) with
density 1/sqrt(n), zero otherwise), seeded, as a scipy.sparse matrix: ~1/255 of the work.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from neoslam_stream.messages import Message
from neoslam_stream.stage import Output, StageAdapter, StageInputError

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
    threads: int = Field(1, ge=1)


def gaussian_matrix(n: int, seed: int, m: int = N_PROJ) -> np.ndarray:
    """(n, m) float32 N(0,1), filled row chunk by row chunk from one seeded stream."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, m), dtype=np.float32)
    for start in range(0, n, _CHUNK_ROWS):
        stop = min(n, start + _CHUNK_ROWS)
        rng.standard_normal((stop - start, m), dtype=np.float32, out=out[start:stop])
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


@njit(cache=True)
def _project_rows(F, W, out):  # pragma: no cover - compiled
    """out[r] = F[r] @ W, summing over W's rows in order for every output element.

    BLAS rounds a matrix-vector product differently from a matrix-matrix one, so a frame's bits
    would depend on how many frames were batched with it; here the summation order is fixed, so
    results are identical for any batch size (and lossless runs are repeatable). One pass over W
    serves the whole batch (micro-batching amortises the 265 MB read).
    """
    n, m = W.shape
    for i in range(n):
        for r in range(F.shape[0]):
            a = F[r, i]
            if a != 0.0:
                for j in range(m):
                    out[r, j] += a * W[i, j]


def slsbh(d: np.ndarray, sparsity: float = 0.25) -> np.ndarray:
    """sLSBH bits of one projected vector: sorted uint16 indices, exactly 2*round(m*sparsity).

    Bit j (j < m) marks d_j among the k largest, bit m+j marks d_j among the k smallest; ties are
    broken by the lower index (stable sorts).
    """
    d = np.asarray(d)
    if d.ndim != 1:
        raise ValueError(f"expected a 1-D vector, got shape {d.shape}")
    m = d.shape[0]
    k = int(round(m * sparsity))
    order_desc = np.argsort(-d, kind="stable")[:k]
    order_asc = np.argsort(d, kind="stable")[:k]
    bits = np.concatenate([np.sort(order_desc), np.sort(order_asc) + m]).astype(np.uint16)
    return bits


class BinaryProjector:
    """float32[n] -> 512 sorted bit indices of 2048 (see module docstring)."""

    def __init__(self, input_dim: int = 64896, projection: str = "gaussian", seed: int = 42,
                 matrix_path: str | None = None, sparsity: float = 0.25, threads: int = 1) -> None:
        self.input_dim = input_dim
        self.projection = projection
        self.sparsity = sparsity
        self.seed = seed
        if projection == "gaussian":
            self.matrix = load_bin(matrix_path, input_dim) if matrix_path else gaussian_matrix(input_dim, seed)
        elif projection == "sparse":
            if matrix_path:
                raise ValueError("matrix_path is only for the gaussian projection")
            self.matrix = sparse_matrix(input_dim, seed)
        else:
            raise ValueError(f"unknown projection {projection!r} (gaussian or sparse)")

    def project(self, feats: np.ndarray) -> np.ndarray:
        """(n,) or (b, n) features -> (1024,) or (b, 1024) float32."""
        f = np.asarray(feats, dtype=np.float32)
        if f.shape[-1] != self.input_dim:
            raise ValueError(f"feature vector of length {f.shape[-1]}, projector expects {self.input_dim}")
        if self.projection == "sparse":
            out = (self.matrix.T @ f.T).T
            return np.asarray(out, dtype=np.float32)
        rows = np.ascontiguousarray(np.atleast_2d(f))
        out = np.zeros((rows.shape[0], self.matrix.shape[1]), dtype=np.float32)
        _project_rows(rows, self.matrix, out)
        return out[0] if f.ndim == 1 else out

    def bits(self, feats: np.ndarray) -> np.ndarray:
        return slsbh(self.project(feats), self.sparsity)

    def bits_batch(self, feats: np.ndarray) -> list[np.ndarray]:
        d = self.project(np.atleast_2d(feats))
        return [slsbh(row, self.sparsity) for row in d]


class ProjectorStage(StageAdapter):
    """``visual_features`` -> ``bin_features`` (bits: sorted uint16 indices of 2048)."""

    inputs = ("visual_features",)
    outputs = ("bin_features",)
    batchable = True

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.config = ProjectorConfig(**params)
        self.projector: BinaryProjector | None = None

    def setup(self) -> None:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(self.config.threads)
        except ImportError:
            pass
        self.projector = BinaryProjector(**self.config.model_dump(exclude={"threads"}))
        self.projector.project(np.zeros(self.config.input_dim, np.float32))  # compile before frames come

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        assert self.projector is not None
        feats = []
        for m in msgs:
            f = m["features"]
            if f.ndim != 1 or f.shape[0] != self.projector.input_dim:
                raise StageInputError(f"features of shape {f.shape}, expected ({self.projector.input_dim},)")
            feats.append(f)
        bits = self.projector.bits_batch(np.stack(feats))
        return [("bin_features", m.derive("bin_features", {"bits": b, "size": N_BITS}))
                for m, b in zip(msgs, bits, strict=True)]

    def info(self) -> dict[str, Any]:
        return {"projection": self.config.projection, "input_dim": self.config.input_dim,
                "matrix": self.config.matrix_path or f"generated (seed {self.config.seed})"}


def make_stage(**params: Any) -> ProjectorStage:
    return ProjectorStage(**params)
