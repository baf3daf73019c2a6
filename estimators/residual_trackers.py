"""Online trackers of the live field-vector test (estimators.field_consistency), each learned from
the changes of the residual over a short lag, so that a body offset (constant over the lag) never
teaches them anything: the motor field per unit of the motor signal (``MotorFieldTracker``; the
offline fits are estimators.motor_field) and the magnetometer's tilt against the attitude's axes
(``TiltTracker``).  Pure, plain floats.
"""
from __future__ import annotations

import math
from collections import deque

__all__ = ["MotorFieldTracker", "TiltTracker"]


def _lagged(hist: deque, row: tuple, lag_s: float) -> tuple | None:
    """Append ``row`` (its time first) to ``hist`` and return the newest row at least ``lag_s``
    older (None while the history is shorter): the other end of the change both trackers learn from."""
    t_s = row[0]
    hist.append(row)
    while len(hist) > 2 and hist[1][0] <= t_s - lag_s:
        hist.popleft()
    return hist[0] if hist[0][0] <= t_s - lag_s else None


def _huber(y: float, pred: float, clip: float) -> float:
    """``y`` with its departure from ``pred`` clipped at ``clip`` (Huber)."""
    return pred + min(max(y - pred, -clip), clip)


class MotorFieldTracker:
    """Online field per unit of the motor signal from its changes (for the live field-vector test).

    Over a short lag L the Earth part of the field barely changes outside turns, so the change of
    u = m − Cᵀh (measured minus the predicted Earth field, body frame [mG]) is the motor field's:
        y = u(t) − u(t − L) = f · (x(t) − x(t − L)) + noise,
    independent of the body offset and of a steady heading error.  f is the exponentially weighted
    least-squares slope per axis, f_k = Σ w z y_k / (Σ w z² + reg) with z = x(t) − x(t − L), the
    weights forgetting with ``memory_s``, each y_k Huber-clipped at ``clip_mG`` around f_k z (a
    disturbance that starts while the current changes does not teach it much).  ``excitation`` is
    Σ z² Δt [unit² s], how much signal change f has been learned from.
    Uncertainty: the weighted least-squares standard error per axis, sd_k = √(s²_k / (Σ w z² + reg))
    with s²_k = Σ w (y_k − f_k z)² / Σ w the weighted mean square of the (clipped) fit residual, so
    the noise of the field's change, a lag of the current sensor and a coarse (1-2 Hz, held) current
    all widen it; ``significant`` (|f| ≥ k |sd|) says whether f should be removed from the field.
    Units: mG, A (or %), s.
    """

    def __init__(self, lag_s: float = 1.0, memory_s: float = 300.0, reg: float = 1.0) -> None:
        self.lag_s, self.memory_s, self.reg = lag_s, memory_s, reg
        self.f = [0.0, 0.0, 0.0]
        self.sd = [math.inf, math.inf, math.inf]
        self.excitation = 0.0
        self._sxx = 0.0
        self._sxy = [0.0, 0.0, 0.0]
        self._see = [0.0, 0.0, 0.0]
        self._sw = 0.0
        self._hist: deque = deque()

    def significant(self, k_sigma: float = 3.0) -> bool:
        """|f| ≥ k_sigma · |sd|: the motor field is known well enough to be removed."""
        f2 = self.f[0] ** 2 + self.f[1] ** 2 + self.f[2] ** 2
        sd2 = self.sd[0] ** 2 + self.sd[1] ** 2 + self.sd[2] ** 2
        return f2 > 0.0 and f2 >= k_sigma * k_sigma * sd2

    def clear_history(self) -> None:
        """Forget the recent samples (after a gap), keep what has been learned."""
        self._hist.clear()

    def update(self, t_s: float, u_mG, x: float, dt_s: float, learn: bool, clip_mG: float) -> None:
        """One step: u = m − Cᵀh [mG], signal x (NaN: none); learns only when ``learn``."""
        if not math.isfinite(x):
            self._hist.clear()
            return
        old = _lagged(self._hist, (t_s, float(u_mG[0]), float(u_mG[1]), float(u_mG[2]), x), self.lag_s)
        if not learn or old is None:
            return
        z = x - old[4]
        w = math.exp(-dt_s / self.memory_s)
        self._sxx = w * self._sxx + z * z * dt_s
        self._sw = w * self._sw + dt_s
        self.excitation += z * z * dt_s
        for k in range(3):
            pred = self.f[k] * z
            y = _huber(float(u_mG[k]) - old[k + 1], pred, clip_mG)
            self._see[k] = w * self._see[k] + (y - pred) ** 2 * dt_s
            self._sxy[k] = w * self._sxy[k] + z * y * dt_s
            self.f[k] = self._sxy[k] / (self._sxx + self.reg)
            if self._sw > 0.0:
                self.sd[k] = math.sqrt(self._see[k] / self._sw / (self._sxx + self.reg))


