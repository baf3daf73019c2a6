"""The models of the live field-vector test (estimators.field_consistency): the body field's model
with its uncertainty, a Kalman filter over the Earth field, the body offset and the motor field per
unit of the motor signal (``FieldModelFilter``, the one motor-field model; the offline fits are
estimators.motor_field), and the magnetometer's tilt against the attitude's axes (``TiltTracker``,
learned from the changes of the residual over a short lag, so that a body offset never teaches it
anything).  Pure; the 11-state filter's covariance steps compiled by numba
(estimators.field_model_kernels), plain floats for the rest.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from estimators.field_model_kernels import (filter_step, forget_covariance, kalman_update, observe_covariance,
                                           predicted_field)

__all__ = ["FieldModelFilter", "TiltTracker", "MOTOR_TIMEOUT_S"]


def _lagged(hist: deque, row: tuple, lag_s: float) -> tuple | None:
    """Append ``row`` (its time first) to ``hist`` and return the newest row at least ``lag_s``
    older (None while the history is shorter): the other end of the change both trackers learn from."""
    t_s = row[0]
    hist.append(row)
    while len(hist) > 2 and hist[1][0] <= t_s - lag_s:
        hist.popleft()
    return hist[0] if hist[0][0] <= t_s - lag_s else None


def quad_inv3(v: Sequence[float], a: Sequence[float]) -> float:
    """vᵀ A⁻¹ v for a 3-vector v and a 3 × 3 matrix A (nine floats row by row), as vᵀ adj(A) v / det A."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    v0, v1, v2 = v
    c0, c1, c2 = a4 * a8 - a5 * a7, a5 * a6 - a3 * a8, a3 * a7 - a4 * a6
    det = a0 * c0 + a1 * c1 + a2 * c2
    return ((v0 * c0 + v1 * (a2 * a7 - a1 * a8) + v2 * (a1 * a5 - a2 * a4)) * v0
            + (v0 * c1 + v1 * (a0 * a8 - a2 * a6) + v2 * (a2 * a3 - a0 * a5)) * v1
            + (v0 * c2 + v1 * (a1 * a6 - a0 * a7) + v2 * (a0 * a4 - a1 * a3)) * v2) / det


_ZERO9 = (0.0,) * 9
SIGNAL_SCALE = 10.0     # a typical excursion of the motor signal [A or %]: sets f's random walk
MOTOR_TIMEOUT_S = 2.5   # the one motor-signal timeout [s]: an older current (or throttle) sample is not
                        # used; 1-2 Hz battery telemetry stays held between its samples


