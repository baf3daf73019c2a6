"""The models of the live field-vector test (estimators.field_consistency): the body field's model
with its uncertainty, a Kalman filter over the Earth field, the body offset and the motor field per
unit of the motor signal (``FieldModelFilter``, the one motor-field model; the offline fits are
estimators.motor_field), and the magnetometer's tilt against the attitude's axes (``TiltTracker``,
learned from the changes of the residual over a short lag, so that a body offset never teaches it
anything).  Pure; both keep their state in arrays and step by numba-compiled kernels
(estimators.field_model_kernels' ``model_*``, ``tilt_update`` here), the ones the field-vector
test's compiled step (estimators.field_consistency_kernel) runs on its own state, which the test's
``motor`` and ``tilt`` are views of (``view``).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from estimators import ring_buffers as ring
from estimators.field_model_kernels import (BIAS_WALK, CORR_S, GYRO_SCALE, MODEL_SCALARS, SIGNAL_SCALE, X0, inflate,
                                           model_forget, model_init, model_signal, model_step, model_update,
                                           observe_covariance, predicted_field, quad_inv3, restart_heading,
                                           take_heading)

__all__ = ["FieldModelFilter", "TiltTracker", "MOTOR_TIMEOUT_S", "quad_inv3", "SIGNAL_SCALE", "tilt_update",
           "TILT_STATE", "TILT_PARAMS"]


_ZERO9 = (0.0,) * 9
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

    Speed (issue 29: this runs at every IMU step of a log): θ, P, the random walks and the scalars
    (x₀, τ_c, ...) are arrays and every step is compiled (estimators.field_model_kernels' ``model_*``);
    the field-vector test's compiled step runs the same kernels on its own state arrays, and its
    ``motor`` is this class as a view of them (``view``).
    """

    def __init__(self, h0_mG, h_sd_mG: float = 5.0, b_sd_mG: float = 50.0, f_sd: float = 3.0,
                 h_tau_s: float = 2000.0, b_tau_s: float = 20.0, f_tau_s: float = 300.0,
                 corr_s: float = 1.0, heading_sd_rad: float = 0.17, bias_sd_rad_s: float = 0.0087,
                 bias_walk_rad_s2: float = 1.0e-4, gyro_scale: float = 0.02) -> None:
        th, P, walk, mv = np.zeros(11), np.zeros((11, 11)), np.zeros(11), np.zeros(MODEL_SCALARS)
        model_init(th, P, walk, mv, tuple(float(v) for v in h0_mG), float(h_sd_mG), float(b_sd_mG), float(f_sd),
                   float(h_tau_s), float(b_tau_s), float(f_tau_s), float(corr_s), float(heading_sd_rad),
                   float(bias_sd_rad_s), float(bias_walk_rad_s2), float(gyro_scale))
        self._bind(th, P, walk, mv)

    @classmethod
    def view(cls, th: np.ndarray, P: np.ndarray, walk: np.ndarray, mv: np.ndarray) -> "FieldModelFilter":
        """The filter over arrays someone else holds (the field-vector test's state): no copy."""
        obj = cls.__new__(cls)
        obj._bind(th, P, walk, mv)
        return obj

    def _bind(self, th: np.ndarray, P: np.ndarray, walk: np.ndarray, mv: np.ndarray) -> None:
        self.th, self.P, self._walk, self._mv = th, P, walk, mv     # θ (11), P (11 × 11), walks (11), scalars
        self._diag = P.reshape(-1)[::12]               # a view of P's diagonal (P is changed in place)

    @property
    def corr_s(self) -> float:
        return float(self._mv[CORR_S])

    @property
    def gyro_scale(self) -> float:
        return float(self._mv[GYRO_SCALE])

    @property
    def bias_walk_rad_s2(self) -> float:
        return float(self._mv[BIAS_WALK])

    @property
    def x0(self) -> float | None:
        """The first signal value (None before it)."""
        return None if math.isnan(self._mv[X0]) else float(self._mv[X0])

    @property
    def theta(self) -> np.ndarray:
        """θ as an array (a copy)."""
        return self.th.copy()

    @property
    def h(self) -> list:
        return self.th[2:5].tolist()

    @property
    def b(self) -> list:
        return self.th[5:8].tolist()

    @property
    def f(self) -> list:
        return self.th[8:11].tolist()

    @property
    def sd(self) -> list:
        """f's standard error per axis (√ of P's diagonal)."""
        return [math.sqrt(v) if v >= 0.0 else math.nan for v in self._diag[8:].tolist()]   # np.sqrt's NaN below 0

    def significant(self, k_sigma: float = 3.0) -> bool:
        """|f| ≥ k_sigma · |sd|: the motor field is known well enough to be removed."""
        f0, f1, f2 = self.th[8:11].tolist()
        ff = f0 * f0 + f1 * f1 + f2 * f2
        v0, v1, v2 = self._diag[8:].tolist()
        return ff > 0.0 and ff >= k_sigma * k_sigma * (v0 + v1 + v2)

    @property
    def yaw_bias_rad_s(self) -> float:
        """β̂, the yaw-rate bias ψ_f takes out of the gyro."""
        return float(self.th[1])

    def take_heading(self) -> float:
        """ε, reset to 0 (the caller's ψ_f takes it: ψ_f ← ψ_f − ε)."""
        return take_heading(self.th)

    def restart_heading(self, heading_sd_rad: float) -> None:
        """ψ_f started again (after an IMU gap, at the heading where h fits m − b − f·x̃): its error ε
        is new, unknown to ``heading_sd_rad`` and no longer tied to what was learnt with the old
        one, so ε is 0 with its prior variance and no covariance with h, b, f or β (otherwise the
        filter would take the new ψ_f's error as already known and split it wrongly into b)."""
        restart_heading(self.th, self.P, float(heading_sd_rad))

    def signal(self, x: float) -> float:
        """x̃ = x − x₀; while the signal is unknown (NaN: none yet, or lost in a telemetry gap
        longer than the caller holds it) its last value (0 before the first): the current does
        not fall to x₀ because its telemetry stopped, so f·x̃ is not dropped from the prediction
        and from ψ_f's restart after the gap."""
        return model_signal(self._mv, float(x))

    def jacobian(self, c_bt, xt: float) -> np.ndarray:
        """H (3 × 11) for the body-from-navigation matrix c_bt = R(δ)Cᵀ and the signal x̃ (as an
        array; ``observe`` uses its structure instead)."""
        hn, he = float(self.th[2]), float(self.th[3])
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
        PHt, hph, a = observe_covariance(self.P, rows, float(self.th[2]), float(self.th[3]), xt)
        return predicted_field(self.th, rows, a, xt), hph, PHt, xt

    def forget(self, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float = 0.0) -> None:
        """The random walks over dt: P += diag(r_c / τ²) dt, r_c = σ² τ_c; the heading's error grows
        by what is left of the gyro's bias and by its scale error in turns."""
        model_forget(self.P, self._walk, self._mv, float(dt_s), float(sigma_mG), float(yaw_rate_rad_s))

    def step(self, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float, c_bt: tuple, xt: float, m_mG: tuple,
             learn: bool, clip: float, extra_cov: list | None = None) -> tuple:
        """``forget``, ``observe`` and, when ``learn``, ``update`` in one compiled call (the field-vector
        test's step; the same numbers): (H θ, the predicted body field [mG]; H P Hᵀ before the
        update [mG², nine floats]).  c_bt: R(δ)Cᵀ as three tuples of floats; m_mG a tuple."""
        rows = tuple(tuple(float(v) for v in r) for r in c_bt)
        return model_step(self.th, self.P, self._walk, self._mv, float(dt_s), float(sigma_mG), float(yaw_rate_rad_s),
                          rows, float(xt), tuple(float(v) for v in m_mG), bool(learn), float(clip),
                          tuple(float(v) for v in extra_cov) if extra_cov is not None else _ZERO9)

    def inflate(self, h_sd_mG: float, b_sd_mG: float) -> None:
        """Forget h and b to this much more variance (a disturbance has ended: learn them again)."""
        inflate(self.P, float(h_sd_mG), float(b_sd_mG))

    def update(self, H, m_mG, dt_s: float, sigma_mG: float, clip: float, extra_cov: list | None = None) -> None:
        """One Kalman measurement update with measurement noise R = (σ² τ_c / dt) I (+ extra_cov, nine
        floats row by row): ``H`` is ``observe``'s tuple (or H as an array, observed here)."""
        if dt_s <= 0.0:
            return
        if isinstance(H, np.ndarray):
            H = self.observe(H[:, 2:5].tolist(), float(H[0, 8]))
        pred, hph, PHt, _ = H
        model_update(self.th, self.P, self._mv, PHt, hph, pred, tuple(float(v) for v in m_mG[:3]), float(dt_s),
                     float(sigma_mG), float(clip),
                     tuple(float(v) for v in extra_cov) if extra_cov is not None else _ZERO9)


