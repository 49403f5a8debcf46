"""RatSLAM pose cells: a 3-D continuous attractor network (x, y, theta), as in OpenRatSLAM.

Per odometry message (``on_odo(vtrans, vrot, dt)``): excitation with a wrapped separable Gaussian
(pc_w_e_dim, pc_w_e_var), inhibition of the excited activity (pc_w_i_dim, pc_w_i_var), global
inhibition (pc_global_inhib), normalisation, path integration (translation by vtrans/pc_cell_x_size
cells along each theta layer's direction, rotation along theta), then the best pose (population
vector over the 7x7x7 window around the peak). Per view template (``on_view_template``): a new
template remembers the current best pose; a known one injects pc_vt_inject_energy*(30-exp(1.2 d))/30
at its pose, with d its decay (vt_active_decay, restored by pc_vt_restore). ``get_action`` then
creates, links or sets experiences (exp_delta_pc_threshold), once both an odometry and a template
update have arrived.

The activity array is ``P[th, y, x]``. Pose-cell space is a mirror of the map frame: translation
moves layer k by dx = v sin(theta_k), dy = v cos(theta_k) cells (as OpenRatSLAM).

``openratslam_compat=True`` reproduces the C++ exactly, quirks included; the default fixes them:

1. *Corner mass leak*: the C++ fold-back of the padded translation never adds two entries, so
   mass wrapping through one corner of each layer is lost (0.05-0.12 % per step). Fixed: an exact,
   mass-conserving bilinear shift on the torus.
2. *Unsigned guard*: "the 10 newest templates do not inject" is off while fewer than 10 templates
   exist (size_t wrap-round), so early templates inject immediately. Fixed: signed comparison, by
   creation order rather than by id (ids from a front end may skip).
3. *Truncated injection index*: the C++ casts the stored pose to int (MATLAB rounds) and silently
   skips an index equal to N. Fixed: rounded and wrapped onto the torus.
4. *No SET_NODE*: the C++ sends CREATE_EDGE even to an experience already linked to the current
   one (its SET_NODE branch is dead). Fixed: SET_NODE when the link exists.
5. *Stale relative rotation*: ``vt_delta_pc_th`` is only updated when a template injects, so a
   panoramic rotation keeps biasing delta_pc and the actions' relative_rad afterwards. Fixed: it
   follows the current view's relative_rad on every template message.

Template ids that skip or repeat never crash: an unknown id is a new template wherever it falls.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.ndimage import correlate1d

from .._config import make_config
from ..errors import InvalidInput
from .actions import CREATE_EDGE, CREATE_NODE, NO_ACTION, SET_NODE  # noqa: F401 (used here and re-exported)
from .odometry_bias import OdometryBiasConfig
from .odometry_gate import OdometryGateConfig

CELLS_TO_AVG = 3


class PoseCellConfig(BaseModel):
    """OpenRatSLAM's pose-cell parameters with the C++ code defaults."""

    model_config = ConfigDict(extra="forbid")

    pc_dim_xy: int = Field(21, ge=3)
    pc_dim_th: int = Field(36, ge=3)
    pc_w_e_dim: int = Field(7, ge=1)
    pc_w_e_var: int = Field(1, ge=1)
    pc_w_i_dim: int = Field(5, ge=1)
    pc_w_i_var: int = Field(2, ge=1)
    pc_global_inhib: float = 0.00002
    vt_active_decay: float = 1.0
    pc_vt_inject_energy: float = 0.15
    pc_cell_x_size: float = Field(1.0, gt=0)
    exp_delta_pc_threshold: float = 2.0
    pc_vt_restore: float = 0.05
    openratslam_compat: bool = False
    #: issue #14: templates whose place odometry cannot explain do not reach the network (used by
    #: the pose-cell node, see odometry_gate.py; radius_m 0 = off, OpenRatSLAM)
    odometry_gate: OdometryGateConfig = Field(default_factory=OdometryGateConfig)
    #: issue #14: the odometry's yaw-rate bias estimated from loop closures and subtracted (used by
    #: the pose-cell node, see odometry_bias.py; enabled false = off, OpenRatSLAM)
    odometry_bias: OdometryBiasConfig = Field(default_factory=OdometryBiasConfig)


