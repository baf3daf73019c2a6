"""Online motor field per unit of the motor signal, for the live field-vector test
(estimators.field_consistency); the offline fits are estimators.motor_field.  Pure, plain floats.
"""
from __future__ import annotations

import math
from collections import deque

__all__ = ["MotorFieldTracker"]


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
