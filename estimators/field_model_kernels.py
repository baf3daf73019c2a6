"""The covariance steps of the field-vector test's 11-state Kalman filter
(``estimators.residual_trackers.FieldModelFilter``), compiled by numba: they run at every IMU step
of a log, and as numpy calls on 11 × 11 arrays they cost more in call overhead than in arithmetic
(about 17 calls a step, half of the test's time; issue 29).

State order θ = (ε, β, h_N, h_E, h_D, b_x, b_y, b_z, f_x, f_y, f_z); the measurement's Hᵀ (11 × 3)
has rows a = R(δ)Cᵀ(−h_E, h_N, 0) for ε, 0 for β, (R(δ)Cᵀ)ᵀ for h, I for b and x̃ I for f, so
P Hᵀ and H P Hᵀ are written out through that structure.  Kalman steps as in Simon, Optimal State
Estimation (2006), ch. 5: P ← F P Fᵀ + Q with F = I + Δt e_ε e_βᵀ; K = P Hᵀ S⁻¹, θ ← θ + K ν,
P ← (I − K H) P, symmetrised.  Units: those of the filter (rad, rad/s, mG, mG per unit signal).
The caller's arrays are float64, C-ordered; P is changed in place.

The filter's whole step is here too (``model_*``: θ, P, the random walks and the scalars ``mv``
as arrays, changed in place), so that the field-vector test's compiled step
(estimators.field_consistency_kernel) and ``FieldModelFilter``'s methods run the same code.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["forget_covariance", "observe_covariance", "predicted_field", "update_covariance", "kalman_update",
           "filter_step", "quad_inv3", "MODEL_SCALARS", "X0", "LAST_XT", "CORR_S", "GYRO_SCALE", "BIAS_WALK",
           "SIGNAL_SCALE", "model_init", "model_signal", "model_forget", "model_step", "model_update",
           "take_heading", "restart_heading", "inflate"]

# mv, the filter's scalars beside θ and P: x₀ (the first signal value, NaN before it), the last x̃,
# the residual's correlation time τ_c [s], the gyro's scale error, the yaw-rate bias's walk [rad/s²]
X0, LAST_XT, CORR_S, GYRO_SCALE, BIAS_WALK = range(5)
MODEL_SCALARS = 5
SIGNAL_SCALE = 10.0     # a typical excursion of the motor signal [A or %]: sets f's random walk


@njit(cache=True)
def forget_covariance(P: np.ndarray, walk: np.ndarray, dt_s: float, walk_scale: float,
                      q_heading: float, q_bias: float) -> None:
    """P ← F P Fᵀ + Q over dt_s: F = I + Δt e_ε e_βᵀ (ε̇ = β − β̂); Q = diag(q_heading, q_bias,
    walk[2:] · walk_scale) (walk: the random walks per unit of walk_scale = σ² τ_c Δt)."""
    n = P.shape[0]
    for j in range(n):                       # row ε += Δt row β
        P[0, j] += dt_s * P[1, j]
    P[0, 0] += dt_s * P[0, 1]                # then column ε += Δt column β (P symmetric: row ε again)
    for i in range(1, n):
        P[i, 0] = P[0, i]
    P[0, 0] += q_heading
    P[1, 1] += q_bias
    for i in range(2, n):
        P[i, i] += walk[i] * walk_scale


@njit(cache=True)
def observe_covariance(P: np.ndarray, c_bt: tuple, h_n_mG: float, h_e_mG: float, xt: float) -> tuple:
    """(P Hᵀ (11 × 3), H P Hᵀ [mG², nine floats row by row], a: H's ε column) for the
    body-from-navigation matrix c_bt = R(δ)Cᵀ (three rows) and the signal x̃."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = c_bt
    a0 = r01 * h_n_mG - r00 * h_e_mG
    a1 = r11 * h_n_mG - r10 * h_e_mG
    a2 = r21 * h_n_mG - r20 * h_e_mG
    n = P.shape[0]
    pht = np.empty((n, 3))
    for i in range(n):
        p0, p2, p3, p4 = P[i, 0], P[i, 2], P[i, 3], P[i, 4]
        pht[i, 0] = p0 * a0 + p2 * r00 + p3 * r01 + p4 * r02 + P[i, 5] + xt * P[i, 8]
        pht[i, 1] = p0 * a1 + p2 * r10 + p3 * r11 + p4 * r12 + P[i, 6] + xt * P[i, 9]
        pht[i, 2] = p0 * a2 + p2 * r20 + p3 * r21 + p4 * r22 + P[i, 7] + xt * P[i, 10]
    h = np.empty(9)
    for k in range(3):
        h[k] = a0 * pht[0, k] + r00 * pht[2, k] + r01 * pht[3, k] + r02 * pht[4, k] + pht[5, k] + xt * pht[8, k]
        h[3 + k] = a1 * pht[0, k] + r10 * pht[2, k] + r11 * pht[3, k] + r12 * pht[4, k] + pht[6, k] + xt * pht[9, k]
        h[6 + k] = a2 * pht[0, k] + r20 * pht[2, k] + r21 * pht[3, k] + r22 * pht[4, k] + pht[7, k] + xt * pht[10, k]
    return pht, (h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]), (a0, a1, a2)


