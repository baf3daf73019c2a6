"""Block-end logic of the AHRS (estimators/ahrs.py): rest detection, gyro-bias update, acceleration
and magnetic rejection, field reference.  One implementation, compiled by numba (``close_block``),
run by both the per-sample ``Ahrs`` (``Supervisor.close``, once per block) and the batch
``run_ahrs`` (``supervise_blocks``, every block of a chunk in one compiled loop), so both forms
take the same decisions.  It runs ~10 times a second of data: as plain Python floats it was half
of the batch AHRS's time on a long log (issue 29).

Inputs per block (``BlockSums``, one row of ``BLOCK_FIELDS`` floats) are in the raw-gyro frame of
the block end: the filter vectors at the block end (before the bias rotation), the sum of the
fresh magnetometer samples rotated to the block end, and plain sums of the gyro and specific force
for the rest test.  The supervisor's state is one float array (``STATE``; NaN where there is no
value yet), its settings another (``settings_row``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from estimators.ahrs_math import ACCEPT, REJECT, rodrigues

__all__ = ["BlockSums", "Supervisor", "supervise_blocks", "BLOCK_FIELDS"]

_rodrigues = njit(cache=True)(rodrigues)      # the same function, compiled for close_block

# the state array: b̂ (3), the variants, the triggers and timers, the candidate and reference
# field (NaN: none yet), the rest test's low-passes (NaN: none yet), the knock, the gains cached
# for the block duration T_CACHED
(BIAS, _B1, _B2, VAR_G, VAR_M, ACC_TRIG, MAG_TRIG, DIST_T, REST_T, CAND_NORM, CAND_DIP, GYRO_NORM,
 ACC_RECOVERING, MAG_RECOVERING, AT_REST, ACC_QUIET, FIELD_DISTURBED, REF_NORM, REF_DIP, LP_W, _W1, _W2,
 LP_F, _F1, _F2, KNOCK, RESET_X1, KNOCK_T, SUS_T, T_CACHED, K_REST_LP, K_BIAS_REST, K_REF, K_REST_TILT,
 K_REST_FIELD, K_TILT, K_HEAD, STATE) = range(38)

# the settings row (``settings_row``): time constants and limits, and the angles' cosines
(S_REST_FILTER, S_BIAS_REST, S_FIELD_REF, S_REST_TILT, S_REST_FIELD, S_BIAS_TILT, S_SMOOTHING, S_BIAS_HEADING,
 S_FIELD_GAIN, S_BIAS_MAX, S_GRAVITY, S_BIAS_ACC_NORM, S_ACC_NORM_TOL, S_REST_TIME, S_RECOVERY_RATIO,
 S_KNOCK, S_KNOCK_END, S_KNOCK_HOLD, S_SUSTAINED_S, S_ACC_RECOVERY, S_FIELD_NORM_TOL, S_RELEARN_GYRO,
 S_FIELD_RELEARN, S_MAG_RECOVERY, S_COS_ACC, S_COS_SUS, S_COS_REST_DIR, S_PSI_MAX, S_DIP_TOL, S_G2, S_A2,
 S_Q2, S_GD2, S_AD2, SETTINGS) = range(35)

# a block's row: duration, x1, x2, x_m at the block end (rotated in place by ``close_block``: the
# next block's start), Σ fresh fields, their count, the rest test's sums, the initialisation flags,
# and the duration rounded to 1 ns by Python's round (the per-block gains are cached on it: block
# durations repeat up to round-off; numba's round differs from Python's in the last digit)
(DURATION, FAST, _X11, _X12, GRAVITY, _X21, _X22, FIELD, _XM1, _XM2, MAG_SUM, _MS1, _MS2, MAG_N, GYRO_SUM,
 _GS1, _GS2, GYRO_SQ, GYRO_N, FORCE_SUM, _FS1, _FS2, FORCE_SQ, FORCE_N, GRAVITY_INIT, FIELD_INIT,
 REINIT_GRAVITY, REINIT_FIELD, GAIN_DURATION, BLOCK_FIELDS) = range(30)


def settings_row(s) -> np.ndarray:
    """The settings ``close_block`` reads (estimators.ahrs.AhrsSettings), as one float array."""
    row = np.empty(SETTINGS)
    row[[S_REST_FILTER, S_BIAS_REST, S_FIELD_REF, S_REST_TILT, S_REST_FIELD, S_BIAS_TILT, S_SMOOTHING,
         S_BIAS_HEADING, S_FIELD_GAIN, S_BIAS_MAX, S_GRAVITY, S_BIAS_ACC_NORM, S_ACC_NORM_TOL, S_REST_TIME,
         S_RECOVERY_RATIO, S_KNOCK, S_KNOCK_END, S_KNOCK_HOLD, S_SUSTAINED_S, S_ACC_RECOVERY, S_FIELD_NORM_TOL,
         S_RELEARN_GYRO, S_FIELD_RELEARN, S_MAG_RECOVERY]] = (
        s.rest_filter_s, s.bias_rest_time_s, s.field_ref_time_s, s.rest_tilt_time_s, s.rest_field_time_s,
        s.bias_tilt_time_s, s.gravity_smoothing_per_s, s.bias_heading_time_s, s.field_gain_per_s,
        s.bias_max_rad_s, s.gravity_mps2, s.bias_acc_norm_mps2, s.acc_norm_tol_mps2, s.rest_time_s,
        s.recovery_ratio, s.acc_knock_mps2, s.acc_knock_end_mps2, s.acc_knock_hold_s, s.acc_sustained_s,
        s.acc_recovery_s, s.field_norm_tol, s.relearn_min_gyro_rad_s, s.field_relearn_s, s.mag_recovery_s)
    row[S_COS_ACC] = math.cos(math.radians(s.acc_reject_deg))
    row[S_COS_SUS] = math.cos(math.radians(s.acc_sustained_deg))
    row[S_COS_REST_DIR] = math.cos(math.radians(s.rest_dir_deg))
    row[S_PSI_MAX] = math.radians(s.mag_reject_deg)
    row[S_DIP_TOL] = math.radians(s.field_dip_tol_deg)
    row[S_G2], row[S_A2] = s.rest_gyro_rad_s ** 2, s.rest_acc_mps2 ** 2
    row[S_Q2] = s.bias_acc_spread_mps2 ** 2
    row[S_GD2], row[S_AD2] = s.rest_gyro_drift_rad_s ** 2, s.rest_acc_drift_mps2 ** 2
    return row


@dataclass(slots=True)
class BlockSums:
    duration_s: float
    fast_end: list              # x1 (first gravity stage) at the block end, raw-gyro frame
    gravity_end: list           # x2 (tilt) likewise
    field_end: list             # x_m likewise
    mag_sum: list               # Σ of the fresh magnetometer samples, rotated to the block end
    mag_n: int
    gyro_sum: tuple             # Σ ω of the valid gyro samples, Σ |ω|², count (rest test)
    gyro_sq: float
    gyro_n: int
    force_sum: tuple            # Σ f of the valid specific force samples, Σ |f|², count
    force_sq: float
    force_n: int
    gravity_init: bool          # the gravity stages are initialised at the block end
    field_init: bool
    reinit_gravity: bool        # a (re-)initialisation happened inside the block
    reinit_field: bool

    def row(self) -> np.ndarray:
        """The block as ``close_block`` reads it (BLOCK_FIELDS floats)."""
        return np.array([self.duration_s, *self.fast_end, *self.gravity_end, *self.field_end, *self.mag_sum,
                         self.mag_n, *self.gyro_sum, self.gyro_sq, self.gyro_n, *self.force_sum, self.force_sq,
                         self.force_n, self.gravity_init, self.field_init, self.reinit_gravity,
                         self.reinit_field, round(self.duration_s, 9)], dtype=np.float64)


@njit(cache=True)
def _cross(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float) -> tuple:
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True)
def _trigger(trig: float, bad: bool, T: float, limit: float, recovery_ratio: float) -> float:
    trig = trig + T if bad else trig - recovery_ratio * T
    return min(max(trig, 0.0), limit)


@njit(cache=True)
def _gains(st: np.ndarray, cfg: np.ndarray, T: float) -> None:
    """Per-block gains, cached for the block duration T (most blocks have the same)."""
    st[T_CACHED] = T
    st[K_REST_LP] = -math.expm1(-T / cfg[S_REST_FILTER])
    st[K_BIAS_REST] = -math.expm1(-T / cfg[S_BIAS_REST])
    st[K_REF] = -math.expm1(-T / cfg[S_FIELD_REF])
    st[K_REST_TILT] = -math.expm1(-T / cfg[S_REST_TILT])
    st[K_REST_FIELD] = -math.expm1(-T / cfg[S_REST_FIELD])
    st[K_TILT] = T / cfg[S_BIAS_TILT] * cfg[S_SMOOTHING]
    st[K_HEAD] = T / cfg[S_BIAS_HEADING] * cfg[S_FIELD_GAIN]


@njit(cache=True)
def _rest(st: np.ndarray, cfg: np.ndarray, b: np.ndarray, T: float) -> None:
    """Still: the gyro and specific-force spread inside the block (vibration, shocks), |f̄| within
    ``acc_norm_tol_mps2`` of g (a steady acceleration is not rest), and the
    drift of the block means from their low-pass (a slow rotation about a horizontal axis turns
    the specific force) under the thresholds, and f̄ within ``rest_dir_deg`` of the gyro-tracked
    tilt x2 (a specific force that turned without the gyro turning is a steady acceleration); at
    rest after ``rest_time_s`` still (VQF's rest detection on block means).  A slow turn about
    the vertical below ``bias_max_rad_s`` is not seen: a platform yawing slowly while otherwise
    still is taken for a gyro bias."""
    ng, nf = b[GYRO_N], b[FORCE_N]
    if not (ng != 0.0 and nf != 0.0):
        st[REST_T], st[AT_REST], st[ACC_QUIET] = 0.0, 0.0, 0.0
        return
    w0, w1, w2 = b[GYRO_SUM] / ng, b[GYRO_SUM + 1] / ng, b[GYRO_SUM + 2] / ng
    f0, f1, f2 = b[FORCE_SUM] / nf, b[FORCE_SUM + 1] / nf, b[FORCE_SUM + 2] / nf
    st[GYRO_NORM] = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if math.isnan(st[LP_W]):
        st[LP_W], st[LP_W + 1], st[LP_W + 2] = w0, w1, w2
        st[LP_F], st[LP_F + 1], st[LP_F + 2] = f0, f1, f2
    f2n = f0 * f0 + f1 * f1 + f2 * f2
    f_spread2 = b[FORCE_SQ] / nf - f2n
    g = cfg[S_GRAVITY]
    st[ACC_QUIET] = f_spread2 < cfg[S_Q2] and abs(math.sqrt(f2n) - g) < cfg[S_BIAS_ACC_NORM]
    still = (b[GYRO_SQ] / ng - (w0 * w0 + w1 * w1 + w2 * w2) < cfg[S_G2]
             and f_spread2 < cfg[S_A2] and abs(math.sqrt(f2n) - g) < cfg[S_ACC_NORM_TOL]
             and max(abs(w0), abs(w1), abs(w2)) < cfg[S_BIAS_MAX])
    c0, c1, c2 = b[GRAVITY], b[GRAVITY + 1], b[GRAVITY + 2]
    cn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2) * math.sqrt(f2n)
    if b[GRAVITY_INIT] != 0.0 and cn > 0.0:      # f̄ turned away from the gyro-tracked tilt: not gravity
        still = still and (f0 * c0 + f1 * c1 + f2 * c2) / cn > cfg[S_COS_REST_DIR]
    k = st[K_REST_LP]
    d0, d1, d2 = w0 - st[LP_W], w1 - st[LP_W + 1], w2 - st[LP_W + 2]
    still = still and d0 * d0 + d1 * d1 + d2 * d2 < cfg[S_GD2]
    st[LP_W] += k * d0
    st[LP_W + 1] += k * d1
    st[LP_W + 2] += k * d2
    d0, d1, d2 = f0 - st[LP_F], f1 - st[LP_F + 1], f2 - st[LP_F + 2]
    still = still and d0 * d0 + d1 * d1 + d2 * d2 < cfg[S_AD2]
    st[LP_F] += k * d0
    st[LP_F + 1] += k * d1
    st[LP_F + 2] += k * d2
    if not still:                       # moving: the low-pass starts again from this block, so
        st[LP_W], st[LP_W + 1], st[LP_W + 2] = w0, w1, w2    # a hold after a move is seen within rest_time_s
        st[LP_F], st[LP_F + 1], st[LP_F + 2] = f0, f1, f2
    st[REST_T] = st[REST_T] + T if still else 0.0
    st[AT_REST] = st[REST_T] >= cfg[S_REST_TIME]


@njit(cache=True)
def _gravity(st: np.ndarray, cfg: np.ndarray, b: np.ndarray, T: float, was_rest: bool) -> tuple:
    """Acceleration rejection on the low-passed stages: an acceleration shows as |x1| departing
    from g or x1 turning away from x2 (at once over ``acc_reject_deg``, or over
    ``acc_sustained_deg`` for ``acc_sustained_s``), a knock right after rest as the block's RMS
    |f| departing from g; then x2 holds on the gyro.  Returns the
    tilt-bias measurement r = x̂2 × x̂1 (times k2 in ``_gains``; zero when not usable): the
    second stage lags the first by β⊥/k2 under a residual bias β."""
    if b[REINIT_GRAVITY] != 0.0 or b[GRAVITY_INIT] == 0.0:
        st[ACC_TRIG], st[ACC_RECOVERING], st[VAR_G], st[SUS_T] = 0.0, 0.0, ACCEPT, 0.0
        st[KNOCK] = 0.0
        return 0.0, 0.0, 0.0
    used = st[VAR_G] == ACCEPT
    a0, a1, a2 = b[FAST], b[FAST + 1], b[FAST + 2]
    c0, c1, c2 = b[GRAVITY], b[GRAVITY + 1], b[GRAVITY + 2]
    n1 = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    n2 = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    if n1 == 0.0 or n2 == 0.0:
        return 0.0, 0.0, 0.0
    u10, u11, u12 = a0 / n1, a1 / n1, a2 / n1
    u20, u21, u22 = c0 / n2, c1 / n2, c2 / n2
    cos12 = u10 * u20 + u11 * u21 + u12 * u22
    # a sustained acceleration (the second detector): x1 more than acc_sustained_deg from x2 for
    # acc_sustained_s in a row; with k2 > k1 a 0.5 g step peaks at ~7° of x1-x2 angle, under the
    # immediate acc_reject_deg, while the oscillating translations of BROAD's trial 15 stay shorter
    st[SUS_T] = st[SUS_T] + T if cos12 < cfg[S_COS_SUS] else 0.0
    # a knock on a body at rest (the third detector): the block's RMS |f| (rotation-invariant)
    # departs from g by over acc_knock_mps2 right after rest; x2 holds until a block is back
    # within acc_knock_end_mps2 (at most acc_knock_hold_s), then x1, which low-passed the knock,
    # restarts from x2 (``close_block``) instead of handing the knock's residue to the tilt
    g = cfg[S_GRAVITY]
    dev = abs(math.sqrt(b[FORCE_SQ] / b[FORCE_N]) - g) if b[FORCE_N] != 0.0 else 0.0
    if was_rest and dev > cfg[S_KNOCK]:
        st[KNOCK], st[KNOCK_T] = 1.0, 0.0
    elif st[KNOCK] != 0.0:
        st[KNOCK_T] += T
    if st[KNOCK] != 0.0 and (dev < cfg[S_KNOCK_END] or st[KNOCK_T] >= cfg[S_KNOCK_HOLD]):
        st[KNOCK], st[RESET_X1] = 0.0, 1.0
    bad = (cos12 < cfg[S_COS_ACC] or abs(n1 - g) > cfg[S_ACC_NORM_TOL]
           or st[SUS_T] >= cfg[S_SUSTAINED_S] or st[KNOCK] != 0.0)
    trig = _trigger(st[ACC_TRIG], bad, T, cfg[S_ACC_RECOVERY], cfg[S_RECOVERY_RATIO])
    st[ACC_TRIG] = trig
    if trig >= cfg[S_ACC_RECOVERY]:
        st[ACC_RECOVERING] = 1.0
    elif trig <= 0.0:
        st[ACC_RECOVERING] = 0.0
    st[VAR_G] = ACCEPT if (st[ACC_RECOVERING] != 0.0 or not bad) else REJECT
    if not used or bad:
        return 0.0, 0.0, 0.0
    return _cross(u20, u21, u22, u10, u11, u12)


@njit(cache=True)
def _field(st: np.ndarray, cfg: np.ndarray, b: np.ndarray, T: float) -> tuple:
    """Magnetic rejection and reference.  Returns (ψ, up): the heading innovation of the block
    mean field about the up direction (ψ = 0 when not usable), for the heading-bias path."""
    if b[REINIT_FIELD] != 0.0:
        st[MAG_TRIG], st[DIST_T], st[MAG_RECOVERING], st[VAR_M] = 0.0, 0.0, 0.0, ACCEPT
        st[CAND_NORM] = math.nan
        st[FIELD_DISTURBED] = 0.0
    if b[MAG_N] == 0.0 or b[FIELD_INIT] == 0.0 or b[GRAVITY_INIT] == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    c0, c1, c2 = b[GRAVITY], b[GRAVITY + 1], b[GRAVITY + 2]          # x2 points up (−down)
    gn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    if gn == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    ux, uy, uz = c0 / gn, c1 / gn, c2 / gn
    n = b[MAG_N]
    mx, my, mz = b[MAG_SUM] / n, b[MAG_SUM + 1] / n, b[MAG_SUM + 2] / n
    norm = math.sqrt(mx * mx + my * my + mz * mz)
    if norm == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    q = ux * mx + uy * my + uz * mz
    dip = math.asin(max(-1.0, min(1.0, -q / norm)))
    if math.isnan(st[REF_NORM]):
        st[REF_NORM], st[REF_DIP] = norm, dip
    x0, x1, x2 = b[FIELD], b[FIELD + 1], b[FIELD + 2]
    p = ux * x0 + uy * x1 + uz * x2
    h10, h11, h12 = x0 - p * ux, x1 - p * uy, x2 - p * uz
    h20, h21, h22 = mx - q * ux, my - q * uy, mz - q * uz
    cr0, cr1, cr2 = _cross(h10, h11, h12, h20, h21, h22)
    psi = math.atan2(ux * cr0 + uy * cr1 + uz * cr2, h10 * h20 + h11 * h21 + h12 * h22)
    tol, dip_tol = cfg[S_FIELD_NORM_TOL], cfg[S_DIP_TOL]
    dist = abs(norm - st[REF_NORM]) > tol * st[REF_NORM] or abs(dip - st[REF_DIP]) > dip_tol
    # a new field: its strength and dip steady (within the tolerances of their own low-pass)
    # for field_relearn_s counted while turning faster than relearn_min_gyro_rad_s (a field
    # that stays the same while the body turns is homogeneous); then it is the reference
    if (not math.isnan(st[CAND_NORM]) and abs(norm - st[CAND_NORM]) <= tol * st[CAND_NORM]
            and abs(dip - st[CAND_DIP]) <= dip_tol):
        if st[GYRO_NORM] >= cfg[S_RELEARN_GYRO]:
            st[DIST_T] += T
        k = st[K_REF]
        st[CAND_NORM] += k * (norm - st[CAND_NORM])
        st[CAND_DIP] += k * (dip - st[CAND_DIP])
    else:
        st[CAND_NORM], st[CAND_DIP], st[DIST_T] = norm, dip, 0.0
    if dist and st[DIST_T] >= cfg[S_FIELD_RELEARN]:       # a new, lasting field: take it
        st[REF_NORM], st[REF_DIP] = st[CAND_NORM], st[CAND_DIP]
        dist = False
    st[FIELD_DISTURBED] = dist
    bad = dist or abs(psi) > cfg[S_PSI_MAX]
    trig = _trigger(st[MAG_TRIG], bad, T, cfg[S_MAG_RECOVERY], cfg[S_RECOVERY_RATIO])
    st[MAG_TRIG] = trig
    if trig >= cfg[S_MAG_RECOVERY]:
        st[MAG_RECOVERING] = 1.0
    elif trig <= 0.0:
        st[MAG_RECOVERING] = 0.0
    used = st[VAR_M] == ACCEPT
    if not bad:
        k = st[K_REF]
        st[REF_NORM] += k * (norm - st[REF_NORM])
        st[REF_DIP] += k * (dip - st[REF_DIP])
    st[VAR_M] = ACCEPT if (st[MAG_RECOVERING] != 0.0 or not bad) else REJECT
    if used and not bad:
        return psi, ux, uy, uz
    return 0.0, 0.0, 0.0, 0.0


@njit(cache=True)
def _pull_at_rest(st: np.ndarray, b: np.ndarray) -> None:
    """At rest the specific force is gravity and the body does not turn: the gravity stages
    are pulled to the block-mean specific force and the field vector to the block-mean field
    (when it is accepted) with the short time constants ``rest_tilt_time_s`` and
    ``rest_field_time_s``, so tilt and heading settle within a hold instead of over the
    motion time constants (1/k)."""
    if b[FORCE_N] != 0.0 and st[VAR_G] == ACCEPT:
        n, k = b[FORCE_N], st[K_REST_TILT]
        f0, f1, f2 = b[FORCE_SUM] / n, b[FORCE_SUM + 1] / n, b[FORCE_SUM + 2] / n
        for v in (FAST, GRAVITY):
            b[v] += k * (f0 - b[v])
            b[v + 1] += k * (f1 - b[v + 1])
            b[v + 2] += k * (f2 - b[v + 2])
    if b[MAG_N] != 0.0 and b[FIELD_INIT] != 0.0 and st[VAR_M] == ACCEPT and st[FIELD_DISTURBED] == 0.0:
        n, k = b[MAG_N], st[K_REST_FIELD]
        m0, m1, m2 = b[MAG_SUM] / n, b[MAG_SUM + 1] / n, b[MAG_SUM + 2] / n
        b[FIELD] += k * (m0 - b[FIELD])
        b[FIELD + 1] += k * (m1 - b[FIELD + 1])
        b[FIELD + 2] += k * (m2 - b[FIELD + 2])


@njit(cache=True)
def close_block(st: np.ndarray, cfg: np.ndarray, b: np.ndarray) -> None:
    """Decide the next block from block ``b`` (a BLOCK_FIELDS row): the state ``st`` is updated
    and b's vectors x1, x2, x_m become the next block's start vectors: the block-end vectors
    rotated by the bias that was in effect, R(b̂·T)."""
    T = b[DURATION]
    if b[GAIN_DURATION] != st[T_CACHED]:             # block durations repeat up to round-off
        _gains(st, cfg, b[GAIN_DURATION])
    was_rest = st[AT_REST] != 0.0
    _rest(st, cfg, b, T)
    r0, r1, r2 = _gravity(st, cfg, b, T, was_rest)
    psi, up0, up1, up2 = _field(st, cfg, b, T)
    bx, by, bz = st[BIAS], st[BIAS + 1], st[BIAS + 2]
    if st[AT_REST] != 0.0 and b[GYRO_N] != 0.0:
        k, n = st[K_BIAS_REST], b[GYRO_N]
        n0 = bx + k * (b[GYRO_SUM] / n - bx)
        n1 = by + k * (b[GYRO_SUM + 1] / n - by)
        n2 = bz + k * (b[GYRO_SUM + 2] / n - bz)
    else:
        kg = st[K_TILT] if st[ACC_QUIET] != 0.0 else 0.0
        km = st[K_HEAD] * psi
        n0, n1, n2 = bx + kg * r0 + km * up0, by + kg * r1 + km * up1, bz + kg * r2 + km * up2
    lim = cfg[S_BIAS_MAX]
    st[BIAS] = min(lim, max(-lim, n0))
    st[BIAS + 1] = min(lim, max(-lim, n1))
    st[BIAS + 2] = min(lim, max(-lim, n2))
    tx, ty, tz = -bx * T, -by * T, -bz * T            # rotation by +b̂·T (ahrs_math.rotate, inlined)
    c, sn, q = _rodrigues(tx, ty, tz)
    for v in (FAST, GRAVITY, FIELD):
        vx, vy, vz = b[v], b[v + 1], b[v + 2]
        d = q * (tx * vx + ty * vy + tz * vz)
        b[v] = c * vx - sn * (ty * vz - tz * vy) + d * tx
        b[v + 1] = c * vy - sn * (tz * vx - tx * vz) + d * ty
        b[v + 2] = c * vz - sn * (tx * vy - ty * vx) + d * tz
    if st[RESET_X1] != 0.0:                           # the knock is over: x1 restarts from x2
        st[RESET_X1] = 0.0
        b[FAST], b[FAST + 1], b[FAST + 2] = b[GRAVITY], b[GRAVITY + 1], b[GRAVITY + 2]
    if st[AT_REST] != 0.0:
        _pull_at_rest(st, b)


def new_state(expected_field=None, bias_rad_s=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The supervisor's state at the start (``STATE`` floats): the bias known beforehand, both
    variants accepted, the reference field the expected one (NaN: learned from the first)."""
    st = np.zeros(STATE)
    st[BIAS:BIAS + 3] = [float(v) for v in bias_rad_s]
    st[VAR_G] = st[VAR_M] = ACCEPT
    st[[CAND_NORM, CAND_DIP, T_CACHED, LP_W, LP_F]] = math.nan
    st[REF_NORM] = expected_field.strength_mG if expected_field else math.nan
    st[REF_DIP] = math.radians(expected_field.inclination_deg) if expected_field else 0.0
    return st


class Supervisor:
    """The block-end logic's state for the per-sample form; ``close`` consumes one block and
    decides the next (``close_block``)."""

    def __init__(self, s, expected_field=None, bias_rad_s=(0.0, 0.0, 0.0)):
        self.s = s
        self.cfg = settings_row(s)
        self.state = new_state(expected_field, bias_rad_s)

    @property
    def bias(self) -> list:
        return self.state[BIAS:BIAS + 3].tolist()

    @property
    def var_g(self) -> int:
        return int(self.state[VAR_G])

    @property
    def var_m(self) -> int:
        return int(self.state[VAR_M])

    @property
    def at_rest(self) -> bool:
        return bool(self.state[AT_REST])

    @property
    def field_disturbed(self) -> bool:
        return bool(self.state[FIELD_DISTURBED])

    def close(self, b: BlockSums) -> tuple[list, list, list]:
        """Decide the next block from block ``b``.  Returns the start vectors (x1, x2, x_m) of the
        next block: the block-end vectors rotated by the bias that was in effect, R(b̂·T)."""
        row = b.row()
        close_block(self.state, self.cfg, row)
        return row[FAST:FAST + 3].tolist(), row[GRAVITY:GRAVITY + 3].tolist(), row[FIELD:FIELD + 3].tolist()


# what supervise_blocks records per block, in force during it: the variants, at rest, b̂ (3),
# field disturbed
D_VAR_G, D_VAR_M, D_AT_REST, D_BIAS, _D1, _D2, D_DISTURBED, DECISIONS = range(8)


# a column of the batch form's block table (``ahrs_batch._block_loop``): P (3 × 3, row by row)
# and c (3 × 3: rows, then the stages x1, x2, x_m) of the first pass, Σm (3), the products
# α1, m21, m22, α_m, the rest test's sums, the duration, the counts and flags
(T_P, T_C, T_SUMS, T_PROD, T_STATS, T_DURATION, T_MAG_N, T_G_INIT, T_M_INIT, T_REINIT_G, T_REINIT_M,
 TABLE_COLUMNS) = (0, 9, 18, 21, 25, 35, 36, 37, 38, 39, 40, 41)


@njit(cache=True)
def supervise_blocks(st: np.ndarray, cfg: np.ndarray, table: np.ndarray, gain_T: np.ndarray,
                     x_start: np.ndarray) -> tuple:
    """The batch form's sequential pass (estimators.ahrs_batch, step 3) over every block of a
    chunk: each block's end vectors from its start vectors through the first pass's affine map
    (table, B × TABLE_COLUMNS: x1_end = α1 P x1 + c1, x2_end = m21 P x1 + m22 P x2 + c2 and
    x_m,end = α_m P x_m + c_m, or P x when the stage holds on the gyro), then ``close_block``;
    gain_T: the durations rounded as ``BlockSums.row`` does.  Returns the start vectors of every
    block (B, 9), the decisions in force during it (B, DECISIONS), and the start vectors (9,)
    of the block after the last."""
    B = table.shape[0]
    starts = np.empty((B, 9))
    decisions = np.empty((B, DECISIONS))
    x = x_start.copy()
    b = np.empty(BLOCK_FIELDS)
    for j in range(B):
        t = table[j]
        starts[j] = x
        decisions[j, D_VAR_G], decisions[j, D_VAR_M] = st[VAR_G], st[VAR_M]
        decisions[j, D_AT_REST], decisions[j, D_DISTURBED] = st[AT_REST], st[FIELD_DISTURBED]
        decisions[j, D_BIAS:D_BIAS + 3] = st[BIAS:BIAS + 3]
        accept_g = t[T_REINIT_G] != 0.0 or st[VAR_G] == ACCEPT
        accept_m = t[T_REINIT_M] != 0.0 or st[VAR_M] == ACCEPT
        al1, m21, m22, alm = t[T_PROD], t[T_PROD + 1], t[T_PROD + 2], t[T_PROD + 3]
        for r in range(3):
            p0, p1, p2 = t[T_P + 3 * r], t[T_P + 3 * r + 1], t[T_P + 3 * r + 2]
            q = p0 * x[0] + p1 * x[1] + p2 * x[2]
            b[FAST + r] = al1 * q + t[T_C + 3 * r]
            g = p0 * x[3] + p1 * x[4] + p2 * x[5]
            b[GRAVITY + r] = m21 * q + m22 * g + t[T_C + 3 * r + 1] if accept_g else g
            m = p0 * x[6] + p1 * x[7] + p2 * x[8]
            b[FIELD + r] = alm * m + t[T_C + 3 * r + 2] if accept_m else m
        b[DURATION] = t[T_DURATION]
        b[MAG_SUM:MAG_SUM + 3] = t[T_SUMS:T_SUMS + 3]
        b[MAG_N] = t[T_MAG_N]
        b[GYRO_SUM:GYRO_SUM + 3] = t[T_STATS:T_STATS + 3]
        b[GYRO_SQ], b[GYRO_N] = t[T_STATS + 3], t[T_STATS + 4]
        b[FORCE_SUM:FORCE_SUM + 3] = t[T_STATS + 5:T_STATS + 8]
        b[FORCE_SQ], b[FORCE_N] = t[T_STATS + 8], t[T_STATS + 9]
        b[GRAVITY_INIT] = 1.0 if t[T_G_INIT] > 0 else 0.0
        b[FIELD_INIT] = 1.0 if t[T_M_INIT] > 0 else 0.0
        b[REINIT_GRAVITY] = 1.0 if t[T_REINIT_G] > 0 else 0.0
        b[REINIT_FIELD] = 1.0 if t[T_REINIT_M] > 0 else 0.0
        b[GAIN_DURATION] = gain_T[j]
        close_block(st, cfg, b)
        x[:] = b[FAST:FAST + 9]
    return starts, decisions, x