class TiltTracker:
    """Online tilt δ = (δ_x, δ_y) [rad] of the magnetometer against the attitude's body axes.

    The field the tilted sensor measures is R(δ) p ≈ p + δ × p (p = Cᵀh, the predicted Earth field in
    the body frame [mG]), so the part of the residual u = m − p − b − f·Δx that a tilt explains
    changes over a short lag L only when p does (the nose turning):
        y = u(t) − u(t − L) = δ × Δp + noise = A δ,  Δp = p(t) − p(t − L),  A = −[Δp×] (x, y columns)
    (a body offset cancels; a heading error of the attitude, a rotation about z, is the third
    column, left out).  δ is the exponentially weighted least-squares solution of the 2 × 2 normal
    equations (Σ w AᵀA + reg I) δ = Σ w Aᵀy, the weights forgetting with ``memory_s``, each y
    Huber-clipped at ``clip_mG`` around A δ, δ at most ``max_rad`` per axis.  ``reg`` [mG² s] holds δ
    at 0 until the heading has turned enough.  Units: rad, mG, s.
    """

    def __init__(self, lag_s: float = 2.0, memory_s: float = 300.0, reg: float = 1.0e4,
                 max_rad: float = 0.087) -> None:
        self.lag_s, self.memory_s, self.reg, self.max_rad = lag_s, memory_s, reg, max_rad
        self.tilt_rad = [0.0, 0.0]
        self._s = [0.0, 0.0, 0.0]          # Σ w AᵀA: xx, xy, yy
        self._r = [0.0, 0.0]               # Σ w Aᵀy
        self._hist: deque = deque()

    def clear_history(self) -> None:
        """Forget the recent samples (after a gap), keep what has been learned."""
        self._hist.clear()

    def update(self, t_s: float, p_mG, u_mG, dt_s: float, learn: bool, clip_mG: float) -> None:
        """One step: p = Cᵀh and u = m − p − b − f·Δx (no tilt term) [mG]; learns only when ``learn``."""
        old = _lagged(self._hist, (t_s, float(p_mG[0]), float(p_mG[1]), float(p_mG[2]),
                                   float(u_mG[0]), float(u_mG[1]), float(u_mG[2])), self.lag_s)
        if not learn or old is None:
            return
        dpx, dpy, dpz = (float(p_mG[k]) - old[k + 1] for k in range(3))
        a_x = (0.0, -dpz, dpy)             # e_x × Δp: the residual change per radian of δ_x
        a_y = (dpz, 0.0, -dpx)             # e_y × Δp
        tx, ty = self.tilt_rad
        w = math.exp(-dt_s / self.memory_s)
        s, r = self._s, self._r
        s[0] = w * s[0] + dt_s * (a_x[1] * a_x[1] + a_x[2] * a_x[2])
        s[1] = w * s[1] + dt_s * (a_x[2] * a_y[2])
        s[2] = w * s[2] + dt_s * (a_y[0] * a_y[0] + a_y[2] * a_y[2])
        rx, ry = w * r[0], w * r[1]
        for k in range(3):
            pred = a_x[k] * tx + a_y[k] * ty
            y = _huber(float(u_mG[k]) - old[k + 4], pred, clip_mG)
            rx += dt_s * a_x[k] * y
            ry += dt_s * a_y[k] * y
        self._r = [rx, ry]
        sxx, sxy, syy = s[0] + self.reg, s[1], s[2] + self.reg
        det = sxx * syy - sxy * sxy
        lim = self.max_rad
        self.tilt_rad = [min(max((syy * rx - sxy * ry) / det, -lim), lim),
                         min(max((sxx * ry - sxy * rx) / det, -lim), lim)]