@njit(cache=True)
def predicted_field(th: tuple, c_bt: tuple, a: tuple, xt: float) -> tuple:
    """H θ, the body field the model predicts [mG]: a ε + R(δ)Cᵀ h + b + x̃ f (a: H's ε column)."""
    e0, hn, he, hd = th[0], th[2], th[3], th[4]
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = c_bt
    return (a[0] * e0 + r00 * hn + r01 * he + r02 * hd + th[5] + xt * th[8],
            a[1] * e0 + r10 * hn + r11 * he + r12 * hd + th[6] + xt * th[9],
            a[2] * e0 + r20 * hn + r21 * he + r22 * hd + th[7] + xt * th[10])


@njit(cache=True)
def _inverse3(a: tuple) -> tuple:
    """A⁻¹ of a 3 × 3 matrix (nine floats row by row) by its adjugate over the determinant."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    c0, c1, c2 = a4 * a8 - a5 * a7, a5 * a6 - a3 * a8, a3 * a7 - a4 * a6
    det = a0 * c0 + a1 * c1 + a2 * c2
    return (c0 / det, (a2 * a7 - a1 * a8) / det, (a1 * a5 - a2 * a4) / det,
            c1 / det, (a0 * a8 - a2 * a6) / det, (a2 * a3 - a0 * a5) / det,
            c2 / det, (a1 * a6 - a0 * a7) / det, (a0 * a4 - a1 * a3) / det)


@njit(cache=True)
def kalman_update(P: np.ndarray, pht: np.ndarray, hph: tuple, extra: tuple, extra_scale: float,
                  nu: tuple, r_mG2: float, rs_mG2: float, clip: float) -> tuple:
    """One measurement update (changes P; returns K ν, eleven floats) for P Hᵀ, H P Hᵀ (nine floats
    row by row) and the innovation ν [mG]: S = H P Hᵀ + extra · extra_scale + rs I (rs: the
    measurement noise over the step, σ² τ_c / Δt); ν Huber-clipped at ``clip`` in the metric
    C = H P Hᵀ + r I (r = σ², the noise of one residual: the model's error counts, a disturbance's
    onset teaches little); K = P Hᵀ S⁻¹, P ← sym(P − K (P Hᵀ)ᵀ)."""
    S = [hph[i] + extra[i] * extra_scale for i in range(9)]
    S[0] += rs_mG2
    S[4] += rs_mG2
    S[8] += rs_mG2
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = _inverse3((hph[0] + r_mG2, hph[1], hph[2], hph[3], hph[4] + r_mG2,
                                                    hph[5], hph[6], hph[7], hph[8] + r_mG2))
    n0, n1, n2 = nu
    d2 = (n0 * (c0 * n0 + c1 * n1 + c2 * n2) + n1 * (c3 * n0 + c4 * n1 + c5 * n2)
          + n2 * (c6 * n0 + c7 * n1 + c8 * n2))
    d = np.sqrt(max(d2, 0.0))
    if d > clip:
        g = clip / d
        n0, n1, n2 = n0 * g, n1 * g, n2 * g
    s_inv = _inverse3((S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7], S[8]))
    return update_covariance(P, pht, s_inv, (n0, n1, n2))


@njit(cache=True)
def update_covariance(P: np.ndarray, pht: np.ndarray, s_inv: tuple, nu: tuple) -> tuple:
    """One measurement update for P Hᵀ, S⁻¹ (nine floats row by row) and the innovation ν:
    P ← sym((I − K H) P) = sym(P − K (P Hᵀ)ᵀ), K = P Hᵀ S⁻¹; returns K ν (eleven floats)."""
    s0, s1, s2, s3, s4, s5, s6, s7, s8 = s_inv
    n0, n1, n2 = nu
    w0 = s0 * n0 + s1 * n1 + s2 * n2         # S⁻¹ ν
    w1 = s3 * n0 + s4 * n1 + s5 * n2
    w2 = s6 * n0 + s7 * n1 + s8 * n2
    n = P.shape[0]
    k = np.empty((n, 3))
    d = np.empty(n)
    for i in range(n):
        p0, p1, p2 = pht[i, 0], pht[i, 1], pht[i, 2]
        k[i, 0] = p0 * s0 + p1 * s3 + p2 * s6
        k[i, 1] = p0 * s1 + p1 * s4 + p2 * s7
        k[i, 2] = p0 * s2 + p1 * s5 + p2 * s8
        d[i] = p0 * w0 + p1 * w1 + p2 * w2
    for i in range(n):
        for j in range(i, n):
            upper = P[i, j] - (k[i, 0] * pht[j, 0] + k[i, 1] * pht[j, 1] + k[i, 2] * pht[j, 2])
            lower = P[j, i] - (k[j, 0] * pht[i, 0] + k[j, 1] * pht[i, 1] + k[j, 2] * pht[i, 2])
            v = 0.5 * (upper + lower)
            P[i, j] = v
            P[j, i] = v
    return (d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7], d[8], d[9], d[10])


@njit(cache=True)
def filter_step(P: np.ndarray, walk: np.ndarray, th: tuple, c_bt: tuple, xt: float, m_mG: tuple,
                dt_s: float, walk_scale: float, q_heading: float, q_bias: float, learn: bool,
                extra: tuple, extra_scale: float, r_mG2: float, rs_mG2: float, clip: float) -> tuple:
    """The field-vector test's step in one call: ``forget_covariance``, ``observe_covariance`` and,
    when ``learn`` (and Δt > 0), ``kalman_update`` with ν = m − H θ.  Returns (H θ, the predicted
    body field [mG]; H P Hᵀ before the update [mG², nine floats]; K ν, zeros when not learning)."""
    forget_covariance(P, walk, dt_s, walk_scale, q_heading, q_bias)
    pht, hph, a = observe_covariance(P, c_bt, th[2], th[3], xt)
    pred = predicted_field(th, c_bt, a, xt)
    step = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if learn and dt_s > 0.0:
        nu = (m_mG[0] - pred[0], m_mG[1] - pred[1], m_mG[2] - pred[2])
        step = kalman_update(P, pht, hph, extra, extra_scale, nu, r_mG2, rs_mG2, clip)
    return pred, hph, step


@njit(cache=True)
def quad_inv3(v, a) -> float:
    """vᵀ A⁻¹ v for a 3-vector v and a 3 × 3 matrix A (nine floats row by row), as vᵀ adj(A) v / det A."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8]
    v0, v1, v2 = v[0], v[1], v[2]
    c0, c1, c2 = a4 * a8 - a5 * a7, a5 * a6 - a3 * a8, a3 * a7 - a4 * a6
    det = a0 * c0 + a1 * c1 + a2 * c2
    return ((v0 * c0 + v1 * (a2 * a7 - a1 * a8) + v2 * (a1 * a5 - a2 * a4)) * v0
            + (v0 * c1 + v1 * (a0 * a8 - a2 * a6) + v2 * (a2 * a3 - a0 * a5)) * v1
            + (v0 * c2 + v1 * (a1 * a6 - a0 * a7) + v2 * (a0 * a4 - a1 * a3)) * v2) / det


