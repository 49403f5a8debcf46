"""RatSLAM pose cells: a 3-D continuous attractor network ``P[th, y, x]`` on a torus, as
OpenRatSLAM's ``PosecellNetwork``.

``on_odo``: excitation (pc_w_e_dim, pc_w_e_var), inhibition of the excited activity (pc_w_i_dim,
pc_w_i_var), global inhibition (pc_global_inhib), normalisation, path integration (vtrans /
pc_cell_x_size cells along each theta layer's direction, dx = v sin(theta_k), dy = v cos(theta_k):
pose-cell space mirrors the map frame; vrot along theta), then the best pose (population vector
over the 7x7x7 window around the peak). ``on_view_template``: a new template stores the best pose;
a known one injects pc_vt_inject_energy * (30 - exp(1.2 d)) / 30 there, d its decay
(vt_active_decay, pc_vt_restore). ``get_action`` creates, links or sets experiences
(exp_delta_pc_threshold) once both an odometry and a template update have arrived.

``openratslam_compat=True`` reproduces the C++ with its quirks; the default fixes five of them,
marked "fix n" below and tabled in docs/ratslam.md. An unknown or skipped template id never
crashes: it is a new template.
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
        self.config = c = make_config(PoseCellConfig, config, overrides)
        N, T = c.pc_dim_xy, c.pc_dim_th
        self.w_e = gaussian_1d(c.pc_w_e_dim, c.pc_w_e_var)
        self.w_i = gaussian_1d(c.pc_w_i_dim, c.pc_w_i_var)
        self.P = np.zeros((T, N, N))
        self.best = (float(N // 2), float(N // 2), float(T // 2))  # x, y, th
        self.P[T // 2, N // 2, N // 2] = 1.0
        self.templates: dict[int, list[float]] = {}  # id -> [x, y, th, decay, creation rank]
        # the decay relaxes on every template step, for every template; it is applied lazily (on
        # a template's next use, one step at a time: the same floats) so that a step costs O(1),
        # not O(templates): the template steps done, and the last step each decay is up to date with
        self._vt_steps = 0
        self._decay_step: dict[int, int] = {}
        self.experiences: list[tuple[float, float, float, int]] = []  # x, y, th, vt
        self.template_exps: dict[int, list[int]] = {}
        self.links: set[tuple[int, int]] = set()
        self.current_exp = 0
        self.current_vt = 0
        self.prev_vt = 0
        self.vt_delta_pc_th = 0.0
        self.odo_update = False
        self.vt_update = False
        #: a new session on a stored map waits for its first recognised place (:meth:`new_session`):
        #: whether it still waits, and how many templates the earlier sessions made
        self.lost = False
        self.session_templates = 0

    @property
    def C(self) -> float:
        """The angle of one theta layer, 2 pi / pc_dim_th."""
        return 2 * math.pi / self.config.pc_dim_th

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
        reach = self.config.pc_w_e_dim // 2 + self.config.pc_w_i_dim // 2
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
        g = self.config.pc_global_inhib
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
        T, N = self.config.pc_dim_th, self.config.pc_dim_xy
        out = np.zeros_like(self.P)
        for k in np.flatnonzero(self.P.reshape(T, -1).any(axis=1)):  # empty layers stay empty
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
        """Fix 1: a mass-conserving bilinear shift of every theta layer on the torus (the C++'s
        fold-back of the padded shift loses what wraps through one corner), vectorised.

        Layers are grouped by their integer shift (at most four groups for v <= 1) so each group
        is shifted by four rolls of a 3-D block; empty layers (most of them) are skipped.
        """
        P = self.P
        ks = np.flatnonzero(P.reshape(self.config.pc_dim_th, -1).any(axis=1))
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
        v = vtrans / self.config.pc_cell_x_size
        base = 0.0
        if v < 0:
            v, base = -v, math.pi
        if v != 0:
            if self.config.openratslam_compat:
                self._translate_compat(v, base)
            else:
                self._translate_exact(v, base)
        if vrot != 0:
            self._rotate(vrot)

    def _find_best(self) -> None:
        T, N = self.config.pc_dim_th, self.config.pc_dim_xy
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
        c = self.config
        N, T = c.pc_dim_xy, c.pc_dim_th
        vt = int(vt)
        if vt < 0:
            raise InvalidInput(f"template id must be >= 0, got {vt}")
        if not math.isfinite(rad):
            raise InvalidInput(f"relative_rad must be finite, got {rad}")
        if not c.openratslam_compat:
            # fix 5: the C++ only updates vt_delta_pc_th when injecting, so a stale rotation
            # leaks into delta_pc and into later actions' relative_rad
            self.vt_delta_pc_th = rad / (2 * math.pi) * T
        if vt not in self.templates:
            self.templates[vt] = [self.best[0], self.best[1], self.best[2], c.vt_active_decay,
                                  float(len(self.templates))]
            self._decay_step[vt] = self._vt_steps - 1
        elif self.lost and self.templates[vt][4] < self.session_templates:
            self._relocalise(self._decayed(vt), rad)
        else:
            t = self._decayed(vt)
            size = len(self.templates)
            if c.openratslam_compat:
                guard = size < 10 or vt < size - 10  # size_t wrap-round: no guard below 10 templates
            else:
                guard = t[4] < size - 10  # fix 2: signed, by creation order (ids may skip)
            if guard:
                if vt == self.current_vt:
                    t[3] += c.vt_active_decay
                # operation order as the C++, so that compat mode agrees to the last bit
                energy = c.pc_vt_inject_energy * 1.0 / 30.0 * (30.0 - math.exp(1.2 * t[3]))
                if energy > 0:
                    self.vt_delta_pc_th = rad / (2 * math.pi) * T
                    th_c = t[2] + self.vt_delta_pc_th
                    if th_c < 0:
                        th_c += T
                    if th_c >= T:
                        th_c -= T
                    if c.openratslam_compat:
                        ix, iy, ik = int(t[0]), int(t[1]), int(th_c)
                        if 0 <= ix < N and 0 <= iy < N and 0 <= ik < T:
                            self.P[ik, iy, ix] += energy
                    else:  # fix 3: rounded and wrapped (the C++ truncates and skips an index of N)
                        ix, iy, ik = round(t[0]) % N, round(t[1]) % N, round(th_c) % T
                        self.P[ik, iy, ix] += energy
        # this step's relaxation of every decay (the others' when they are next used)
        t = self.templates[vt]
        t[3] = max(c.vt_active_decay, t[3] - c.pc_vt_restore)
        self._decay_step[vt] = self._vt_steps
        self._vt_steps += 1
        self.prev_vt = self.current_vt
        self.current_vt = vt
        self.vt_update = True

    def _relocalise(self, t: list[float], rad: float) -> None:
        """The packet starts afresh at template ``t``'s pose (its heading turned by ``rad``), as the
        network starts a run: one active cell."""
        N, T = self.config.pc_dim_xy, self.config.pc_dim_th
        th = (t[2] + rad / (2 * math.pi) * T) % T
        self.P = np.zeros_like(self.P)
        self.P[round(th) % T, round(t[1]) % N, round(t[0]) % N] = 1.0
        self.best = (t[0], t[1], th)
        self.lost = False

    def new_session(self) -> None:
        """A new session on a stored map: where the robot is, nothing says until it recognises a
        place of an earlier session. Until then the packet stays where it was (the new session's
        own places are laid out around it, and the experience map keeps them apart from the old
        map); the first template of an earlier session that comes back puts the packet at that
        template's pose, so that the next action links the new session's places to that
        template's experience. No experience is current: the old session's last one is not where
        the new session starts."""
        self.lost = True
        self.session_templates = len(self.templates)
        self.current_exp = -1

    def _decayed(self, vt: int) -> list[float]:
        """Template vt with its decay relaxed by pc_vt_restore for every template step since it was
        last up to date (floor vt_active_decay), one step at a time as the steps would have."""
        t = self.templates[vt]
        c = self.config
        # a template set directly (not through this method) counts as up to date
        for _ in range(self._vt_steps - 1 - self._decay_step.get(vt, self._vt_steps - 1)):
            d = max(c.vt_active_decay, t[3] - c.pc_vt_restore)
            if d == t[3]:  # at the floor (or a step too small to change it): no later step moves it
                break
            t[3] = d
        self._decay_step[vt] = self._vt_steps - 1
        return t

    # ---------------------------------------------------------------- actions
    def _delta_pc(self, e: int) -> float:
        x, y, th = self.best
        ex, ey, eth, _ = self.experiences[e]
        th = th - self.vt_delta_pc_th

        def circ(a: float, b: float, n: int) -> float:
            d = abs(a - b)
            return min(d, n - d)

        N, T = self.config.pc_dim_xy, self.config.pc_dim_th
        return math.sqrt(circ(x, ex, N) ** 2 + circ(y, ey, N) ** 2 + circ(th, eth, T) ** 2)

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
                thr = self.config.exp_delta_pc_threshold
                if not self.experiences or not self.template_exps.get(self.current_vt):
                    new = self._create_experience()
                    if self.experiences and len(self.experiences) > 1 and src >= 0:
                        self.links.add((src, new))
                    self.current_exp = new
                    action = CREATE_NODE
                elif (self.current_exp < 0 or self._delta_pc(self.current_exp) > thr
                      or self.current_vt != self.prev_vt):
                    best_e, best_d = -1, math.inf
                    for e in self.template_exps[self.current_vt]:
                        if e == self.current_exp:
                            continue
                        d = self._delta_pc(e)
                        if d < best_d:
                            best_e, best_d = e, d
                    if best_e >= 0 and best_d < thr:
                        linked = (src, best_e) in self.links or (best_e, src) in self.links
                        # fix 4: SET_NODE when the link exists (the C++'s SET_NODE branch is dead)
                        action = SET_NODE if (linked and not self.config.openratslam_compat) else CREATE_EDGE
                        self.links.add((src, best_e))
                        self.current_exp = best_e
                    else:
                        new = self._create_experience()
                        if src >= 0:
                            self.links.add((src, new))
                        self.current_exp = new
                        action = CREATE_NODE
        return action, src, self.current_exp, self.vt_delta_pc_th * 2 * math.pi / self.config.pc_dim_th

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """The network's state; the activity's shape records pc_dim_th and pc_dim_xy."""
        for vt in self.templates:  # every decay up to date
            self._decayed(vt)
        return {"P": self.P.copy(), "best": list(self.best),
                "templates": {str(k): list(v) for k, v in self.templates.items()},
                "experiences": [list(e) for e in self.experiences],
                "template_exps": {str(k): v for k, v in self.template_exps.items()},
                "links": [list(lk) for lk in sorted(self.links)],
                "scalars": [self.current_exp, self.current_vt, self.prev_vt, self.vt_delta_pc_th,
                            int(self.odo_update), int(self.vt_update)],
                "session": [int(self.lost), self.session_templates]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; a checkpoint of another network size is refused (ValueError)."""
        P = np.array(st["P"], dtype=float)
        c = self.config
        if P.ndim != 3:
            raise ValueError(f"checkpoint's pose-cell activity has shape {P.shape}, expected (th, y, x)")
        for field, got, want in (("pc_dim_th", P.shape[0], c.pc_dim_th), ("pc_dim_xy", P.shape[1], c.pc_dim_xy),
                                 ("pc_dim_xy", P.shape[2], c.pc_dim_xy)):
            if got != want:
                raise ValueError(f"{field}: the checkpoint's is {got}, the config's {want}")
        self.P = P
        self.best = tuple(float(v) for v in st["best"])
        self.templates = {int(k): [float(x) for x in v] for k, v in st["templates"].items()}
        self._vt_steps = 0
        self._decay_step = {vt: -1 for vt in self.templates}
        self.experiences = [(float(e[0]), float(e[1]), float(e[2]), int(e[3])) for e in st["experiences"]]
        self.template_exps = {int(k): [int(x) for x in v] for k, v in st["template_exps"].items()}
        self.links = {(int(a), int(b)) for a, b in st["links"]}
        ce, cv, pv, d, ou, vu = st["scalars"]
        self.current_exp, self.current_vt, self.prev_vt = int(ce), int(cv), int(pv)
        self.vt_delta_pc_th, self.odo_update, self.vt_update = float(d), bool(ou), bool(vu)
        lost, known = st.get("session", (0, 0))  # maps exported before sessions were kept: not lost
        self.lost, self.session_templates = bool(lost), int(known)