# the tilt tracker's state (``tv``): δ_x, δ_y [rad]; Σ w AᵀA (xx, xy, yy); Σ w Aᵀy (x, y); then its
# settings: the lag [s], the memory [s], the regularisation [mG² s], the largest δ [rad]
TILT_X, TILT_Y, TILT_SXX, TILT_SXY, TILT_SYY, TILT_RX, TILT_RY, TILT_LAG, TILT_MEMORY, TILT_REG, TILT_MAX = range(11)
TILT_STATE, TILT_PARAMS = 7, 11      # tv[:TILT_STATE] is learned state, tv[TILT_STATE:TILT_PARAMS] its settings


@njit(cache=True, inline="always")
def _lagged(hist: np.ndarray, hist_ring: np.ndarray, t_s: float, p0: float, p1: float, p2: float,
            u0: float, u1: float, u2: float, lag_s: float) -> int:
    """Append the row (t, p, u) to ``hist`` and return the buffer row of the newest row at least
    ``lag_s`` older (−1 while the history is shorter): the other end of the change the tilt learns from."""
    cap = hist.shape[0]
    i = ring.push(hist_ring, cap)
    hist[i, 0], hist[i, 1], hist[i, 2], hist[i, 3] = t_s, p0, p1, p2
    hist[i, 4], hist[i, 5], hist[i, 6] = u0, u1, u2
    while ring.size(hist_ring) > 2 and hist[ring.at(hist_ring, 1, cap), 0] <= t_s - lag_s:
        ring.pop_front(hist_ring, cap)
    first = ring.first(hist_ring, cap)
    return first if hist[first, 0] <= t_s - lag_s else -1