@njit(cache=True)
def model_init(th: np.ndarray, P: np.ndarray, walk: np.ndarray, mv: np.ndarray, h0_mG: tuple, h_sd_mG: float,
               b_sd_mG: float, f_sd: float, h_tau_s: float, b_tau_s: float, f_tau_s: float, corr_s: float,
               heading_sd_rad: float, bias_sd_rad_s: float, bias_walk_rad_s2: float, gyro_scale: float) -> None:
    """The filter's start: θ = (0, 0, h₀, 0, 0), P = diag(prior variances), the random walks
    q = r_c / τ² per unit of r_c (f's per SIGNAL_SCALE of signal), no signal seen yet."""
    th[:] = 0.0
    th[2], th[3], th[4] = h0_mG[0], h0_mG[1], h0_mG[2]
    P[:, :] = 0.0
    P[0, 0] = heading_sd_rad ** 2
    P[1, 1] = bias_sd_rad_s ** 2
    walk[0] = walk[1] = 0.0
    for i in range(3):
        P[2 + i, 2 + i] = h_sd_mG ** 2
        P[5 + i, 5 + i] = b_sd_mG ** 2
        P[8 + i, 8 + i] = f_sd ** 2
        walk[2 + i] = 1.0 / (h_tau_s * h_tau_s)
        walk[5 + i] = 1.0 / (b_tau_s * b_tau_s)
        walk[8 + i] = (1.0 / SIGNAL_SCALE ** 2) / (f_tau_s * f_tau_s)
    mv[X0] = math.nan
    mv[LAST_XT] = 0.0
    mv[CORR_S] = corr_s
    mv[GYRO_SCALE] = gyro_scale
    mv[BIAS_WALK] = bias_walk_rad_s2


