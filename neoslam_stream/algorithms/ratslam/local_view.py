"""RatSLAM's local-view cells (OpenRatSLAM's ``LocalViewMatch``), the baseline front end: image
templates matched by the sum of absolute differences.

Template: grey levels (colour channels summed and divided by 3*255, as the C++), cropped to
``image_crop_*`` (-1: the image edge), block means into ``template_x_size x template_y_size`` cells
(leftover pixels ignored), optionally normalised globally (``vt_normalisation``) and per patch
(``vt_patch_normalise``). Matching skips templates whose mean differs by more than
``vt_match_threshold`` + 0.005 and compares the central columns ``[S, X-S)`` with the shifts ``0,
step, .., 2S`` (S = vt_shift_match), or every circular shift in panoramic mode (``relative_rad``).
The lowest mean absolute difference wins (the first on ties); at most ``vt_match_threshold`` is a
match, otherwise a new template (ids from 0). A compiled loop sums in the C++'s order and stops a
candidate once it exceeds the best: the errors are OpenRatSLAM's to the last bit.

``openratslam_compat`` changes one thing: a flat patch with ``vt_min_patch_normalisation_std`` 0
gives 0/0 in the C++, clamped to 1.0; the default gives it the C++'s neutral 0.5.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from numpy.lib.stride_tricks import sliding_window_view
from pydantic import BaseModel, ConfigDict, Field

from .._config import make_config
from ..errors import InvalidInput

#: OpenRatSLAM's slack on the mean pre-filter (hard-coded in the C++).
MEAN_EPSILON = 0.005


class LocalViewConfig(BaseModel):
    """OpenRatSLAM's local-view parameters (-1 = image edge), with the C++ code defaults except the
    template size and shift: the C++'s 1 x 1 template with shift 25 (step 5) leaves no column to
    compare, so the defaults are the iRat 2011 settings (60 x 20 cells, shift 4, step 1)."""

    model_config = ConfigDict(extra="forbid")

    image_crop_x_min: int = Field(0, ge=0)
    image_crop_x_max: int = -1
    image_crop_y_min: int = Field(0, ge=0)
    image_crop_y_max: int = -1
    template_x_size: int = Field(60, ge=1)
    template_y_size: int = Field(20, ge=1)
    vt_shift_match: int = Field(4, ge=0)
    vt_step_match: int = Field(1, ge=1)
    vt_match_threshold: float = 0.03
    vt_normalisation: float = 0.0
    vt_patch_normalise: int = Field(0, ge=0)
    vt_min_patch_normalisation_std: float = 0.0
    vt_panoramic: bool = False
    openratslam_compat: bool = False


@njit(cache=True)
def _best_match(templates, keep, cur, shift, step, panoramic):  # pragma: no cover - compiled
    """(template, offset, summed absolute difference) of the best match over ``keep``.

    Non-panoramic: current columns [S, X-S) against template columns [off, off+X-2S), off = 0,
    step, .., 2S. Panoramic: current column c against template column (c+off) mod X, off = 0,
    step, .. < X, summed as the C++ does (columns [0, X-off) row by row, then [X-off, X)).
    A candidate stops once its partial sum exceeds the best (the C++'s "fast break"); only a
    strictly smaller sum replaces the best, so ties go to the first template and offset.
    """
    Y, X = cur.shape
    best = np.inf
    bt = -1
    bo = 0
    for ti in keep:
        if panoramic:
            for o in range(0, X, step):
                cd = 0.0
                for y in range(Y):
                    for c in range(X - o):
                        cd += abs(cur[y, c] - templates[ti, y, c + o])
                    if cd > best:
                        break
                if cd <= best:
                    for y in range(Y):
                        for c in range(X - o, X):
                            cd += abs(cur[y, c] - templates[ti, y, c + o - X])
                        if cd > best:
                            break
                if cd < best:
                    best, bt, bo = cd, ti, o
        else:
            W = X - 2 * shift
            for o in range(0, 2 * shift + 1, step):
                cd = 0.0
                for y in range(Y):
                    for k in range(W):
                        cd += abs(cur[y, shift + k] - templates[ti, y, o + k])
                    if cd > best:
                        break
                if cd < best:
                    best, bt, bo = cd, ti, o
    return bt, bo, best


def offset_rad(off: Any, x_size: int) -> np.ndarray:
    """A panoramic template's column offset as relative_rad, in (-pi, pi]."""
    rad = np.asarray(off, dtype=np.float64) / x_size * 2 * math.pi
    return np.where(rad > math.pi, rad - 2 * math.pi, rad)


def _seq_mean(t: np.ndarray) -> float:
    """Mean summed left to right, as the C++ loop does (np.mean's pairwise sum can differ in the
    last bit, which matters at the mean pre-filter's boundary)."""
    return float(np.cumsum(t.ravel())[-1]) / t.size


class LocalViewCells:
    """OpenRatSLAM's ``LocalViewMatch``: one template id (and relative_rad) per image."""

    @staticmethod
    def warm_up() -> None:
        """Compile (or load from numba's cache) the matching kernel before the first frame."""
        _best_match(np.zeros((1, 1, 4)), np.zeros(1, np.int64), np.zeros((1, 4)), 1, 1, False)

    def __init__(self, config: LocalViewConfig | None = None, **overrides: Any) -> None:
        self.config = c = make_config(LocalViewConfig, config, overrides)
        if not c.vt_panoramic and 2 * c.vt_shift_match >= c.template_x_size:
            raise ValueError(f"vt_shift_match {c.vt_shift_match} too large for template_x_size {c.template_x_size}")
        self._store = np.zeros((0, c.template_y_size, c.template_x_size))  # grows by doubling
        self._means = np.zeros(0)
        self._n = 0
        self.current_id = -1
        self.relative_rad = 0.0
        self.last_error = math.inf

    @property
    def templates(self) -> np.ndarray:
        """The stored templates, (n, template_y_size, template_x_size); row i is template id i."""
        return self._store[: self._n]

    @property
    def means(self) -> np.ndarray:
        return self._means[: self._n]

    def add_template(self, t: np.ndarray) -> int:
        """Store a template (as made by :meth:`view_template`) and return its id."""
        c = self.config
        t = np.asarray(t, dtype=np.float64)
        if t.shape != (c.template_y_size, c.template_x_size):
            raise ValueError(f"template shape {t.shape} != {(c.template_y_size, c.template_x_size)}")
        if self._n == self._store.shape[0]:
            cap = max(64, 2 * self._n)
            store, means = np.zeros((cap,) + t.shape), np.zeros(cap)
            store[: self._n], means[: self._n] = self.templates, self.means
            self._store, self._means = store, means
        self._store[self._n], self._means[self._n] = t, _seq_mean(t)
        self._n += 1
        return self._n - 1

    def view_template(self, grey: np.ndarray) -> np.ndarray:
        """HxW grey or HxWxC colour (0..255) -> the template_y_size x template_x_size template in [0, 1]."""
        c = self.config
        img = np.asarray(grey)
        if img.ndim not in (2, 3) or img.size == 0:
            raise InvalidInput(f"expected a grey (HxW) or colour (HxWxC) image, got shape {img.shape}")
        h, w = img.shape[:2]
        x1 = w if c.image_crop_x_max < 0 else min(c.image_crop_x_max, w)
        y1 = h if c.image_crop_y_max < 0 else min(c.image_crop_y_max, h)
        crop = img[c.image_crop_y_min:y1, c.image_crop_x_min:x1].astype(np.float64)
        scale = 255.0
        if crop.ndim == 3:  # the C++ sums the three channels and divides by 3 * 255
            crop, scale = crop.sum(axis=2), 255.0 * crop.shape[2]
        bh, bw = crop.shape[0] // c.template_y_size, crop.shape[1] // c.template_x_size
        if bh == 0 or bw == 0:
            raise InvalidInput(f"crop of {crop.shape[1]}x{crop.shape[0]} px is smaller than the "
                             f"{c.template_x_size}x{c.template_y_size} template")
        used = crop[: bh * c.template_y_size, : bw * c.template_x_size]
        # 8-bit pixels make every block sum an exact integer, so dividing in the C++'s order
        # (by 255, then by the block size) gives its values to the last bit
        t = used.reshape(c.template_y_size, bh, c.template_x_size, bw).sum(axis=(1, 3)) / scale / (bh * bw)
        if c.vt_normalisation > 0:
            m = _seq_mean(t)
            t = np.clip(t * c.vt_normalisation / m, 0, 1) if m > 0 else t
        if c.vt_patch_normalise > 0:
            t = self._patch_normalise(t, c.vt_patch_normalise)
        return t

    def _patch_normalise(self, t: np.ndarray, p: int) -> np.ndarray:
        """Local contrast over a (2p+1)^2 window whose indices are clamped to the template (edge
        cells repeat, and the window always counts (2p+1)^2 cells, as the C++):
        ((v - mean)/std + 3)/6 clipped to [0, 1]; 0.5 where std < vt_min_patch_normalisation_std."""
        win = sliding_window_view(np.pad(t, p, mode="edge"), (2 * p + 1, 2 * p + 1))
        mu = win.mean(axis=(2, 3))
        sd = np.sqrt(((win - mu[:, :, None, None]) ** 2).mean(axis=(2, 3)))
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.clip(((t - mu) / sd + 3.0) / 6.0, 0.0, 1.0)
        flat = sd == 0
        out[flat] = 1.0 if self.config.openratslam_compat else 0.5  # C++: min(1, NaN) is 1
        out[sd < self.config.vt_min_patch_normalisation_std] = 0.5
        return out

    def compare(self, t: np.ndarray) -> tuple[int, float, float]:
        """(best template, error, relative_rad) over all templates; (-1, inf, 0) when none qualifies."""
        c = self.config
        if len(self.templates) == 0:
            return -1, math.inf, 0.0
        keep = np.flatnonzero(np.abs(self.means - _seq_mean(t)) <= c.vt_match_threshold + MEAN_EPSILON)
        if keep.size == 0:
            return -1, math.inf, 0.0
        X, Y = c.template_x_size, c.template_y_size
        ti, off, total = _best_match(self._store, keep.astype(np.int64), np.ascontiguousarray(t),
                                     c.vt_shift_match, c.vt_step_match, c.vt_panoramic)
        if c.vt_panoramic:
            return int(ti), float(total / (X * Y)), float(offset_rad(off, X))
        return int(ti), float(total / (X * Y - 2 * c.vt_shift_match * Y)), 0.0

    def errors(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every template's mean absolute difference to ``t`` at its best offset, and that offset's
        relative_rad: :meth:`compare`'s comparison for all templates, without its mean pre-filter
        and early stop (what a decision from the run's own statistics needs)."""
        c = self.config
        temps = self.templates
        if temps.shape[0] == 0:
            return np.zeros(0), np.zeros(0)
        X = c.template_x_size
        if c.vt_panoramic:
            offs = list(range(0, X, c.vt_step_match))
            errs = np.stack([np.abs(t[None] - np.roll(temps, -o, axis=2)).mean(axis=(1, 2)) for o in offs])
        else:
            S, W = c.vt_shift_match, X - 2 * c.vt_shift_match
            offs = list(range(0, 2 * S + 1, c.vt_step_match))
            cur = t[:, S:S + W]
            errs = np.stack([np.abs(cur[None] - temps[:, :, o:o + W]).mean(axis=(1, 2)) for o in offs])
        best = np.argmin(errs, axis=0)
        rad = offset_rad(np.asarray(offs)[best], X) if c.vt_panoramic else np.zeros(temps.shape[0])
        return errs[best, np.arange(temps.shape[0])], rad

    def on_image(self, grey: np.ndarray) -> tuple[int, float]:
        """Template id for this image (existing or new) and its relative_rad."""
        t = self.view_template(grey)
        best, err, rad = self.compare(t)
        self.last_error = err
        if best >= 0 and err <= self.config.vt_match_threshold:
            self.current_id, self.relative_rad = best, rad
        else:
            self.current_id, self.relative_rad = self.add_template(t), 0.0
        return self.current_id, self.relative_rad

    def state_dict(self) -> dict[str, Any]:
        """The templates, (n, template_y_size, template_x_size), and the current id."""
        return {"templates": self.templates.copy(), "current": self.current_id}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; templates of another size are refused (ValueError)."""
        c = self.config
        store = np.array(st["templates"], dtype=float)
        if store.size == 0:
            store = store.reshape(0, c.template_y_size, c.template_x_size)
        if store.ndim != 3:
            raise ValueError(f"checkpoint's templates have shape {store.shape}, expected (n, y, x)")
        for field, got, want in (("template_y_size", store.shape[1], c.template_y_size),
                                 ("template_x_size", store.shape[2], c.template_x_size)):
            if got != want:
                raise ValueError(f"{field}: the checkpoint's is {got}, the config's {want}")
        self._store = store
        self._n = self._store.shape[0]
        # the C++ keeps the mean it computed when the template was made: the same sum, recomputed
        self._means = np.array([_seq_mean(t) for t in self._store])
        self.current_id = int(st["current"])