@njit(cache=True)
def tilt_update(tv: np.ndarray, hist: np.ndarray, hist_ring: np.ndarray, t_s: float, p0: float, p1: float, p2: float,
                u0: float, u1: float, u2: float, dt_s: float, learn: bool, clip_mG: float) -> None:
    """``TiltTracker.update`` on its arrays (tv: TILT_* above; hist: (t, p, u) rows of a ring, hist_ring its
    head and count, estimators.ring_buffers)."""
    k = _lagged(hist, hist_ring, t_s, p0, p1, p2, u0, u1, u2, tv[TILT_LAG])
    if not learn or k < 0:
        return
    dpx, dpy, dpz = p0 - hist[k, 1], p1 - hist[k, 2], p2 - hist[k, 3]
    # e_x × Δp = (0, −Δp_z, Δp_y) and e_y × Δp = (Δp_z, 0, −Δp_x): the residual's change per
    # radian of δ_x and of δ_y (written out term by term, zeros included: the same arithmetic
    # as the loop over the three axes it replaces)
    ax1, ax2, ay0, ay2 = -dpz, dpy, dpz, -dpx
    tx, ty = tv[TILT_X], tv[TILT_Y]
    w = math.exp(-dt_s / tv[TILT_MEMORY])
    tv[TILT_SXX] = w * tv[TILT_SXX] + dt_s * (ax1 * ax1 + ax2 * ax2)
    tv[TILT_SXY] = w * tv[TILT_SXY] + dt_s * (ax2 * ay2)
    tv[TILT_SYY] = w * tv[TILT_SYY] + dt_s * (ay0 * ay0 + ay2 * ay2)
    rx, ry = w * tv[TILT_RX], w * tv[TILT_RY]
    pred = 0.0 * tx + ay0 * ty
    y = pred + min(max(u0 - hist[k, 4] - pred, -clip_mG), clip_mG)         # Huber-clipped around A δ
    rx += dt_s * 0.0 * y
    ry += dt_s * ay0 * y
    pred = ax1 * tx + 0.0 * ty
    y = pred + min(max(u1 - hist[k, 5] - pred, -clip_mG), clip_mG)
    rx += dt_s * ax1 * y
    ry += dt_s * 0.0 * y
    pred = ax2 * tx + ay2 * ty
    y = pred + min(max(u2 - hist[k, 6] - pred, -clip_mG), clip_mG)
    rx += dt_s * ax2 * y
    ry += dt_s * ay2 * y
    tv[TILT_RX], tv[TILT_RY] = rx, ry
    sxx, sxy, syy = tv[TILT_SXX] + tv[TILT_REG], tv[TILT_SXY], tv[TILT_SYY] + tv[TILT_REG]
    det = sxx * syy - sxy * sxy
    lim = tv[TILT_MAX]
    tv[TILT_X] = min(max((syy * rx - sxy * ry) / det, -lim), lim)
    tv[TILT_Y] = min(max((sxx * ry - sxy * rx) / det, -lim), lim)


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

    The state is arrays (``tv``, see TILT_*; the last ``lag_s`` of samples as a ring of rows,
    estimators.ring_buffers, at most its CAPACITY) and the step is compiled (``tilt_update``), the
    one the field-vector test's compiled step runs on its own arrays (``view``).
    """

    def __init__(self, lag_s: float = 2.0, memory_s: float = 300.0, reg: float = 1.0e4,
                 max_rad: float = 0.087) -> None:
        tv = np.zeros(TILT_PARAMS)
        tv[TILT_LAG], tv[TILT_MEMORY], tv[TILT_REG], tv[TILT_MAX] = lag_s, memory_s, reg, max_rad
        self._bind(tv, np.zeros((ring.CAPACITY, 7)), np.zeros(2, dtype=np.int64))

    @classmethod
    def view(cls, tv: np.ndarray, hist: np.ndarray, ptr: np.ndarray) -> "TiltTracker":
        """The tracker over arrays someone else holds (the field-vector test's state): no copy."""
        obj = cls.__new__(cls)
        obj._bind(tv, hist, ptr)
        return obj

    def _bind(self, tv: np.ndarray, hist: np.ndarray, ptr: np.ndarray) -> None:
        self._tv, self._hist, self._ptr = tv, hist, ptr

    lag_s = property(lambda self: float(self._tv[TILT_LAG]))
    memory_s = property(lambda self: float(self._tv[TILT_MEMORY]))
    reg = property(lambda self: float(self._tv[TILT_REG]))
    max_rad = property(lambda self: float(self._tv[TILT_MAX]))

    @property
    def tilt_rad(self) -> list:
        """δ = [δ_x, δ_y] [rad]."""
        return [float(self._tv[TILT_X]), float(self._tv[TILT_Y])]

    def update(self, t_s: float, p_mG, u_mG, dt_s: float, learn: bool, clip_mG: float) -> None:
        """One step: p = Cᵀh and u = m − p − b − f·Δx (no tilt term) [mG]; learns only when ``learn``."""
        tilt_update(self._tv, self._hist, self._ptr, float(t_s), float(p_mG[0]), float(p_mG[1]), float(p_mG[2]),
                    float(u_mG[0]), float(u_mG[1]), float(u_mG[2]), float(dt_s), bool(learn), float(clip_mG))