@njit(cache=True, inline="always")
def model_signal(mv: np.ndarray, x: float) -> float:
    """x̃ = x − x₀ (x₀ the first finite x); for a NaN x the last x̃ (0 before the first)."""
    if not math.isfinite(x):
        return mv[LAST_XT]
    if math.isnan(mv[X0]):
        mv[X0] = x
    mv[LAST_XT] = x - mv[X0]
    return mv[LAST_XT]


@njit(cache=True, inline="always")
def _walks(mv: np.ndarray, dt_s: float, sigma_mG: float, yaw_rate_rad_s: float) -> tuple:
    """(σ² τ_c Δt, the heading's and the yaw-rate bias's variance growth over Δt)."""
    return (sigma_mG * sigma_mG * mv[CORR_S] * dt_s, (mv[GYRO_SCALE] * yaw_rate_rad_s) ** 2 * dt_s,
            mv[BIAS_WALK] ** 2 * dt_s)


@njit(cache=True, inline="always")
def _noise(mv: np.ndarray, dt_s: float, sigma_mG: float) -> tuple:
    """(τ_c / Δt (0 when Δt ≤ 0), r = σ², r τ_c / Δt): the measurement noise of ``kalman_update``."""
    r = sigma_mG * sigma_mG
    k = mv[CORR_S] / dt_s if dt_s > 0.0 else 0.0
    return k, r, r * k


@njit(cache=True)
def model_forget(P: np.ndarray, walk: np.ndarray, mv: np.ndarray, dt_s: float, sigma_mG: float,
                 yaw_rate_rad_s: float) -> None:
    """The random walks over Δt (``forget_covariance`` with r_c = σ² τ_c)."""
    w, q_heading, q_bias = _walks(mv, dt_s, sigma_mG, yaw_rate_rad_s)
    forget_covariance(P, walk, dt_s, w, q_heading, q_bias)


@njit(cache=True)
def model_step(th: np.ndarray, P: np.ndarray, walk: np.ndarray, mv: np.ndarray, dt_s: float, sigma_mG: float,
               yaw_rate_rad_s: float, c_bt: tuple, xt: float, m_mG: tuple, learn: bool, clip: float,
               extra: tuple) -> tuple:
    """``filter_step`` with the filter's own walks and noise; θ += K ν when learning (Δt > 0).
    Returns (H θ [mG], H P Hᵀ before the update [mG², nine floats])."""
    w, q_heading, q_bias = _walks(mv, dt_s, sigma_mG, yaw_rate_rad_s)
    k, r, rs = _noise(mv, dt_s, sigma_mG)
    pred, hph, step = filter_step(P, walk, th, c_bt, xt, m_mG, dt_s, w, q_heading, q_bias, learn, extra, k, r, rs,
                                  clip)
    if learn and dt_s > 0.0:
        for i in range(11):
            th[i] = th[i] + step[i]
    return pred, hph


@njit(cache=True)
def model_update(th: np.ndarray, P: np.ndarray, mv: np.ndarray, pht: np.ndarray, hph: tuple, pred: tuple,
                 m_mG: tuple, dt_s: float, sigma_mG: float, clip: float, extra: tuple) -> None:
    """One measurement update (``kalman_update`` with ν = m − H θ, the filter's noise), none when Δt ≤ 0."""
    if dt_s <= 0.0:
        return
    nu = (m_mG[0] - pred[0], m_mG[1] - pred[1], m_mG[2] - pred[2])
    k, r, rs = _noise(mv, dt_s, sigma_mG)
    step = kalman_update(P, pht, hph, extra, k, nu, r, rs, clip)
    for i in range(11):
        th[i] = th[i] + step[i]


@njit(cache=True, inline="always")
def take_heading(th: np.ndarray) -> float:
    """ε, reset to 0 (ψ_f takes it)."""
    eps = th[0]
    th[0] = 0.0
    return eps


@njit(cache=True)
def restart_heading(th: np.ndarray, P: np.ndarray, heading_sd_rad: float) -> None:
    """ε = 0 with its prior variance and no covariance with the rest (ψ_f started again)."""
    th[0] = 0.0
    P[0, :] = 0.0
    P[:, 0] = 0.0
    P[0, 0] = heading_sd_rad ** 2


@njit(cache=True)
def inflate(P: np.ndarray, h_sd_mG: float, b_sd_mG: float) -> None:
    """h's and b's variances grown by h_sd² and b_sd² (learn them again)."""
    for i in range(3):
        P[2 + i, 2 + i] += h_sd_mG ** 2
        P[5 + i, 5 + i] += b_sd_mG ** 2
