"""RatSLAM's local-view cells (the baseline front end): image templates matched by SAD.

Template of an image: grey levels (colour averaged), crop ``[image_crop_x_min, x_max)`` columns x
``[image_crop_y_min, y_max)`` rows (-1 = to the edge), block means of ``floor(w/X) x floor(h/Y)``
pixels into ``template_x_size x template_y_size`` (leftover pixels ignored, as OpenRatSLAM), scaled
to [0, 1]; optional global normalisation (``vt_normalisation``) and local patch normalisation
(``vt_patch_normalise``).

Matching against all stored templates at once (numpy broadcasting): templates whose mean differs
by more than ``vt_match_threshold + 0.005`` are skipped; non-panoramic mode compares the central
columns ``[S, X-S)`` with every shift ``0, step, .., 2S`` of the template (S = vt_shift_match), error
= mean absolute difference; panoramic mode tries every circular shift and reports it as
``relative_rad``. The lowest error wins (first template, first shift on ties); at most
``vt_match_threshold`` is a match, otherwise a new template is created (ids from 0).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class LocalViewConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    image_crop_x_min: int = Field(0, ge=0)
    image_crop_x_max: int = -1
    image_crop_y_min: int = Field(0, ge=0)
    image_crop_y_max: int = -1
    template_x_size: int = Field(1, ge=1)
    template_y_size: int = Field(1, ge=1)
    vt_shift_match: int = Field(25, ge=0)
    vt_step_match: int = Field(5, ge=1)
    vt_match_threshold: float = 0.03
    vt_normalisation: float = 0.0
    vt_patch_normalise: int = Field(0, ge=0)
    vt_min_patch_normalisation_std: float = 0.0
    vt_panoramic: bool = False


class LocalViewCells:
    def __init__(self, **params: Any) -> None:
        self.cfg = LocalViewConfig(**params)
        c = self.cfg
        if not c.vt_panoramic and 2 * c.vt_shift_match >= c.template_x_size:
            raise ValueError(f"vt_shift_match {c.vt_shift_match} too large for template_x_size {c.template_x_size}")
        self.templates = np.zeros((0, c.template_y_size, c.template_x_size))
        self.means = np.zeros(0)
        self.current_id = -1
        self.relative_rad = 0.0
        self.last_error = math.inf

    def view_template(self, grey: np.ndarray) -> np.ndarray:
        """HxW grey (0..255) -> the Y x X template in [0, 1]."""
        c = self.cfg
        img = np.asarray(grey, dtype=np.float64)
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.ndim != 2:
            raise ValueError(f"expected a grey or colour image, got shape {img.shape}")
        h, w = img.shape
        x1 = w if c.image_crop_x_max < 0 else min(c.image_crop_x_max, w)
        y1 = h if c.image_crop_y_max < 0 else min(c.image_crop_y_max, h)
        crop = img[c.image_crop_y_min:y1, c.image_crop_x_min:x1]
        bh, bw = crop.shape[0] // c.template_y_size, crop.shape[1] // c.template_x_size
        if bh == 0 or bw == 0:
            raise ValueError(f"crop of {crop.shape[1]}x{crop.shape[0]} px is smaller than the "
                             f"{c.template_x_size}x{c.template_y_size} template")
        used = crop[: bh * c.template_y_size, : bw * c.template_x_size]
        t = used.reshape(c.template_y_size, bh, c.template_x_size, bw).mean(axis=(1, 3)) / 255.0
        if c.vt_normalisation > 0:
            m = t.mean()
            t = np.clip(t * c.vt_normalisation / m, 0, 1) if m > 0 else t
        if c.vt_patch_normalise > 0:
            t = self._patch_normalise(t, c.vt_patch_normalise)
        return t

    def _patch_normalise(self, t: np.ndarray, p: int) -> np.ndarray:
        Y, X = t.shape
        out = np.empty_like(t)
        for yy in range(Y):
            for xx in range(X):
                win = t[max(0, yy - p):min(Y, yy + p + 1), max(0, xx - p):min(X, xx + p + 1)]
                mu, sd = win.mean(), win.std()
                if sd < self.cfg.vt_min_patch_normalisation_std or sd == 0:
                    out[yy, xx] = 0.5
                else:
                    out[yy, xx] = min(1.0, max(0.0, ((t[yy, xx] - mu) / sd + 3) / 6))
        return out

    def compare(self, t: np.ndarray) -> tuple[int, float, float]:
        """(best template, error, relative_rad) over all templates; (-1, inf, 0) when none qualifies."""
        c = self.cfg
        if len(self.templates) == 0:
            return -1, math.inf, 0.0
        keep = np.flatnonzero(np.abs(self.means - t.mean()) <= c.vt_match_threshold + 0.005)
        if keep.size == 0:
            return -1, math.inf, 0.0
        cand = self.templates[keep]
        X, Y = c.template_x_size, c.template_y_size
        if c.vt_panoramic:
            offs = np.arange(0, X, c.vt_step_match)
            errs = np.stack([np.abs(t[None] - np.roll(cand, -o, axis=2)).sum(axis=(1, 2)) for o in offs], axis=1)
            errs /= X * Y
        else:
            S = c.vt_shift_match
            offs = np.arange(0, 2 * S + 1, c.vt_step_match)
            cur = t[:, S:X - S]
            errs = np.stack([np.abs(cur[None] - cand[:, :, o:o + X - 2 * S]).sum(axis=(1, 2)) for o in offs], axis=1)
            errs /= X * Y - 2 * S * Y
        flat = int(np.argmin(errs))  # row-major: first template, then first offset, on ties
        ti, oi = divmod(flat, errs.shape[1])
        rad = 0.0
        if c.vt_panoramic:
            rad = offs[oi] / X * 2 * math.pi
            if rad > math.pi:
                rad -= 2 * math.pi
        return int(keep[ti]), float(errs[ti, oi]), rad

    def on_image(self, grey: np.ndarray) -> tuple[int, float]:
        """Template id for this image (existing or new) and its relative_rad."""
        t = self.view_template(grey)
        best, err, rad = self.compare(t)
        self.last_error = err
        if best >= 0 and err <= self.cfg.vt_match_threshold:
            self.current_id, self.relative_rad = best, rad
        else:
            self.templates = np.concatenate([self.templates, t[None]])
            self.means = np.append(self.means, t.mean())
            self.current_id, self.relative_rad = len(self.templates) - 1, 0.0
        return self.current_id, self.relative_rad

    def state_dict(self) -> dict[str, Any]:
        return {"templates": self.templates.copy(), "means": self.means.copy(), "current": self.current_id}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.templates = np.array(st["templates"], dtype=float).reshape(
            -1, self.cfg.template_y_size, self.cfg.template_x_size)
        self.means = np.array(st["means"], dtype=float)
        self.current_id = int(st["current"])
