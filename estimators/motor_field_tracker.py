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


class MotorFieldTracker:
    """Online field per unit of the motor signal from its changes (for the live field-vector test).

    Over a short lag L the Earth part of the field barely changes outside turns, so the change of
    u = m − Cᵀh (measured minus the predicted Earth field, body frame [mG]) is the motor field's:
        y = u(t) − u(t − L) = f · (x(t) − x(t − L)) + noise,
    independent of the body offset and of a steady heading error.  f is the exponentially weighted
    least-squares slope per axis, f_k = Σ w z y_k / (Σ w z² + reg) with z = x(t) − x(t − L), the
    weights forgetting with ``memory_s``, each y_k Huber-clipped at ``clip_mG`` around f_k z (a
    disturbance that starts while the current changes does not teach it much).  ``excitation`` is
    Σ z² Δt [unit² s], how much signal change f has been learned from.  Units: mG, A (or %), s.
    """

    def __init__(self, lag_s: float = 1.0, memory_s: float = 300.0, reg: float = 1.0) -> None:
        self.lag_s, self.memory_s, self.reg = lag_s, memory_s, reg
        self.f = [0.0, 0.0, 0.0]
        self.excitation = 0.0
        self._sxx = 0.0
        self._sxy = [0.0, 0.0, 0.0]
        self._hist: deque = deque()

    def clear_history(self) -> None:
        """Forget the recent samples (after a gap), keep what has been learned."""
        self._hist.clear()

    def update(self, t_s: float, u_mG, x: float, dt_s: float, learn: bool, clip_mG: float) -> None:
        """One step: u = m − Cᵀh [mG], signal x (NaN: none); learns only when ``learn``."""
        if not math.isfinite(x):
            self._hist.clear()
            return
        h = self._hist
        h.append((t_s, float(u_mG[0]), float(u_mG[1]), float(u_mG[2]), x))
        while len(h) > 2 and h[1][0] <= t_s - self.lag_s:
            h.popleft()
        if not learn or h[0][0] > t_s - self.lag_s:
            return
        z = x - h[0][4]
        w = math.exp(-dt_s / self.memory_s)
        self._sxx = w * self._sxx + z * z * dt_s
        self.excitation += z * z * dt_s
        for k in range(3):
            pred = self.f[k] * z
            y = pred + min(max(float(u_mG[k]) - h[0][k + 1] - pred, -clip_mG), clip_mG)
            self._sxy[k] = w * self._sxy[k] + z * y * dt_s
            self.f[k] = self._sxy[k] / (self._sxx + self.reg)


