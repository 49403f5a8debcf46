"""Stage B: binary projector, a Gaussian random projection then sLSBH.

d = P f (the matrix, its storages and kernels: :mod:`.projection`), then sLSBH with s = 25 %
(Neubert's sparsified LSBH, as in the paper): bits [0, 1024) mark the 256 largest components of
d, bits [1024, 2048) the 256 smallest; exactly 512 bits, ties to the lower index; output sorted
uint16 bit indices. The ROS 2 C++'s two ``partial_sort`` calls mark the 256 smallest and the next
quartile instead, never the largest; we follow the paper. ``centre_window`` W > 0 (off in the
paper) first subtracts a running mean of the features (:class:`RunningCentre`): CNN features share
a large common component that makes the codes of unrelated images overlap (docs/frontend.md); this
is the online form of the feature standardisation of Schubert, Neubert & Protzel (ICRA 2020). The
window counts frames, or with ``centre_kappa`` > 0 places: a frame enters the mean only when it has
moved far enough from the last one that did, so a slow or still camera does not centre a place away
from itself. With ``descriptor`` B also keeps each frame's centred features as int8, the finer
descriptor from which D re-ranks the candidates its bits shortlisted (a binary code of 512 bits
ranks places that differ a little worse than the features it came from). The running mean is the
projector's state. :class:`TorchProjection` runs B in torch on stage A's device, so that only the
bits (and the descriptor) leave it.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numba
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ._config import make_config
from .errors import InvalidInput
from .projection import (
    N_BITS,
    N_PROJ,
    QuantisedLinear,
    gaussian_matrix,
    gaussian_matrix_int8,
    half_bits_to_float32,
    int8_to_float32,
    project_rows,
    project_rows_int8,
    quantise_features,
    quantise_int8,
    slsbh_rows,
    sparse_matrix,
    to_half_bits,
)
from .records import BinaryCode
from .weights import load_bin

__all__ = ["N_BITS", "N_PROJ", "BinaryProjector", "ProjectorConfig", "TorchProjection", "slsbh"]


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
    #: 0: the window counts frames. kappa > 0: it counts places: a frame enters the running mean
    #: only when its features lie at least kappa times the spread of the run's places (the RMS
    #: distance of the features seen so far to their mean) from the last frame that entered, so
    #: the window is W places at any camera rate and a still camera leaves the mean as it is
    centre_kappa: float = Field(0.0, ge=0)
    #: also give each frame's centred features as int8 (``BinaryCode.descriptor``), from which D
    #: re-ranks the candidates the bits shortlisted (``spatial_view.rerank``)
    descriptor: bool = False
    threads: int = Field(1, ge=1)
    #: storage precision of the Gaussian matrix P: float32 (the reference), float16 (half the
    #: memory traffic per frame; every product still accumulates in float32) or int8 (a quarter;
    #: 16-bit integer features, exact integer sums): algorithms/projection.py, docs/frontend.md
    matrix_dtype: Literal["float32", "float16", "int8"] = "float32"
    #: with ``matrix_dtype: int8``: features rounded to 16-bit integers (exact numba kernel) or to
    #: 7 bits per frame (torch's quantised int8 kernels, faster: docs/performance.md)
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


class RunningCentre:
    """The running mean m that B subtracts from each frame's features f_t, updated with f_t first:
    m <- m + (f_t - m) / min(k, W) for the k-th frame that enters it. With ``kappa`` 0 every frame
    enters (the window counts frames); with kappa > 0 a frame enters only when it lies at least
    kappa * D_t from the last that entered, D_t the spread of the run's places (the RMS distance of
    every frame so far to their cumulative mean, Welford's sums), so W counts places whatever the
    camera's rate. Written with operators alone, so numpy arrays (float64) and torch tensors
    (float64, on a device) share it."""

    def __init__(self, window: int, kappa: float, mean: Any) -> None:
        self.window, self.kappa = window, kappa
        self.mean = mean
        #: frames seen, frames that entered the mean
        self.n_seen = self.n_entered = 0
        #: the cumulative mean and sum of squared deviations (kappa > 0), and the last frame that entered
        self.cum_mean = mean * 0
        self.sum_sq = 0.0
        self.last: Any = None

    def __call__(self, row: Any) -> Any:
        """``row`` (one frame's features) less the mean, the mean updated with it first."""
        self.n_seen += 1
        if not self.kappa:
            self.mean += (row - self.mean) / min(self.n_seen, self.window)
            return row - self.mean
        dev = row - self.cum_mean
        self.cum_mean += dev / self.n_seen
        self.sum_sq += float((dev * (row - self.cum_mean)).sum())
        spread = math.sqrt(self.sum_sq / self.n_seen)
        if self.last is None or math.sqrt(float(((row - self.last) ** 2).sum())) >= self.kappa * spread:
            self.n_entered += 1
            self.last = row * 1.0
            self.mean += (row - self.mean) / min(self.n_entered, self.window)
        return row - self.mean

    def state(self, to_numpy: Any) -> dict[str, Any]:
        out: dict[str, Any] = {"mean": to_numpy(self.mean), "n_seen": self.n_seen}
        if self.kappa:
            out.update({"n_entered": self.n_entered, "cum_mean": to_numpy(self.cum_mean), "sum_sq": self.sum_sq,
                        "last": None if self.last is None else to_numpy(self.last)})
        return out

    def load(self, st: dict[str, Any], from_numpy: Any) -> None:
        self.mean, self.n_seen = from_numpy(st["mean"]), int(st["n_seen"])
        if self.kappa:
            self.n_entered, self.sum_sq = int(st["n_entered"]), float(st["sum_sq"])
            self.cum_mean = from_numpy(st["cum_mean"])
            self.last = None if st["last"] is None else from_numpy(st["last"])


def int8_descriptor(centred: np.ndarray) -> np.ndarray:
    """One frame's centred features as int8, scaled so its largest magnitude is 127 (cosines
    between descriptors do not depend on the scale)."""
    peak = float(np.abs(centred).max()) if centred.size else 0.0
    if peak == 0.0:
        return np.zeros(centred.shape, np.int8)
    return np.rint(centred * (127.0 / peak)).astype(np.int8)


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

        if projector.config.projection != "gaussian":
            raise ValueError("the torch path implements the gaussian projection only")
        self.projector = projector
        self.device = torch.device(device)
        self.k = int(round(N_PROJ * projector.config.sparsity))
        self.matrix = torch.from_numpy(np.ascontiguousarray(projector.matrix_float32())).to(self.device)
        cfg = projector.config
        self.centring = RunningCentre(cfg.centre_window, cfg.centre_kappa,
                                      torch.from_numpy(projector.centring.mean).to(self.device))

    def _to_device(self, a: np.ndarray) -> Any:
        import torch

        return torch.from_numpy(np.asarray(a, dtype=np.float64)).to(self.device)

    def bits_batch(self, feats: Any) -> list[np.ndarray]:
        """(b, n) features (a torch tensor on any device, or numpy) -> b sorted uint16 bit arrays."""
        return [c.bits for c in self.codes_batch(feats)]

    def codes_batch(self, feats: Any) -> list[BinaryCode]:
        """(b, n) features -> b codes: bits, and the int8 descriptor when the config keeps one."""
        import torch

        f = torch.as_tensor(feats).to(self.device, torch.float32)
        cfg = self.projector.config
        n = cfg.input_dim
        if f.ndim != 2 or f.shape[1] != n:
            raise InvalidInput(f"features of shape {tuple(f.shape)}, projector expects (b, {n})")
        if not bool(torch.isfinite(f).all()):
            raise InvalidInput("features contain NaN or infinite values")
        out = []
        with torch.inference_mode():
            for row in f:
                if cfg.centre_window:
                    row = self.centring(row.double()).float()
                d = row @ self.matrix
                desc = torch.sort(d, descending=True, stable=True).indices[: self.k]
                asc = torch.sort(d, stable=True).indices[: self.k]
                bits = torch.cat([torch.sort(desc).values, torch.sort(asc).values + d.shape[0]])
                descriptor = None
                if cfg.descriptor:
                    peak = float(row.abs().max())
                    descriptor = (torch.round(row * (127.0 / peak)) if peak else row * 0).to(torch.int8).cpu().numpy()
                out.append(BinaryCode(bits.to(torch.int32).cpu().numpy().astype(np.uint16), N_BITS, descriptor))
        return out

    def state_dict(self) -> dict[str, Any]:
        """The running mean, fetched from the device (only here: per frame only bits leave it)."""
        return self.projector.state_dict(self.centring.state(lambda t: t.cpu().numpy().astype(np.float64)))

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.projector.load_state_dict(state)
        self.centring.load(self.projector.centring.state(np.copy), self._to_device)


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
        self.centring = RunningCentre(cfg.centre_window, cfg.centre_kappa, np.zeros(cfg.input_dim, dtype=np.float64))
        #: s_P of ``matrix_dtype: int8`` (P ~ s_P q); 1.0 for the float storages
        self.matrix_scale = 1.0
        self._quantised_linear: QuantisedLinear | None = None
        n, path = cfg.input_dim, cfg.matrix_path
        if cfg.projection == "gaussian" and cfg.matrix_dtype == "int8":
            if path:
                self.matrix, self.matrix_scale = quantise_int8(load_bin(path, n))
            else:
                self.matrix, self.matrix_scale = gaussian_matrix_int8(n, cfg.seed)
        elif cfg.projection == "gaussian":
            half = cfg.matrix_dtype == "float16"
            if path:
                self.matrix = to_half_bits(load_bin(path, n)) if half else load_bin(path, n)
            else:
                self.matrix = gaussian_matrix(n, cfg.seed, half=half)
        elif cfg.projection == "sparse":
            if path:
                raise ValueError("matrix_path is only for the gaussian projection")
            self.matrix = sparse_matrix(n, cfg.seed)
            # P as CSR (m, n): one pass over its rows per frame is cheaper than P^T's columns
            self._sparse_rows = self.matrix.T.tocsr()
        else:
            raise ValueError(f"unknown projection {cfg.projection!r} (gaussian or sparse)")
        if cfg.feature_bits == 7:
            self._quantised_linear = QuantisedLinear(self.matrix, self.matrix_scale)

    def matrix_float32(self) -> np.ndarray:
        """P as float32 (n, m), e.g. for :func:`~.weights.save_bin`; with ``matrix_dtype: float16``
        the values it uses, i.e. the binary16-rounded ones; with ``int8`` s_P q (a new array)."""
        if self.config.projection != "gaussian":
            raise ValueError("only the gaussian projection has a dense matrix")
        if self.config.matrix_dtype == "int8":
            return int8_to_float32(self.matrix, self.matrix_scale)
        return half_bits_to_float32(self.matrix) if self.config.matrix_dtype == "float16" else np.asarray(self.matrix)

    def _check(self, feats: np.ndarray) -> np.ndarray:
        f = np.asarray(feats, dtype=np.float32)
        n = self.config.input_dim
        if f.ndim not in (1, 2) or f.shape[-1] != n:
            raise InvalidInput(f"features of shape {f.shape}, projector expects ({n},) or (b, {n})")
        if not np.all(np.isfinite(f)):
            raise InvalidInput("features contain NaN or infinite values")
        return f

    @property
    def mean(self) -> np.ndarray:
        """The running mean that centring subtracts."""
        return self.centring.mean

    @property
    def n_seen(self) -> int:
        """Frames centred so far."""
        return self.centring.n_seen

    def centre(self, feats: np.ndarray) -> np.ndarray:
        """Subtract the running mean (:class:`RunningCentre`, updated with each row, in order) when
        ``centre_window`` > 0. Frame by frame, so the result does not depend on how frames were batched.
        """
        f = self._check(feats)
        if not self.config.centre_window:
            return f
        rows = np.atleast_2d(f)
        out = np.empty_like(rows)
        for r, row in enumerate(rows):
            out[r] = self.centring(row)
        return out[0] if f.ndim == 1 else out

    def project(self, feats: np.ndarray) -> np.ndarray:
        """d = P f: (n,) or (b, n) features -> (1024,) or (b, 1024) float32 (no centring)."""
        f = self._check(feats)
        out = self._project(np.atleast_2d(f)).astype(np.float32, copy=False)
        return out[0] if f.ndim == 1 else out

    def _project(self, rows: np.ndarray) -> np.ndarray:
        """(b, n) -> (b, 1024): float32, or float64 for int8 storage (s_f s_P times an exact integer
        sum < 2^53, so no two different sums round to the same value before sLSBH ranks them)."""
        cfg = self.config
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        if cfg.projection == "sparse":
            return np.asarray((self._sparse_rows @ rows.T).T, dtype=np.float32)
        if self._quantised_linear is not None:
            return self._quantised_linear(rows, cfg.threads)
        numba.set_num_threads(min(cfg.threads, numba.config.NUMBA_NUM_THREADS))
        if cfg.matrix_dtype == "int8":
            x, scale = quantise_features(rows)
            sums = np.empty((rows.shape[0], self.matrix.shape[1]), dtype=np.int64)
            project_rows_int8(x, self.matrix, sums)
            return sums * (scale * self.matrix_scale)[:, None]
        out = np.empty((rows.shape[0], self.matrix.shape[1]), dtype=np.float32)
        project_rows(rows, self.matrix, out)  # float32 or binary16 storage
        return out

    def bits(self, feats: np.ndarray) -> np.ndarray:
        """One feature vector (n,) -> its sLSBH bits (centring first when enabled); its values are
        checked once, by :meth:`bits_batch`'s centring."""
        f = np.asarray(feats)
        if f.ndim != 1:
            raise InvalidInput(f"bits() takes one feature vector ({self.config.input_dim},), got shape "
                               f"{f.shape}: use bits_batch for several")
        return self.bits_batch(f[None, :])[0]

    def bits_batch(self, feats: np.ndarray) -> list[np.ndarray]:
        """(b, n) features -> b arrays of sorted uint16 bit indices; one pass over P."""
        return [c.bits for c in self.codes_batch(feats)]

    def codes_batch(self, feats: np.ndarray) -> list[BinaryCode]:
        """(b, n) features -> b codes: the sorted uint16 bit indices (one pass over P), and each
        frame's int8 descriptor when the config keeps one."""
        centred = self.centre(np.atleast_2d(feats))
        d = np.ascontiguousarray(self._project(centred))
        k = int(round(d.shape[1] * self.config.sparsity))
        out = np.empty((d.shape[0], 2 * k), dtype=np.int64)
        slsbh_rows(d, k, out)
        keep = self.config.descriptor
        return [BinaryCode(b, N_BITS, int8_descriptor(c) if keep else None)
                for b, c in zip(out.astype(np.uint16), centred, strict=True)]

    def warm_up(self) -> None:
        """Compile the numba kernels now (not on the first frame), without touching the running mean."""
        d = self._project(np.zeros((1, self.config.input_dim), np.float32))
        k = int(round(N_PROJ * self.config.sparsity))
        slsbh_rows(d, k, np.empty((1, 2 * k), np.int64))

    def state_dict(self, centring: dict[str, Any] | None = None) -> dict[str, Any]:
        """The running mean (``centring``: one fetched from elsewhere, the torch path's) and the
        window it was made with (the matrix is not state: it is regenerated from the seed or file)."""
        return {"centre_window": self.config.centre_window, "centre_kappa": self.config.centre_kappa,
                **(centring or self.centring.state(np.copy))}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict`; a running mean made with another ``centre_window``,
        ``centre_kappa`` or ``input_dim`` is refused."""
        cfg = self.config
        for name in ("centre_window", "centre_kappa"):
            if state[name] != getattr(cfg, name):
                raise ValueError(f"projector.{name}: the state was made with {state[name]}, the config has "
                                 f"{getattr(cfg, name)}")
        mean = np.asarray(state["mean"], dtype=np.float64)
        if mean.shape != (cfg.input_dim,):
            raise ValueError(f"projector.input_dim: the state's running mean has shape {mean.shape}, the config "
                             f"has input_dim {cfg.input_dim}")
        self.centring.load(state, lambda a: np.array(a, dtype=np.float64))