def _wrapped_support(mask: np.ndarray, margin: int) -> np.ndarray | None:
    """Indices of the shortest circular arc holding every True of ``mask``, widened by ``margin``
    on both sides; None when that covers the whole circle (or nothing is active)."""
    n = mask.size
    on = np.flatnonzero(mask)
    if on.size == 0:
        return None
    # the arc is the complement of the largest circular gap between consecutive active indices
    gaps = np.diff(np.concatenate([on, on[:1] + n]))
    k = int(np.argmax(gaps))
    start = int(on[(k + 1) % on.size])
    length = n - int(gaps[k]) + 1
    if length + 2 * margin >= n:
        return None
    return (start - margin + np.arange(length + 2 * margin)) % n


def gaussian_1d(dim: int, var: int) -> np.ndarray:
    """Normalised 1-D kernel; the 3-D OpenRatSLAM kernel is its outer product (exactly separable)."""
    c = dim // 2
    g = np.exp(-((np.arange(dim) - c) ** 2) / (2.0 * var * var))
    return g / g.sum()


class PoseCellNetwork:
    """OpenRatSLAM's ``PosecellNetwork``: activity ``P[th, y, x]`` of pc_dim_th x pc_dim_xy^2 cells.

    Call :meth:`on_view_template` for every template message and :meth:`on_odo` for every odometry
    message, then :meth:`get_action` after each odometry step. ``best`` is the decoded pose (x, y,
    th in cell units), ``experiences`` the pose-cell side of the experience map.
    """

    def __init__(self, config: PoseCellConfig | None = None, **overrides: Any) -> None:
        self.cfg = self.config = make_config(PoseCellConfig, config, overrides)
        c = self.cfg
        self.N, self.T = c.pc_dim_xy, c.pc_dim_th
        self.C = 2 * math.pi / self.T
        self.w_e = gaussian_1d(c.pc_w_e_dim, c.pc_w_e_var)
        self.w_i = gaussian_1d(c.pc_w_i_dim, c.pc_w_i_var)
        self.P = np.zeros((self.T, self.N, self.N))
        self.best = (float(self.N // 2), float(self.N // 2), float(self.T // 2))  # x, y, th
        self.P[self.T // 2, self.N // 2, self.N // 2] = 1.0
        self.templates: dict[int, list[float]] = {}  # id -> [x, y, th, decay, creation rank]
        self.experiences: list[tuple[float, float, float, int]] = []  # x, y, th, vt
        self.template_exps: dict[int, list[int]] = {}
        self.links: set[tuple[int, int]] = set()
        self.current_exp = 0
        self.current_vt = 0
        self.prev_vt = 0
        self.vt_delta_pc_th = 0.0
        self.odo_update = False
        self.vt_update = False

    # ---------------------------------------------------------------- activity
    def _excite_inhibit(self) -> None:
        """Excitation P <- P (*) W_e, inhibition P <- P - P (*) W_i, global inhibition, normalisation.

        The packet occupies a small part of the torus, so the correlations run on the wrapped
        bounding box of the active cells plus the kernels' reach (pc_w_e_dim//2 + pc_w_i_dim//2) on
        each side, zero-padded: every product they skip is a product with an inactive cell, so the
        result equals the full wrapped correlation (axes where the box would cover the torus use
        the full axis with wrap-around).
        """
        P = self.P
        reach = self.cfg.pc_w_e_dim // 2 + self.cfg.pc_w_i_dim // 2
        active = P != 0
        idx = [_wrapped_support(active.any(axis=(1, 2)), reach),
               _wrapped_support(active.any(axis=(0, 2)), reach),
               _wrapped_support(active.any(axis=(0, 1)), reach)]
        full = all(i is None for i in idx)
        modes = ["wrap" if i is None else "constant" for i in idx]
        if full:
            sub = P
        else:
            box = np.ix_(*[np.arange(n) if i is None else i for i, n in zip(idx, P.shape, strict=True)])
            sub = P[box]
        for ax in range(3):
            sub = correlate1d(sub, self.w_e, axis=ax, mode=modes[ax])
        inh = sub
        for ax in range(3):
            inh = correlate1d(inh, self.w_i, axis=ax, mode=modes[ax])
        sub = sub - inh
        g = self.cfg.pc_global_inhib
        sub = np.where(sub >= g, sub - g, 0.0)
        total = sub.sum()
        if not total > 0:
            raise FloatingPointError("pose-cell activity vanished (every cell below pc_global_inhib)")
        sub /= total
        if full:
            self.P = sub
        else:
            self.P = np.zeros_like(P)
            self.P[box] = sub

    def _translate_compat(self, v: float, base: float) -> None:
        N = self.N
        out = np.zeros_like(self.P)
        for k in np.flatnonzero(self.P.reshape(self.T, -1).any(axis=1)):  # empty layers stay empty
            direction = k * self.C + base
            q = int(math.floor(direction * 2 / math.pi))
            layer = np.rot90(self.P[k], -q)
            d90 = direction - q * math.pi / 2
            a, b = v * math.sin(d90), v * math.cos(d90)
            pad = np.zeros((N + 2, N + 2))
            pad[1:N + 1, 1:N + 1] = layer
            new = ((1 - a) * (1 - b)) * pad
            new[:, 1:] += (a * (1 - b)) * pad[:, :-1]
            new[1:, :] += (b * (1 - a)) * pad[:-1, :]
            new[1:, 1:] += (a * b) * pad[:-1, :-1]
            res = new[1:N + 1, 1:N + 1].copy()
            res[0, 1:] += new[N + 1, 2:N + 1]
            res[1:, 0] += new[2:N + 1, N + 1]
            res[0, 0] += new[N + 1, N + 1]
            out[k] = np.rot90(res, q)
        self.P = out

    def _translate_exact(self, v: float, base: float) -> None:
        """Mass-conserving bilinear shift of every theta layer on the torus, vectorised.

        Layers are grouped by their integer shift (at most four groups for v <= 1) so each group
        is shifted by four rolls of a 3-D block; empty layers (most of them) are skipped.
        """
        P = self.P
        ks = np.flatnonzero(P.reshape(self.T, -1).any(axis=1))
        th = ks * self.C + base
        dx, dy = v * np.sin(th), v * np.cos(th)
        ix, iy = np.floor(dx).astype(int), np.floor(dy).astype(int)
        fx, fy = dx - ix, dy - iy
        out = np.zeros_like(P)
        for a, b in set(zip(ix.tolist(), iy.tolist(), strict=True)):
            m = (ix == a) & (iy == b)
            sel = ks[m]
            Q = P[sel]
            wx, wy = fx[m][:, None, None], fy[m][:, None, None]
            out[sel] = ((1 - wx) * (1 - wy) * np.roll(Q, (b, a), axis=(1, 2))
                        + wx * (1 - wy) * np.roll(Q, (b, a + 1), axis=(1, 2))
                        + (1 - wx) * wy * np.roll(Q, (b + 1, a), axis=(1, 2))
                        + wx * wy * np.roll(Q, (b + 1, a + 1), axis=(1, 2)))
        self.P = out

    def _rotate(self, vrot: float) -> None:
        ratio = abs(vrot) / self.C
        sign = 1 if vrot >= 0 else -1
        w = ratio - math.floor(ratio)
        if w == 0:
            w = 1.0
        s1, s2 = sign * math.floor(ratio), sign * math.ceil(ratio)
        self.P = (1 - w) * np.roll(self.P, s1, axis=0) + w * np.roll(self.P, s2, axis=0)

    def _path_integration(self, vtrans: float, vrot: float) -> None:
        v = vtrans / self.cfg.pc_cell_x_size
        base = 0.0
        if v < 0:
            v, base = -v, math.pi
        if v != 0:
            if self.cfg.openratslam_compat:
                self._translate_compat(v, base)
            else:
                self._translate_exact(v, base)
        if vrot != 0:
            self._rotate(vrot)

    def _find_best(self) -> None:
        T, N = self.T, self.N
        k, j, i = np.unravel_index(int(np.argmax(self.P)), self.P.shape)
        r = np.arange(-CELLS_TO_AVG, CELLS_TO_AVG + 1)
        ks, js, is_ = (k + r) % T, (j + r) % N, (i + r) % N
        cube = self.P[np.ix_(ks, js, is_)]
        x_sums = np.zeros(N)
        y_sums = np.zeros(N)
        th_sums = np.zeros(T)
        np.add.at(x_sums, is_, cube.sum(axis=(0, 1)))
        np.add.at(y_sums, js, cube.sum(axis=(0, 2)))
        np.add.at(th_sums, ks, cube.sum(axis=(1, 2)))

        def decode(s: np.ndarray, n: int) -> float:
            ang = 2 * math.pi * (np.arange(n) + 1) / n
            v = math.atan2(float(np.dot(np.sin(ang), s)), float(np.dot(np.cos(ang), s))) * n / (2 * math.pi) - 1
            while v < 0:
                v += n
            while v > n:
                v -= n
            return v

        self.best = (decode(x_sums, N), decode(y_sums, N), decode(th_sums, T))

    def on_odo(self, vtrans: float, vrot: float, dt: float) -> None:
        """One odometry step: vtrans (m/s) and vrot (rad/s) over dt seconds."""
        if not (math.isfinite(vtrans) and math.isfinite(vrot) and math.isfinite(dt)):
            raise InvalidInput(f"odometry must be finite, got vtrans={vtrans} vrot={vrot} dt={dt}")
        self._excite_inhibit()
        self._path_integration(vtrans * dt, vrot * dt)
        self._find_best()
        self.odo_update = True

    # ---------------------------------------------------------------- templates
    def on_view_template(self, vt: int, rad: float = 0.0) -> None:
        """View template ``vt`` seen with relative rotation ``rad`` (vt_rad, panoramic front ends).

        A new id stores the current best pose with decay = vt_active_decay. A known template that
        is not among the 10 newest injects E = pc_vt_inject_energy/30 * (30 - exp(1.2 decay)) at its
        pose, theta shifted by rad/(2 pi)*pc_dim_th; its decay grows by vt_active_decay while it
        stays current. Every template's decay then relaxes by pc_vt_restore (floor vt_active_decay).
        """
        c = self.cfg
        vt = int(vt)
        if vt < 0:
            raise InvalidInput(f"template id must be >= 0, got {vt}")
        if not math.isfinite(rad):
            raise InvalidInput(f"relative_rad must be finite, got {rad}")
        if not c.openratslam_compat:
            # fix 5: the C++ only updates vt_delta_pc_th when injecting, so a stale rotation
            # leaks into delta_pc and into later actions' relative_rad
            self.vt_delta_pc_th = rad / (2 * math.pi) * self.T
        if vt not in self.templates:
            self.templates[vt] = [self.best[0], self.best[1], self.best[2], c.vt_active_decay,
                                  float(len(self.templates))]
        else:
            t = self.templates[vt]
            size = len(self.templates)
            if c.openratslam_compat:
                guard = size < 10 or vt < size - 10  # size_t wrap-round: no guard below 10 templates
            else:
                guard = t[4] < size - 10  # by creation order, so that skipped ids do not matter
            if guard:
                if vt == self.current_vt:
                    t[3] += c.vt_active_decay
                # operation order as the C++, so that compat mode agrees to the last bit
                energy = c.pc_vt_inject_energy * 1.0 / 30.0 * (30.0 - math.exp(1.2 * t[3]))
                if energy > 0:
                    self.vt_delta_pc_th = rad / (2 * math.pi) * self.T
                    th_c = t[2] + self.vt_delta_pc_th
                    if th_c < 0:
                        th_c += self.T
                    if th_c >= self.T:
                        th_c -= self.T
                    if c.openratslam_compat:
                        ix, iy, ik = int(t[0]), int(t[1]), int(th_c)
                        if 0 <= ix < self.N and 0 <= iy < self.N and 0 <= ik < self.T:
                            self.P[ik, iy, ix] += energy
                    else:
                        ix, iy, ik = round(t[0]) % self.N, round(t[1]) % self.N, round(th_c) % self.T
                        self.P[ik, iy, ix] += energy
        for t in self.templates.values():
            t[3] = max(c.vt_active_decay, t[3] - c.pc_vt_restore)
        self.prev_vt = self.current_vt
        self.current_vt = vt
        self.vt_update = True

    # ---------------------------------------------------------------- actions
    def _delta_pc(self, e: int) -> float:
        x, y, th = self.best
        ex, ey, eth, _ = self.experiences[e]
        th = th - self.vt_delta_pc_th

        def circ(a: float, b: float, n: int) -> float:
            d = abs(a - b)
            return min(d, n - d)

        return math.sqrt(circ(x, ex, self.N) ** 2 + circ(y, ey, self.N) ** 2 + circ(th, eth, self.T) ** 2)

    def _create_experience(self) -> int:
        self.experiences.append((self.best[0], self.best[1], self.best[2], self.current_vt))
        e = len(self.experiences) - 1
        self.template_exps.setdefault(self.current_vt, []).append(e)
        return e

    def get_action(self) -> tuple[int, int, int, float]:
        """(action, src experience, dst experience, relative_rad) after an update."""
        src = self.current_exp
        action = NO_ACTION
        if self.odo_update and self.vt_update:
            self.odo_update = self.vt_update = False
            if self.templates:
                thr = self.cfg.exp_delta_pc_threshold
                if not self.experiences or not self.template_exps.get(self.current_vt):
                    new = self._create_experience()
                    if self.experiences and len(self.experiences) > 1:
                        self.links.add((src, new))
                    self.current_exp = new
                    action = CREATE_NODE
                elif self._delta_pc(self.current_exp) > thr or self.current_vt != self.prev_vt:
                    best_e, best_d = -1, math.inf
                    for e in self.template_exps[self.current_vt]:
                        if e == self.current_exp:
                            continue
                        d = self._delta_pc(e)
                        if d < best_d:
                            best_e, best_d = e, d
                    if best_e >= 0 and best_d < thr:
                        linked = (src, best_e) in self.links or (best_e, src) in self.links
                        action = SET_NODE if (linked and not self.cfg.openratslam_compat) else CREATE_EDGE
                        self.links.add((src, best_e))
                        self.current_exp = best_e
                    else:
                        new = self._create_experience()
                        self.links.add((src, new))
                        self.current_exp = new
                        action = CREATE_NODE
        return action, src, self.current_exp, self.vt_delta_pc_th * 2 * math.pi / self.T

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        return {"P": self.P.copy(), "best": list(self.best),
                "templates": {str(k): v for k, v in self.templates.items()},
                "experiences": [list(e) for e in self.experiences],
                "template_exps": {str(k): v for k, v in self.template_exps.items()},
                "links": [list(lk) for lk in sorted(self.links)],
                "scalars": [self.current_exp, self.current_vt, self.prev_vt, self.vt_delta_pc_th,
                            int(self.odo_update), int(self.vt_update)]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.P = np.array(st["P"], dtype=float)
        self.best = tuple(float(v) for v in st["best"])
        self.templates = {int(k): [float(x) for x in v] for k, v in st["templates"].items()}
        self.experiences = [(float(e[0]), float(e[1]), float(e[2]), int(e[3])) for e in st["experiences"]]
        self.template_exps = {int(k): [int(x) for x in v] for k, v in st["template_exps"].items()}
        self.links = {(int(a), int(b)) for a, b in st["links"]}
        ce, cv, pv, d, ou, vu = st["scalars"]
        self.current_exp, self.current_vt, self.prev_vt = int(ce), int(cv), int(pv)
        self.vt_delta_pc_th, self.odo_update, self.vt_update = float(d), bool(ou), bool(vu)