class TiltTracker:
    """Online tilt δ = (δ_x, δ_y) [rad] of the magnetometer against the attitude's body axes.

    The field the tilted sensor measures is R(δ) p ≈ p + δ × p (p = Cᵀh, the predicted Earth field in
    the body frame [mG]), so the part of the residual u = m − p − b − f·Δx that a tilt explains
    changes over a short lag L only when p does (the nose turning):
        y = u(t) − u(t − L) = δ × Δp + η |p| Δd + noise,   Δp = p(t) − p(t − L),
    a body offset cancels; a heading error of the attitude (a rotation about z) is left out.  The
    second term: when level, the vertical Earth field and a body-z offset are one, so b holds
    some of the vertical field (η |p|: its share [mG], d: the down direction in the body, the third
    row of C), which a roll or pitch exposes as a change along Δd; fitted beside δ so it is not
    taken for the sensor's tilt (a wrong WMM vertical, e.g. a site anomaly, ends in b while the
    vehicle hovers level).  (δ_x, δ_y, η) is the exponentially weighted least-squares
    solution of the 3 × 3 normal equations (Σ w AᵀA + reg I) θ = Σ w Aᵀy, A = [e_x × Δp, e_y × Δp,
    |p| Δd], the weights forgetting with ``memory_s``, each y Huber-clipped at ``clip_mG`` around
    A θ, δ at most ``max_rad`` per axis.  ``reg`` [mG² s] holds δ at 0 until the heading has turned
    enough.  The vertical share is handed over with ``take_vertical_mG`` once the rolls and pitches
    have told it apart (the caller moves it from b to h).  Units: rad, mG, s.
    """

    def __init__(self, lag_s: float = 2.0, memory_s: float = 300.0, reg: float = 1.0e4,
                 max_rad: float = 0.087) -> None:
        self.lag_s, self.memory_s, self.reg, self.max_rad = lag_s, memory_s, reg, max_rad
        self.tilt_rad = [0.0, 0.0]
        self._theta = [0.0, 0.0, 0.0]
        self._s = [[0.0] * 3 for _ in range(3)]     # Σ w AᵀA
        self._r = [0.0, 0.0, 0.0]                   # Σ w Aᵀy
        self._hist: deque = deque()
        self._size = 0.0

    def clear_history(self) -> None:
        """Forget the recent samples (after a gap), keep what has been learned."""
        self._hist.clear()

    def take_vertical_mG(self, min_information: float) -> float:
        """The vertical Earth field the body offset holds [mG] (η |p|), once the attitude changes have
        told it apart (Σ w A₃ᵀA₃ ≥ ``min_information`` [mG² s]), else 0; taken: the caller moves it
        from b to h, and η is learned again from 0."""
        s = self._s
        if s[2][2] < min_information:
            return 0.0
        eps = self._theta[2] * self._size
        for k in range(3):
            s[2][k] = s[k][2] = 0.0
        self._r[2] = 0.0
        self._theta[2] = 0.0
        return eps

    def update(self, t_s: float, p_mG, u_mG, down_body, dt_s: float, learn: bool, clip_mG: float) -> None:
        """One step: p = Cᵀh and u = m − p − b − f·Δx (no tilt term) [mG], the down direction in the
        body frame (unit, third row of C); learns only when ``learn``."""
        h = self._hist
        h.append((t_s, *(float(v) for v in p_mG), *(float(v) for v in u_mG), *(float(v) for v in down_body)))
        while len(h) > 2 and h[1][0] <= t_s - self.lag_s:
            h.popleft()
        if not learn or h[0][0] > t_s - self.lag_s:
            return
        old, new = h[0], h[-1]
        dp = [new[k + 1] - old[k + 1] for k in range(3)]
        size = math.sqrt(new[1] ** 2 + new[2] ** 2 + new[3] ** 2)
        cols = ((0.0, -dp[2], dp[1]), (dp[2], 0.0, -dp[0]),       # e_x × Δp, e_y × Δp
                tuple(size * (new[k + 7] - old[k + 7]) for k in range(3)))
        w = math.exp(-dt_s / self.memory_s)
        s, r, th = self._s, self._r, self._theta
        for i in range(3):
            r[i] *= w
            for j in range(3):
                s[i][j] = w * s[i][j] + dt_s * sum(cols[i][k] * cols[j][k] for k in range(3))
        for k in range(3):
            pred = sum(cols[i][k] * th[i] for i in range(3))
            y = pred + min(max(new[k + 4] - old[k + 4] - pred, -clip_mG), clip_mG)
            for i in range(3):
                r[i] += dt_s * cols[i][k] * y
        self._size = size
        self._theta = _solve3([[s[i][j] + (self.reg if i == j else 0.0) for j in range(3)] for i in range(3)], r)
        lim = self.max_rad
        self.tilt_rad = [min(max(self._theta[0], -lim), lim), min(max(self._theta[1], -lim), lim)]


def _solve3(a: list, b: list) -> list:
    """x with a x = b for a symmetric positive definite 3 × 3 (Cramer's rule)."""
    def det(m):
        return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))
    d = det(a)
    return [det([[b[i] if j == c else a[i][j] for j in range(3)] for i in range(3)]) / d for c in range(3)]
