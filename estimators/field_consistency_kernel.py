"""The field-vector consistency test's step, compiled by numba (issue 29: it runs at every IMU step
of a log; as Python it was ~22 s of a 28 s ``magstation analyze``).  The algorithm, its equations
and sources are estimators.field_consistency's docstring; this module is its one implementation:
``FieldConsistency.update`` (live, one step a call) and ``field_consistency`` (batch, ``run`` over
the rows) both run ``step``.

State, all arrays (the caller allocates them with ``new_state``):
* ``st`` (float64, ST_SIZE): the scalars below, NaN for "none yet" (a time, a heading), then the
  field model's θ, random walks and scalars (estimators.field_model_kernels' ``model_*``) and the
  tilt tracker's state (estimators.residual_trackers' ``tilt_update``);
* ``P`` (11 × 11): the field model's covariance;
* the recent-sample windows as rings of rows (estimators.ring_buffers, CAPACITY rows each):
  ``sig_t`` the motor signal's times over ``signal_lag_s``, ``sig_hi``/``sig_lo`` (t, x) its
  running maximum and minimum (monotone queues), ``tilt_hist`` (t, p, u) over ``tilt_lag_s``;
  ``ptr`` (int64, 4 × 2) their heads and counts, a row per ring (SIG, HI, LO, HIST).
* ``cfg`` (float64): the settings (``settings_array``, radians converted once).
``out`` (float64, OUT_SIZE) receives the step: z, q, r̄ (3), status, f (3), f's sd (3).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from estimators import ring_buffers as ring
from estimators.field_model_kernels import (MODEL_SCALARS, inflate, model_init, model_signal, model_step,
                                           quad_inv3, restart_heading, take_heading)
from estimators.residual_trackers import (TILT_LAG, TILT_MAX, TILT_MEMORY, TILT_PARAMS, TILT_REG, TILT_STATE,
                                          TILT_X, TILT_Y, tilt_update)
from estimators.rotations import dcm_body_to_ned_float

__all__ = ["SETTINGS", "settings_array", "new_state", "step", "run", "OUT_SIZE", "ST_SIZE"]

ON, LEARNING, OFF_NO_FIELD, OFF_LOW_RATE, OFF_ATTITUDE, SETTLING = range(6)     # field_consistency.STATUS

# cfg: FieldConsistencySettings' fields by name, in this order, then the angles in radians
SETTINGS = ("learn_s", "model_field_sd_mG", "model_offset_sd_mG", "model_motor_sd", "model_field_tau_s",
            "model_offset_tau_s", "model_motor_tau_s", "model_corr_s", "model_clip_sigma", "signal_lag_s",
            "relearn_sd_mG", "turn_learn_s", "post_turn_s", "tilt_learn_after_s", "tilt_lag_s", "tilt_memory_s",
            "tilt_reg_mG2_s", "model_start_s", "model_gyro_scale", "freeze_max_s", "reanchor_peak",
            "reanchor_margin", "reanchor_s", "relearn_s", "unexplained_q", "fast_turn_q", "turn_evidence",
            "smooth_s", "noise_floor_mG", "noise_track_s", "cusum_drift", "cusum_threshold_s", "cusum_cap",
            "freeze_z", "min_rate_hz", "max_gap_s", "settle_s", "segment_gap_s")
(LEARN_S, FIELD_SD, OFFSET_SD, MOTOR_SD, FIELD_TAU, OFFSET_TAU, MOTOR_TAU, CORR_S, CLIP_SIGMA, SIGNAL_LAG,
 RELEARN_SD, TURN_LEARN_S, POST_TURN_S, TILT_LEARN_AFTER, TILT_LAG_S, TILT_MEMORY_S, TILT_REG_S, MODEL_START_S,
 GYRO_SCALE, FREEZE_MAX_S, REANCHOR_PEAK, REANCHOR_MARGIN, REANCHOR_S, RELEARN_S, UNEXPLAINED_Q, FAST_TURN_Q,
 TURN_EVIDENCE, SMOOTH_S, NOISE_FLOOR, NOISE_TRACK_S, DRIFT, THRESHOLD_S, CAP, FREEZE_Z, MIN_RATE, MAX_GAP,
 SETTLE_S, SEGMENT_GAP) = range(len(SETTINGS))
RADIANS = ("turn_deg", "tilt_min_turn_deg_s", "tilt_max_turn_deg_s", "model_max_turn_deg_s", "first_turn_hold_deg_s",
           "reanchor_heading_deg", "model_heading_sd_deg", "model_yaw_bias_sd_deg_s", "tilt_max_deg")
(TURN_RAD, TILT_MIN_RATE, TILT_MAX_RATE, MODEL_MAX_RATE, HOLD_RATE, REANCHOR_HEADING, HEADING_SD, BIAS_SD,
 TILT_MAX_RAD) = range(len(SETTINGS), len(SETTINGS) + len(RADIANS))
BIAS_WALK_RAD_S2 = 1.0e-4      # the yaw-rate bias's random walk [rad/s²] (FieldModelFilter's default)

# st: the test's scalars (NaN: none yet) ...
(T_LAST, ATT_SINCE, PSI, PSI_LEARNED, TURN_UNTIL, LEARNED_S, YAW_RATE, FROZEN_SINCE, NOISE_SUM, NOISE_N, NOISE_MS,
 NOISE_MG, R_OK, R0, R1, R2, S, Z, PEAK_Q, LOW_SINCE, Q_LAST, S_TURN, RELEARN_UNTIL, TURN_HOLD_UNTIL, SETTLE_UNTIL,
 PRIOR_KNOWN, PRIOR0, PRIOR1, PRIOR2, MODEL_ON) = range(30)
TH = 30                        # ... the field model's θ (11) ...
WALK = TH + 11                 # ... its random walks (11) ...
MV = WALK + 11                 # ... its scalars (MODEL_SCALARS) ...
TV = MV + MODEL_SCALARS        # ... and the tilt tracker's (TILT_PARAMS)
ST_SIZE = TV + TILT_PARAMS
SIG, HI, LO, HIST = range(4)   # the rings' rows in ``ptr``
OUT_Z, OUT_Q, OUT_R, OUT_STATUS, OUT_F, OUT_F_SD = 0, 1, 2, 5, 6, 9
OUT_SIZE = 12

_dcm = njit(cache=True, inline="always")(dcm_body_to_ned_float)     # the one C_b^n of estimators.rotations


def settings_array(s) -> np.ndarray:
    """cfg for a FieldConsistencySettings: SETTINGS' values, then RADIANS' in radians."""
    return np.array([float(getattr(s, name)) for name in SETTINGS]
                    + [math.radians(getattr(s, name)) for name in RADIANS])


def new_state(cfg: np.ndarray) -> tuple:
    """(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr) of a test that has seen nothing."""
    st = np.zeros(ST_SIZE)
    st[PRIOR0:PRIOR2 + 1] = math.nan
    arrays = (st, np.zeros((11, 11)), np.zeros(ring.CAPACITY), np.zeros((ring.CAPACITY, 2)),
              np.zeros((ring.CAPACITY, 2)), np.zeros((ring.CAPACITY, 7)), np.zeros((4, 2), dtype=np.int64))
    reset(*arrays, cfg)
    return arrays


@njit(cache=True, inline="always")
def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def reset(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg) -> None:
    """From scratch (a new segment): no model, no tilt, nothing learned (the prior is kept)."""
    st[MODEL_ON] = 0.0
    tv = st[TV:TV + TILT_PARAMS]
    tv[:TILT_STATE] = 0.0
    tv[TILT_LAG], tv[TILT_MEMORY], tv[TILT_REG], tv[TILT_MAX] = (cfg[TILT_LAG_S], cfg[TILT_MEMORY_S], cfg[TILT_REG_S],
                                                                 cfg[TILT_MAX_RAD])
    st[ATT_SINCE] = st[PSI_LEARNED] = st[TURN_UNTIL] = math.nan
    st[LEARNED_S] = st[YAW_RATE] = 0.0
    st[NOISE_SUM] = st[NOISE_N] = st[NOISE_MS] = 0.0
    st[NOISE_MG] = st[T_LAST] = math.nan
    restart(st, P, ptr, cfg, -math.inf)


@njit(cache=True)
def restart(st, P, ptr, cfg, settle_until: float) -> None:
    """After an IMU gap: ψ_f, the score and the windows start again (the model is kept; ψ_f's
    error ε is new)."""
    st[PSI] = math.nan
    st[R_OK] = 0.0
    st[S] = st[Z] = 0.0
    st[FROZEN_SINCE] = math.nan
    st[PEAK_Q], st[LOW_SINCE] = 0.0, math.nan
    st[Q_LAST] = 0.0
    st[S_TURN] = 0.0
    st[RELEARN_UNTIL] = -math.inf
    st[TURN_HOLD_UNTIL] = -math.inf
    st[SETTLE_UNTIL] = settle_until
    ptr[:, :] = 0                   # the rings emptied
    if st[MODEL_ON] != 0.0:
        restart_heading(st[TH:TH + 11], P, cfg[HEADING_SD])


@njit(cache=True, inline="always")
def _off(st, out, status: float) -> None:
    st[R_OK] = 0.0
    st[S] = st[Z] = 0.0
    st[FROZEN_SINCE] = math.nan
    out[OUT_Z] = out[OUT_Q] = math.nan
    out[OUT_R] = out[OUT_R + 1] = out[OUT_R + 2] = math.nan
    out[OUT_STATUS] = status


@njit(cache=True, inline="always")
def _track_heading(st, cfg, dt: float, roll: float, pitch: float, m0: float, m1: float, m2: float,
                   gyro_q: float, gyro_r: float) -> None:
    """ψ_f: started at the tilt-compensated magnetic heading of the Earth part of the field
    (turned onto the model's h after a gap), then the gyro's yaw rate (ZYX Euler kinematics) less β̂."""
    if math.isnan(st[PSI]):
        if st[MODEL_ON] != 0.0 and st[T_LAST] < st[SETTLE_UNTIL]:
            return          # after a gap the field held may be from before it: start once it is back
        c = _dcm(roll, pitch, 0.0)          # tilt only: the field levelled
        psi = -math.atan2(c[3] * m0 + c[4] * m1 + c[5] * m2, c[0] * m0 + c[1] * m1 + c[2] * m2)
        if st[MODEL_ON] != 0.0:             # the heading at which the model's h fits
            psi = _wrap(psi + math.atan2(st[TH + 3], st[TH + 2]))
        st[PSI] = psi
        return
    cos_p = math.cos(pitch)
    rate = (gyro_q * math.sin(roll) + gyro_r * math.cos(roll)) / cos_p if abs(cos_p) > 1e-3 else 0.0
    if not math.isfinite(rate):
        rate = 0.0
    st[YAW_RATE] = rate
    beta = st[TH + 1] if st[MODEL_ON] != 0.0 else 0.0
    st[PSI] = _wrap(st[PSI] + (rate - beta) * dt)


@njit(cache=True, inline="always")
def _signal_spread(st, sig_t, sig_hi, sig_lo, ptr, cfg, t: float, x: float) -> float:
    """Half the range of the motor signal over the last ``signal_lag_s`` (monotone queues of its
    maximum and minimum)."""
    cap = sig_t.shape[0]
    q, hi, lo = ptr[SIG], ptr[HI], ptr[LO]
    if math.isfinite(x):
        sig_t[ring.push(q, cap)] = t
        while ring.size(hi) > 0 and sig_hi[ring.last(hi, cap), 1] <= x:
            ring.pop_back(hi)
        i = ring.push(hi, cap)
        sig_hi[i, 0], sig_hi[i, 1] = t, x
        while ring.size(lo) > 0 and sig_lo[ring.last(lo, cap), 1] >= x:
            ring.pop_back(lo)
        i = ring.push(lo, cap)
        sig_lo[i, 0], sig_lo[i, 1] = t, x
    t0 = t - cfg[SIGNAL_LAG]
    while ring.size(q) > 0 and sig_t[ring.first(q, cap)] < t0:
        ring.pop_front(q, cap)
    while ring.size(hi) > 0 and sig_hi[ring.first(hi, cap), 0] < t0:
        ring.pop_front(hi, cap)
    while ring.size(lo) > 0 and sig_lo[ring.first(lo, cap), 0] < t0:
        ring.pop_front(lo, cap)
    if ring.size(q) < 2:
        return 0.0
    return 0.5 * (sig_hi[ring.first(hi, cap), 1] - sig_lo[ring.first(lo, cap), 1])


@njit(cache=True, inline="always")
def _relearning_turn(st, cfg, t: float, learning: bool) -> bool:
    """True while the first big turn after learning is being learned again."""
    if learning or math.isnan(st[PSI]):
        return False
    if math.isnan(st[PSI_LEARNED]):
        st[PSI_LEARNED] = st[PSI]
    if (math.isnan(st[TURN_UNTIL]) and st[Z] < cfg[FREEZE_Z]
            and abs(_wrap(st[PSI] - st[PSI_LEARNED])) > cfg[TURN_RAD]):
        st[TURN_UNTIL] = t + cfg[TURN_LEARN_S]
    return not math.isnan(st[TURN_UNTIL]) and t < st[TURN_UNTIL]


@njit(cache=True, inline="always")
def _learning_allowed(st, cfg) -> bool:
    """Learning pauses while the score is at ``freeze_z`` or more, for ``freeze_max_s`` at most."""
    if st[Z] < cfg[FREEZE_Z] or math.isnan(st[FROZEN_SINCE]):
        return True
    return st[T_LAST] - st[FROZEN_SINCE] > cfg[FREEZE_MAX_S]


@njit(cache=True, inline="always")
def _noise_cov(hph: tuple, lag: tuple, sigma: float) -> tuple:
    """Σ = σ²/3 I + H P Hᵀ + the signal's lag term [mG², nine floats row by row]."""
    v = sigma * sigma / 3.0
    return (hph[0] + lag[0] + v, hph[1] + lag[1], hph[2] + lag[2],
            hph[3] + lag[3], hph[4] + lag[4] + v, hph[5] + lag[5],
            hph[6] + lag[6], hph[7] + lag[7], hph[8] + lag[8] + v)


@njit(cache=True, inline="always")
def _non_heading_q(st, cfg, c: tuple, r: tuple, sigma: float) -> tuple:
    """(|r̄| without the part a heading error ε of ψ_f explains, in σ; ε [rad]) (∞ and NaN beyond
    ``reanchor_heading_deg``): a heading error is a residual ε (−h_E, h_N, 0) in the navigation frame."""
    h0, h1 = st[TH + 2], st[TH + 3]
    rn0 = c[0] * r[0] + c[1] * r[1] + c[2] * r[2]
    rn1 = c[3] * r[0] + c[4] * r[1] + c[5] * r[2]
    rn2 = c[6] * r[0] + c[7] * r[1] + c[8] * r[2]
    hh = math.hypot(h0, h1)
    if not hh > 0:
        return math.sqrt(rn0 * rn0 + rn1 * rn1 + rn2 * rn2) / sigma, math.nan
    along = (-h1 * rn0 + h0 * rn1) / hh
    if abs(along) > cfg[REANCHOR_HEADING] * hh:
        return math.inf, math.nan
    return math.sqrt(max(rn0 * rn0 + rn1 * rn1 + rn2 * rn2 - along * along, 0.0)) / sigma, along / hh


@njit(cache=True, inline="always")
def _fast_turn(st, cfg, t: float, q: float, q_other: float, eps: float) -> bool:
    """True while the CUSUM holds for a fast turn and ``post_turn_s`` after it (unless q ≥
    ``fast_turn_q``); when the hold ends, a residual that is a heading error alone leaves ψ_f."""
    if abs(st[YAW_RATE]) > cfg[HOLD_RATE]:
        st[TURN_HOLD_UNTIL] = t + cfg[POST_TURN_S]
        return q < cfg[FAST_TURN_Q]
    if t < st[TURN_HOLD_UNTIL]:
        return q < cfg[FAST_TURN_Q]
    if st[TURN_HOLD_UNTIL] > -math.inf:
        st[TURN_HOLD_UNTIL] = -math.inf
        if q_other < cfg[DRIFT] + cfg[REANCHOR_MARGIN] and math.isfinite(eps):
            st[PSI] = _wrap(st[PSI] - eps)
    return False


@njit(cache=True, inline="always")
def _reanchor(st, P, cfg, t: float, q: float, frozen: bool) -> None:
    """The end of a disturbance: after an alarm that reached ``reanchor_peak`` σ, the residual
    (apart from a heading error) below (κ + ``reanchor_margin``) σ for ``reanchor_s``: relearn."""
    if not frozen:
        st[PEAK_Q], st[LOW_SINCE] = 0.0, math.nan
        return
    if st[Z] >= 1.0:
        st[PEAK_Q] = max(st[PEAK_Q], q)
    low = q < cfg[DRIFT] + cfg[REANCHOR_MARGIN]
    st[LOW_SINCE] = (t if math.isnan(st[LOW_SINCE]) else st[LOW_SINCE]) if low else math.nan
    if st[PEAK_Q] >= cfg[REANCHOR_PEAK] and low and t - st[LOW_SINCE] >= cfg[REANCHOR_S]:
        st[RELEARN_UNTIL] = t + cfg[RELEARN_S]
        inflate(P, cfg[RELEARN_SD], cfg[RELEARN_SD])
        st[S] = st[Z] = 0.0
        st[FROZEN_SINCE], st[PEAK_Q], st[LOW_SINCE] = math.nan, 0.0, math.nan


@njit(cache=True, inline="always")
def _sigma(st, cfg) -> float:
    return st[NOISE_MG] if math.isfinite(st[NOISE_MG]) else cfg[NOISE_FLOOR]


@njit(cache=True, inline="always")
def _noise(st, cfg, learning: bool, turn: bool, dt: float, r: tuple, size: float, hph: tuple, lag: tuple) -> None:
    """σ: RMS of |r̄| over the last quarter of learning, then following min(|r̄|², σ² r̄ᵀ Σ⁻¹ r̄ / 3)
    with ``noise_track_s`` while the test is quiet (not a residual no turn explains)."""
    if learning and st[LEARNED_S] >= 0.75 * cfg[LEARN_S]:
        st[NOISE_SUM] += size * size
        st[NOISE_N] += 1.0
        st[NOISE_MS] = st[NOISE_SUM] / st[NOISE_N]
    elif not (learning or turn) and st[NOISE_N] != 0.0 and st[Z] < cfg[FREEZE_Z] and st[Q_LAST] < cfg[UNEXPLAINED_Q]:
        sigma = _sigma(st, cfg)
        sample = min(size * size, max(quad_inv3(r, _noise_cov(hph, lag, sigma)) / 3.0, 0.0) * sigma * sigma)
        st[NOISE_MS] += (1.0 - math.exp(-dt / cfg[NOISE_TRACK_S])) * (sample - st[NOISE_MS])
    if st[NOISE_N] != 0.0:
        st[NOISE_MG] = max(cfg[NOISE_FLOOR], math.sqrt(st[NOISE_MS]))


@njit(cache=True)
def _test(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t: float, dt: float, c: tuple,
          m0: float, m1: float, m2: float, x: float, out) -> None:
    """The tested step: the model's step, the tilt's, r̄, σ, q and the CUSUM (module docstring of
    estimators.field_consistency)."""
    th, walk, mv, tv = st[TH:TH + 11], st[WALK:WALK + 11], st[MV:MV + MODEL_SCALARS], st[TV:TV + TILT_PARAMS]
    learning = st[LEARNED_S] < cfg[LEARN_S]
    st[LEARNED_S] += min(dt, cfg[MAX_GAP])
    xt = model_signal(mv, x)
    spread = _signal_spread(st, sig_t, sig_hi, sig_lo, ptr, cfg, t, x)
    h0, h1, h2 = th[2], th[3], th[4]
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = c
    p0, p1, p2 = c0 * h0 + c3 * h1 + c6 * h2, c1 * h0 + c4 * h1 + c7 * h2, c2 * h0 + c5 * h1 + c8 * h2
    tx, ty = tv[TILT_X], tv[TILT_Y]
    cbt = ((c0 + ty * c2, c3 + ty * c5, c6 + ty * c8),                 # R(δ)Cᵀ, R(δ) ≈ I + [δ×]
           (c1 - tx * c2, c4 - tx * c5, c7 - tx * c8),
           (c2 - ty * c0 + tx * c1, c5 - ty * c3 + tx * c4, c8 - ty * c6 + tx * c7))
    f0, f1, f2 = th[8], th[9], th[10]
    s2 = spread * spread if spread > 0.0 else 0.0    # the signal's timing: f fᵀ spread² [mG², row by row]
    lag = (s2 * (f0 * f0), s2 * (f0 * f1), s2 * (f0 * f2), s2 * (f1 * f0), s2 * (f1 * f1),
           s2 * (f1 * f2), s2 * (f2 * f0), s2 * (f2 * f1), s2 * (f2 * f2))
    turn = _relearning_turn(st, cfg, t, learning) or t < st[RELEARN_UNTIL]
    allowed = _learning_allowed(st, cfg)
    sigma = _sigma(st, cfg)
    yaw_rate = st[YAW_RATE]
    learn = (turn or allowed) and abs(yaw_rate) <= cfg[MODEL_MAX_RATE]
    pred, hph = model_step(th, P, walk, mv, dt, sigma, yaw_rate, cbt, xt, (m0, m1, m2), learn, cfg[CLIP_SIGMA], lag)
    e0, e1, e2 = m0 - pred[0], m1 - pred[1], m2 - pred[2]
    if learn:
        st[PSI] = _wrap(st[PSI] - take_heading(th))
    tilt_learns = ((turn or allowed) and st[LEARNED_S] >= cfg[TILT_LEARN_AFTER]
                   and cfg[TILT_MIN_RATE] <= abs(yaw_rate) <= cfg[TILT_MAX_RATE])
    tilt_update(tv, tilt_hist, ptr[HIST], t, p0, p1, p2, m0 - p0 - th[5] - th[8] * xt,
                m1 - p1 - th[6] - th[9] * xt, m2 - p2 - th[7] - th[10] * xt, dt, tilt_learns,
                cfg[CLIP_SIGMA] * _sigma(st, cfg))
    if st[R_OK] != 0.0:
        a = 1.0 - math.exp(-dt / cfg[SMOOTH_S])
        st[R0] += a * (e0 - st[R0])
        st[R1] += a * (e1 - st[R1])
        st[R2] += a * (e2 - st[R2])
    else:
        st[R0], st[R1], st[R2], st[R_OK] = e0, e1, e2, 1.0
    r = (st[R0], st[R1], st[R2])
    size = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    _noise(st, cfg, learning, turn, dt, r, size, hph, lag)
    sigma = _sigma(st, cfg)
    # q: r̄ against the noise and the model's own uncertainty, Σ = σ²/3 I + H P Hᵀ + lag term
    q = st[Q_LAST] = math.sqrt(max(quad_inv3(r, _noise_cov(hph, lag, sigma)) / 3.0, 0.0))
    fast = abs(yaw_rate) > cfg[HOLD_RATE]
    q_other, eps = _non_heading_q(st, cfg, c, r, sigma)
    if fast and not learning and t >= st[SETTLE_UNTIL]:     # a fast turn's evidence, summed apart
        st[S_TURN] = min(max(0.0, st[S_TURN] + dt * (min(q, q_other) - cfg[DRIFT])), cfg[CAP] * cfg[THRESHOLD_S])
    else:
        st[S_TURN] = 0.0
    if turn and not learning and q >= (cfg[FAST_TURN_Q] if fast else cfg[UNEXPLAINED_Q]):
        turn = False            # a residual no turn explains: the relearning ends and the test judges it
        st[TURN_UNTIL] = st[RELEARN_UNTIL] = t
    out[OUT_Q], out[OUT_R], out[OUT_R + 1], out[OUT_R + 2] = q, r[0], r[1], r[2]
    if learning or turn or t < st[SETTLE_UNTIL]:
        st[S] = st[Z] = 0.0
        out[OUT_Z] = 0.0 if (turn or learning) else math.nan
        out[OUT_STATUS] = LEARNING if (learning or turn) else SETTLING
        return
    if not _fast_turn(st, cfg, t, q, q_other, eps):
        st[S] = min(max(0.0, st[S] + dt * (q - cfg[DRIFT])), cfg[CAP] * cfg[THRESHOLD_S])
        if cfg[TURN_EVIDENCE] != 0.0 and fast and q >= cfg[FAST_TURN_Q]:   # released by the residual in the turn
            st[S] = max(st[S], st[S_TURN])
    st[Z] = st[S] / cfg[THRESHOLD_S]
    frozen = st[Z] >= cfg[FREEZE_Z]
    st[FROZEN_SINCE] = (t if math.isnan(st[FROZEN_SINCE]) else st[FROZEN_SINCE]) if frozen else math.nan
    _reanchor(st, P, cfg, t, q_other, frozen)
    out[OUT_Z] = st[Z]
    out[OUT_STATUS] = ON


@njit(cache=True)
def step(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t: float, m0: float, m1: float, m2: float,
         roll: float, pitch: float, attitude_ok: bool, gyro_q: float, gyro_r: float, x: float, rate_hz: float,
         field_ok: bool, out) -> None:
    """One IMU step (``FieldConsistency.update``'s arguments, the gyro's q and r only) into ``out``."""
    if not math.isnan(st[T_LAST]) and (t < st[T_LAST] or t - st[T_LAST] > cfg[SEGMENT_GAP]):
        reset(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg)
    dt = 0.0 if math.isnan(st[T_LAST]) else t - st[T_LAST]
    st[T_LAST] = t
    if dt > cfg[MAX_GAP]:
        restart(st, P, ptr, cfg, t + cfg[SETTLE_S])
    _step(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t, dt, m0, m1, m2, roll, pitch, attitude_ok,
          gyro_q, gyro_r, x, rate_hz, field_ok, out)
    model_on = st[MODEL_ON] != 0.0
    for k in range(3):
        out[OUT_F + k] = st[TH + 8 + k] if model_on else 0.0
        v = P[8 + k, 8 + k]
        out[OUT_F_SD + k] = (math.sqrt(v) if v >= 0.0 else math.nan) if model_on else math.inf


@njit(cache=True)
def _step(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t, dt, m0, m1, m2, roll, pitch, attitude_ok,
          gyro_q, gyro_r, x, rate_hz, field_ok, out) -> None:
    """``step`` after the time checks: ψ_f, the switch-offs, the model's start, the tested step."""
    th = st[TH:TH + 11]
    have_field = field_ok and math.isfinite(m0) and math.isfinite(m1) and math.isfinite(m2)
    if attitude_ok and have_field:
        if math.isnan(st[ATT_SINCE]):
            st[ATT_SINCE] = t
        model_on = st[MODEL_ON] != 0.0
        dx = model_signal(st[MV:MV + MODEL_SCALARS], x) if model_on else 0.0
        b0, b1, b2 = (th[5], th[6], th[7]) if model_on else (0.0, 0.0, 0.0)
        f0, f1, f2 = (th[8], th[9], th[10]) if model_on else (0.0, 0.0, 0.0)
        v0, v1, v2 = m0 - b0 - f0 * dx, m1 - b1 - f1 * dx, m2 - b2 - f2 * dx
        tx, ty = st[TV + TILT_X], st[TV + TILT_Y]      # R(δ)ᵀ v ≈ v − δ × v: in the attitude's axes
        _track_heading(st, cfg, dt, roll, pitch, v0 - ty * v2, v1 + tx * v2, v2 - tx * v1 + ty * v0, gyro_q, gyro_r)
    else:
        st[PSI] = math.nan
        st[ATT_SINCE] = math.nan
    if not have_field:
        _off(st, out, float(OFF_NO_FIELD))
        return
    if not rate_hz >= cfg[MIN_RATE]:
        _off(st, out, float(OFF_LOW_RATE))
        return
    if math.isnan(st[PSI]):
        _off(st, out, float(SETTLING if t < st[SETTLE_UNTIL] else OFF_ATTITUDE))
        return
    c = _dcm(roll, pitch, st[PSI])
    if st[MODEL_ON] == 0.0:
        if t - st[ATT_SINCE] < cfg[MODEL_START_S]:
            st[PSI] = math.nan      # the attitude settles first: ψ_f starts on a settled tilt
            _off(st, out, float(SETTLING))
            return
        if (st[PRIOR_KNOWN] != 0.0 and math.isfinite(st[PRIOR0]) and math.isfinite(st[PRIOR1])
                and math.isfinite(st[PRIOR2])):
            h0 = (st[PRIOR0], st[PRIOR1], st[PRIOR2])
        else:                       # no prior: the first field is the Earth field
            h0 = (c[0] * m0 + c[1] * m1 + c[2] * m2, c[3] * m0 + c[4] * m1 + c[5] * m2,
                  c[6] * m0 + c[7] * m1 + c[8] * m2)
        model_init(th, P, st[WALK:WALK + 11], st[MV:MV + MODEL_SCALARS], h0, cfg[FIELD_SD], cfg[OFFSET_SD],
                   cfg[MOTOR_SD], cfg[FIELD_TAU], cfg[OFFSET_TAU], cfg[MOTOR_TAU], cfg[CORR_S], cfg[HEADING_SD],
                   cfg[BIAS_SD], BIAS_WALK_RAD_S2, cfg[GYRO_SCALE])
        st[MODEL_ON] = 1.0
    _test(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t, dt, c, m0, m1, m2, x, out)


@njit(cache=True)
def run(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t, mag, roll, pitch, attitude_ok, gyro, x, rate_hz,
        field_ok, prior, prior_from_s: float, outs) -> None:
    """``step`` over rows (the batch form): the prior (NaNs: none) known from ``prior_from_s`` on;
    outs (N × OUT_SIZE) receives each step's ``out``."""
    have_prior = not (math.isnan(prior[0]) and math.isnan(prior[1]) and math.isnan(prior[2]))
    for i in range(t.shape[0]):
        if st[PRIOR_KNOWN] == 0.0 and have_prior and t[i] >= prior_from_s:
            st[PRIOR0], st[PRIOR1], st[PRIOR2], st[PRIOR_KNOWN] = prior[0], prior[1], prior[2], 1.0
        step(st, P, sig_t, sig_hi, sig_lo, tilt_hist, ptr, cfg, t[i], mag[i, 0], mag[i, 1], mag[i, 2], roll[i],
             pitch[i], attitude_ok[i], gyro[i, 1], gyro[i, 2], x[i], rate_hz[i], field_ok[i], outs[i])