class FieldModelFilter:
    """The field-vector test's model of the calibrated body field, one Kalman filter (the one
    motor-field model: the detector, the explanations and the best heading use its f and sd).

    State θ = (ε, β, h, b, f): the error ε [rad] of the test's gyro-propagated heading ψ_f (an error
    state: folded into ψ_f after each update, ``take_heading``), the yaw-rate bias β [rad/s] left in
    the gyro (ψ_f integrates the yaw rate − β, so ε̇ = β − β̂: F = I + Δt e_ε e_βᵀ), the Earth field in the magnetic
    navigation frame h [mG], a body-fixed offset b [mG] (calibration error, the motor field at the
    first signal value) and the motor field per unit of the motor signal f [mG per A, or per %
    throttle], body frame.  Measurement, linearised in ε (C = C(φ, θ, ψ_f), ∂(Cᵀh)/∂ψ = Cᵀ(h_E, −h_N, 0)):
        m = R(δ) C(φ, θ, ψ_f − ε)ᵀ h + b + f·x̃ + v,   x̃ = x − x₀ (x₀: the first signal value),
    so H = [R(δ)Cᵀ(−h_E, h_N, 0) | 0 | R(δ)Cᵀ | I | x̃ I] (3 × 11).  Kalman steps (Kalman 1960; Simon, Optimal State
    Estimation, 2006, ch. 5): θ ← θ + K ν, P ← (I − K H) P, K = P Hᵀ S⁻¹, S = H P Hᵀ + R, with
    ν the innovation Huber-clipped at ``clip`` σ of the test's noise and the model's uncertainty
    (a disturbance's onset teaches it little).
    Random walks set how fast each part follows after it is known: process noise q = r_c / τ²
    per second (the steady-state time constant of a random walk observed with noise density
    r_c is √(r_c / q); for f, observed through x̃, per SIGNAL_SCALE of signal), with r_c = σ² τ_c (residual noise σ, correlated over τ_c: the residual
    is dominated by attitude and current errors that last about a second).
    What straight flight cannot separate (h against b on one heading, f against b while the
    signal is steady) keeps its prior variance, so the first turn or current change after it
    is learned at once and the test's σ includes the model's own uncertainty H P Hᵀ
    (``observe``) instead of alarming on it.  Units: mG, A (or %), s.

    Speed (issue 29: this runs at every IMU step of a log): θ is a list of plain floats and every
    3-vector and 3 × 3 step is plain-float arithmetic; the steps on the 11 × 11 covariance P are
    compiled loops through H's structure (estimators.field_model_kernels).
    """

    def __init__(self, h0_mG, h_sd_mG: float = 5.0, b_sd_mG: float = 50.0, f_sd: float = 3.0,
                 h_tau_s: float = 2000.0, b_tau_s: float = 20.0, f_tau_s: float = 300.0,
                 corr_s: float = 1.0, heading_sd_rad: float = 0.17, bias_sd_rad_s: float = 0.0087,
                 bias_walk_rad_s2: float = 1.0e-4, gyro_scale: float = 0.02) -> None:
        self.th = [0.0, 0.0] + [float(v) for v in h0_mG] + [0.0] * 6      # θ, plain floats
        self.P = np.diag([heading_sd_rad ** 2, bias_sd_rad_s ** 2] + [h_sd_mG ** 2] * 3 + [b_sd_mG ** 2] * 3
                         + [f_sd ** 2] * 3)
        self._diag = self.P.reshape(-1)[::12]          # a view of P's diagonal (P is changed in place)
        self.tau = np.array([h_tau_s] * 3 + [b_tau_s] * 3 + [f_tau_s] * 3)
        unit = np.array([1.0] * 6 + [1.0 / SIGNAL_SCALE ** 2] * 3)   # f's walk per SIGNAL_SCALE of signal
        self._walk = np.concatenate([[0.0, 0.0], unit / (self.tau * self.tau)])
        self.bias_walk_rad_s2, self.gyro_scale = bias_walk_rad_s2, gyro_scale
        self.corr_s = corr_s
        self.x0: float | None = None
        self._last_xt = 0.0

    @property
    def theta(self) -> np.ndarray:
        """θ as an array (a copy)."""
        return np.array(self.th)

    @property
    def h(self) -> list:
        return self.th[2:5]

    @property
    def b(self) -> list:
        return self.th[5:8]

    @property
    def f(self) -> list:
        return self.th[8:11]

    @property
    def sd(self) -> list:
        """f's standard error per axis (√ of P's diagonal)."""
        return [math.sqrt(v) if v >= 0.0 else math.nan for v in self._diag[8:].tolist()]   # np.sqrt's NaN below 0

    def significant(self, k_sigma: float = 3.0) -> bool:
        """|f| ≥ k_sigma · |sd|: the motor field is known well enough to be removed."""
        f0, f1, f2 = self.th[8:11]
        ff = f0 * f0 + f1 * f1 + f2 * f2
        v0, v1, v2 = self._diag[8:].tolist()
        return ff > 0.0 and ff >= k_sigma * k_sigma * (v0 + v1 + v2)

    @property
    def yaw_bias_rad_s(self) -> float:
        """β̂, the yaw-rate bias ψ_f takes out of the gyro."""
        return self.th[1]

    def take_heading(self) -> float:
        """ε, reset to 0 (the caller's ψ_f takes it: ψ_f ← ψ_f − ε)."""
        eps = self.th[0]
        self.th[0] = 0.0
        return eps

    def restart_heading(self, heading_sd_rad: float) -> None:
        """ψ_f started again (after an IMU gap, at the heading where h fits m − b − f·x̃): its error ε
        is new, unknown to ``heading_sd_rad`` and no longer tied to what was learnt with the old
        one, so ε is 0 with its prior variance and no covariance with h, b, f or β (otherwise the
        filter would take the new ψ_f's error as already known and split it wrongly into b)."""
        self.th[0] = 0.0
        self.P[0, :] = 0.0
        self.P[:, 0] = 0.0
        self.P[0, 0] = heading_sd_rad ** 2

    def signal(self, x: float) -> float:
        """x̃ = x − x₀; while the signal is unknown (NaN: none yet, or lost in a telemetry gap
        longer than the caller holds it) its last value (0 before the first): the current does
        not fall to x₀ because its telemetry stopped, so f·x̃ is not dropped from the prediction
        and from ψ_f's restart after the gap."""
        if not math.isfinite(x):
            return self._last_xt
        if self.x0 is None:
            self.x0 = float(x)
        self._last_xt = float(x) - self.x0
        return self._last_xt

    def jacobian(self, c_bt, xt: float) -> np.ndarray:
        """H (3 × 11) for the body-from-navigation matrix c_bt = R(δ)Cᵀ and the signal x̃ (as an
        array; ``observe`` uses its structure instead)."""
        hn, he = self.th[2], self.th[3]
        rows = c_bt.tolist() if isinstance(c_bt, np.ndarray) else c_bt
        return np.array([[r[1] * hn - r[0] * he, 0.0, r[0], r[1], r[2]]            # R(δ)Cᵀ (−h_E, h_N, 0)
                         + [1.0 if j == k else 0.0 for j in range(3)] + [xt if j == k else 0.0 for j in range(3)]
                         for k, r in enumerate(rows)])

    def observe(self, c_bt: Sequence[Sequence[float]], xt: float) -> tuple:
        """The measurement for c_bt = R(δ)Cᵀ (rows) and the signal x̃: (H θ, the predicted body
        field [mG]; H P Hᵀ, how uncertain that prediction is [mG², nine floats row by row]; P Hᵀ
        (11 × 3 array); x̃).  Pass it to ``update`` after ``forget`` has run (P as it is then)."""
        rows = tuple(tuple(float(v) for v in r) for r in c_bt)       # (not the test's hot path: ``step`` is)
        xt = float(xt)
        PHt, hph, a = observe_covariance(self.P, rows, self.th[2], self.th[3], xt)
        return predicted_field(tuple(self.th), rows, a, xt), hph, PHt, xt

    def _walks(self, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float) -> tuple:
        """(σ² τ_c Δt, the heading's and the yaw-rate bias's variance growth over Δt): the random
        walks' arguments of ``forget_covariance``."""
        return (float(sigma_mG * sigma_mG * self.corr_s * dt_s), float((self.gyro_scale * yaw_rate_rad_s) ** 2 * dt_s),
                float(self.bias_walk_rad_s2 ** 2 * dt_s))

    def _noise(self, dt_s: float, sigma_mG: float, extra_cov: list | None) -> tuple:
        """The measurement noise arguments of ``kalman_update``: (extra_cov, τ_c / Δt (0 when Δt ≤ 0),
        r = σ², r τ_c / Δt)."""
        r = sigma_mG * sigma_mG
        k = self.corr_s / dt_s if dt_s > 0.0 else 0.0
        return tuple(extra_cov) if extra_cov is not None else _ZERO9, k, r, r * k

    def forget(self, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float = 0.0) -> None:
        """The random walks over dt: P += diag(r_c / τ²) dt, r_c = σ² τ_c; the heading's error grows
        by what is left of the gyro's bias and by its scale error in turns."""
        forget_covariance(self.P, self._walk, float(dt_s), *self._walks(dt_s, sigma_mG, yaw_rate_rad_s))

    def step(self, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float, c_bt: tuple, xt: float, m_mG: tuple,
             learn: bool, clip: float, extra_cov: list | None = None) -> tuple:
        """``forget``, ``observe`` and, when ``learn``, ``update`` in one compiled call (the field-vector
        test's step; the same numbers): (H θ, the predicted body field [mG]; H P Hᵀ before the
        update [mG², nine floats]).  c_bt: R(δ)Cᵀ as three tuples of floats; m_mG a tuple."""
        pred, hph, step = filter_step(self.P, self._walk, tuple(self.th), c_bt, float(xt), m_mG, float(dt_s),
                                      *self._walks(dt_s, sigma_mG, yaw_rate_rad_s), learn,
                                      *self._noise(dt_s, sigma_mG, extra_cov), clip)
        if learn and dt_s > 0.0:
            self.th = [a + b for a, b in zip(self.th, step)]
        return pred, hph

    def inflate(self, h_sd_mG: float, b_sd_mG: float) -> None:
        """Forget h and b to this much more variance (a disturbance has ended: learn them again)."""
        self._diag += np.array([0.0, 0.0] + [h_sd_mG ** 2] * 3 + [b_sd_mG ** 2] * 3 + [0.0] * 3)

    def update(self, H, m_mG, dt_s: float, sigma_mG: float, clip: float, extra_cov: list | None = None) -> None:
        """One Kalman measurement update with measurement noise R = (σ² τ_c / dt) I (+ extra_cov, nine
        floats row by row): ``H`` is ``observe``'s tuple (or H as an array, observed here)."""
        if dt_s <= 0.0:
            return
        if isinstance(H, np.ndarray):
            H = self.observe(H[:, 2:5].tolist(), float(H[0, 8]))
        pred, hph, PHt, _ = H
        nu = (float(m_mG[0]) - pred[0], float(m_mG[1]) - pred[1], float(m_mG[2]) - pred[2])
        extra, k, r, rs = self._noise(dt_s, sigma_mG, extra_cov)
        step = kalman_update(self.P, PHt, hph, extra, k, nu, r, rs, clip)
        self.th = [a + b for a, b in zip(self.th, step)]


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
        p0, p1, p2 = float(p_mG[0]), float(p_mG[1]), float(p_mG[2])
        u0, u1, u2 = float(u_mG[0]), float(u_mG[1]), float(u_mG[2])
        old = _lagged(self._hist, (t_s, p0, p1, p2, u0, u1, u2), self.lag_s)
        if not learn or old is None:
            return
        dpx, dpy, dpz = p0 - old[1], p1 - old[2], p2 - old[3]
        # e_x × Δp = (0, −Δp_z, Δp_y) and e_y × Δp = (Δp_z, 0, −Δp_x): the residual's change per
        # radian of δ_x and of δ_y (written out term by term, zeros included: the same arithmetic
        # as the loop over the three axes it replaces)
        ax1, ax2, ay0, ay2 = -dpz, dpy, dpz, -dpx
        tx, ty = self.tilt_rad
        w = math.exp(-dt_s / self.memory_s)
        s, r = self._s, self._r
        s[0] = w * s[0] + dt_s * (ax1 * ax1 + ax2 * ax2)
        s[1] = w * s[1] + dt_s * (ax2 * ay2)
        s[2] = w * s[2] + dt_s * (ay0 * ay0 + ay2 * ay2)
        rx, ry = w * r[0], w * r[1]
        pred = 0.0 * tx + ay0 * ty
        y = pred + min(max(u0 - old[4] - pred, -clip_mG), clip_mG)         # Huber-clipped around A δ
        rx += dt_s * 0.0 * y
        ry += dt_s * ay0 * y
        pred = ax1 * tx + 0.0 * ty
        y = pred + min(max(u1 - old[5] - pred, -clip_mG), clip_mG)
        rx += dt_s * ax1 * y
        ry += dt_s * 0.0 * y
        pred = ax2 * tx + ay2 * ty
        y = pred + min(max(u2 - old[6] - pred, -clip_mG), clip_mG)
        rx += dt_s * ax2 * y
        ry += dt_s * ay2 * y
        self._r = [rx, ry]
        sxx, sxy, syy = s[0] + self.reg, s[1], s[2] + self.reg
        det = sxx * syy - sxy * sxy
        lim = self.max_rad
        self.tilt_rad = [min(max((syy * rx - sxy * ry) / det, -lim), lim),
                         min(max((sxx * ry - sxy * rx) / det, -lim), lim)]
