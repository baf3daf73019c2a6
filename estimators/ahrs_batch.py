"""Batch (replay) form of the AHRS of estimators/ahrs.py: same numbers as ``Ahrs``, vectorised.

Inside a block (see estimators/ahrs.py, "Schedule") every step is x' = a·R(−ω dt)·x + g·z (z the
measurement, or x1 for the second gravity stage) with a, g, ω and z known from the measurements and
the block's gating variant.  The mixing coefficients are scalars, so they commute with the rotations
and a block maps x_start to (M ⊗ P)·x_start + c, M a 2×2 (gravity stages) or scalar (field)
product.  So:
  1. a per-step table from the measurements alone (Rodrigues coefficients of the raw gyro step, the
     stage coefficients and increments), regrouped by position in the block (L × columns × blocks);
  2. pass 1, vectorised over blocks and looping over the position (≤ ``block_max_samples``): the
     raw-gyro rotation product P, M and c with the measurements used (a held stage is P alone) and
     the rotated field sum; the rest statistics are block sums (np.add.reduceat);
  3. a compiled loop over blocks (``ahrs_supervisor.supervise_blocks``): the block's end vectors
     for the variants chosen at the previous block end, then ``close_block`` (the code the
     per-sample form runs) decides bias, gating and the next start vectors;
  4. pass 2, vectorised over blocks again: every step from its block's true start vectors with the
     chosen variants, then the bias rotation (first order, as the per-sample outputs) and the angles.
Round-off: sums taken in a different order (the block maps, reduceat) differ from the per-sample
running values in the last bits only; the tests hold the two forms to 1e-9 with every flag equal.
Bad input is handled as in ``Ahrs``: time stamps by the running maximum (a non-finite or backwards
stamp is a zero step without measurements), non-finite gyro samples count as zero rate,
non-finite or zero measurements are skipped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.ahrs import AhrsSettings, ExpectedField
from estimators.ahrs_math import ACCEPT, REJECT, SERIES_MAX_RAD
from estimators.ahrs_supervisor import (D_AT_REST, D_BIAS, D_DISTURBED, D_VAR_G, D_VAR_M, T_DURATION, Supervisor,
                                       supervise_blocks)
from estimators.rotations import wrap_heading_rad

__all__ = ["AhrsResult", "run_ahrs", "angles_from_vectors"]


@dataclass
class AhrsResult:
    """Arrays on the IMU time base (length N); see ``estimators.ahrs.AhrsState`` for the fields."""
    t_s: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray             # magnetic heading, [0, 2π)
    mag_heading_rad: np.ndarray     # tilt-compensated heading of the latest magnetometer sample
    gyro_bias_rad_s: np.ndarray     # (N, 3)
    acc_rejected: np.ndarray
    mag_rejected: np.ndarray
    mag_disturbed: np.ndarray
    at_rest: np.ndarray
    valid: np.ndarray
    gravity_body: np.ndarray        # (N, 3) x2, m/s²
    field_body_mG: np.ndarray       # (N, 3)
    mag_latest_mG: np.ndarray       # (N, 3) latest applied magnetometer sample (zeros before)


def _rodrigues(theta: np.ndarray):
    """Vectorised ``estimators.ahrs_math.rodrigues`` (same formulas, same order)."""
    a2 = theta[:, 0] * theta[:, 0] + theta[:, 1] * theta[:, 1] + theta[:, 2] * theta[:, 2]
    small = a2 < SERIES_MAX_RAD * SERIES_MAX_RAD
    a = np.sqrt(np.where(small, 1.0, a2))
    c = np.cos(a)
    c = np.where(small, 1.0 - a2 * (0.5 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 / 40320.0))), c)
    s = np.where(small, 1.0 - a2 * (1.0 / 6.0 - a2 * (1.0 / 120.0 - a2 / 5040.0)), np.sin(a) / a)
    w = np.where(small, 0.5 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 / 40320.0)),
                 (1.0 - c) / np.where(small, 1.0, a2))
    return c, s, w


def _rotate(v: np.ndarray, t: np.ndarray, c, s, w) -> np.ndarray:
    """``estimators.ahrs_math.rotate`` on v (3, K, B) with θ (3, B) and coefficients (B,): the
    component axis first and the blocks last, so every operation runs on contiguous rows."""
    vx, vy, vz = v[0], v[1], v[2]
    tx, ty, tz = t[0], t[1], t[2]
    d = w * (tx * vx + ty * vy + tz * vz)
    out = np.empty_like(v)
    out[0] = c * vx - s * (ty * vz - tz * vy) + d * tx
    out[1] = c * vy - s * (tz * vx - tx * vz) + d * ty
    out[2] = c * vz - s * (tx * vy - ty * vx) + d * tz
    return out


def _gain(k: float, interval: np.ndarray, since: np.ndarray) -> np.ndarray:
    """Vectorised ``estimators.ahrs_math.measurement_gain``."""
    pos = interval > 0.0
    g = np.where(pos, -np.expm1(-k * interval), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        boost = interval / (since + interval)
    return np.where(pos & (since > 0.0), np.maximum(g, np.where(pos, boost, 0.0)), g)


def _first_in_segment(have: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """First step with ``have`` at the start and after each gap."""
    seg = np.cumsum(gap)
    out = np.zeros(len(have), bool)
    hi = np.flatnonzero(have)
    if len(hi):
        _, first = np.unique(seg[hi], return_index=True)
        out[hi[first]] = True
    return out


def _last_value(flag: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(value at the last flagged step at or before each step, any flagged so far)."""
    idx = np.maximum.accumulate(np.where(flag, np.arange(len(flag)), -1))
    return values[np.maximum(idx, 0)], idx >= 0


def _clean_time(t_raw: np.ndarray, max_gap_s: float):
    fin = np.isfinite(t_raw)
    tt = np.where(fin, t_raw, -np.inf)
    tt[0] = t_raw[0] if fin[0] else 0.0
    t = np.maximum.accumulate(tt)
    ok = fin.copy()
    ok[1:] &= t_raw[1:] >= t[:-1]
    dt = np.diff(t, prepend=t[0])
    gap = dt > max_gap_s
    return t, np.where(gap, 0.0, dt), ok, gap


def _magnetometer(mag: np.ndarray, t: np.ndarray, s: AhrsSettings):
    """Which IMU step applies which magnetometer sample (the last one when several arrive),
    the interval it stands for, and its time."""
    n = len(t)
    mt, mv = mag[:, 0], mag[:, 1:4]
    with np.errstate(invalid="ignore", over="ignore"):
        ok = np.isfinite(mt) & np.all(np.isfinite(mv), axis=1) & (np.sum(mv * mv, axis=1) > 1.0)
    prev = np.maximum.accumulate(np.where(ok, mt, -np.inf))
    ok &= mt >= np.r_[-np.inf, prev[:-1]]
    mt, mv = mt[ok], mv[ok]
    k = np.searchsorted(t, mt, side="left")
    keep = k < n
    mt, mv, k = mt[keep], mv[keep], k[keep]
    last = np.r_[k[1:] != k[:-1], True] if len(k) else np.zeros(0, bool)
    fresh = np.zeros(n, bool)
    m = np.zeros((n, 3))
    tm = np.zeros(n)
    interval = np.zeros(n)
    ks = k[last]
    fresh[ks] = True
    m[ks] = mv[last]
    tm[ks] = mt[last]
    if len(ks) > 1:
        interval[ks[1:]] = np.minimum(mt[last][1:] - mt[last][:-1], s.mag_max_interval_s)
    return fresh, m, tm, interval


def _blocks(t: np.ndarray, s: AhrsSettings):
    """Block index of every step, the rule of ``Ahrs._time``: a new block where the time grid of
    ``block_s`` moves on and the block has ``block_min_samples`` steps, or where it has
    ``block_max_samples``.  A loop over the blocks (plain integers)."""
    n = len(t)
    grid = np.floor(t / s.block_s)
    crossings = (np.flatnonzero(grid[1:] != grid[:-1]) + 1).tolist()
    lo, cap = s.block_min_samples, s.block_max_samples
    starts, s0, ci = [0], 0, 0
    while True:
        while ci < len(crossings) and crossings[ci] - s0 < lo:
            ci += 1
        nxt = min(crossings[ci] if ci < len(crossings) else n, s0 + cap)
        if nxt >= n:
            break
        starts.append(nxt)
        s0 = nxt
    starts = np.array(starts)
    lengths = np.diff(np.r_[starts, n])
    return np.repeat(np.arange(len(starts)), lengths), starts, lengths


def _pad(x: np.ndarray, fill) -> np.ndarray:
    return np.concatenate([x, np.full((1,) + x.shape[1:], fill, dtype=x.dtype)])


# columns of the per-step table (module docstring, step 1)
TH, CO, SI, VE, DT, A1, AM, INC1, INCM, MSUM, A2, G2 = (
    slice(0, 3), 3, 4, 5, 6, 7, 8, slice(9, 12), slice(12, 15), slice(15, 18), 18, 19)
N_COLS = 20
CHUNK_BLOCKS = 2048          # blocks per chunk of the passes (memory in cache, not the log's size)
_IDENTITY = np.zeros(N_COLS)
_IDENTITY[[CO, SI, VE, A1, AM, A2]] = [1.0, 1.0, 0.5, 1.0, 1.0, 1.0]


def _measurements(imu: np.ndarray, mag: np.ndarray, s: AhrsSettings) -> dict:
    """Measurement-only per-step quantities over the whole log (cleaned time, rates, specific
    force, the magnetometer sample each step applies, (re)initialisations, stage gains)."""
    t, dt, time_ok, gap = _clean_time(imu[:, 0], s.max_gap_s)
    w_raw = imu[:, 1:4]
    gyro_ok = np.all(np.isfinite(w_raw), axis=1)
    w = np.where(gyro_ok[:, None], w_raw, 0.0)
    f = np.where(time_ok[:, None] & np.all(np.isfinite(imu[:, 4:7]), axis=1)[:, None], imu[:, 4:7], 0.0)
    n2 = f[:, 0] * f[:, 0] + f[:, 1] * f[:, 1] + f[:, 2] * f[:, 2]
    f_valid = n2 > 0.0
    fresh, m, tm, interval = _magnetometer(mag, t, s)
    reinit_g = _first_in_segment(f_valid, gap)
    reinit_m = _first_in_segment(fresh, gap)
    t_init_g, g_init = _last_value(reinit_g, t)
    t_init_m, m_init = _last_value(reinit_m, tm)
    blend = g_init & ~reinit_g
    g1 = np.where(reinit_g, 1.0, np.where(blend & f_valid, _gain(s.gravity_gain_per_s, dt, t - t_init_g), 0.0))
    g2 = np.where(reinit_g, 1.0, np.where(blend, _gain(s.gravity_smoothing_per_s, dt, t - t_init_g), 0.0))
    gm = np.where(reinit_m, 1.0, np.where(m_init & fresh, _gain(s.field_gain_per_s, interval, tm - t_init_m), 0.0))
    latest, _ = _last_value(fresh, m)
    return dict(t=t, dt=dt, w=w, gyro_ok=gyro_ok, f=f, n2=n2, f_valid=f_valid, fresh=fresh, m=m, latest=latest,
                reinit_g=reinit_g, reinit_m=reinit_m, g_init=g_init, m_init=m_init, g1=g1, g2=g2, gm=gm)


def _table(ms: dict, k0: int, k1: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps k0..k1−1 as the table (N_COLS, k1 − k0 + 1; the last column an identity step for
    padding): Rodrigues coefficients of the raw gyro step, dt, the stage coefficients a and
    increments g·z; and their rest statistics (k1 − k0, 11): ω (3), |ω|², ω valid, f (3), |f|²,
    f valid, dt."""
    sl = slice(k0, k1)
    n = k1 - k0
    w, f, m, dt = ms["w"][sl], ms["f"][sl], ms["m"][sl], ms["dt"][sl]
    g1, g2, gm, re_g, re_m = ms["g1"][sl], ms["g2"][sl], ms["gm"][sl], ms["reinit_g"][sl], ms["reinit_m"][sl]
    tab = np.empty((N_COLS, n + 1))
    tab[:, n] = _IDENTITY
    tab[TH, :n] = (w * dt[:, None]).T
    tab[CO, :n], tab[SI, :n], tab[VE, :n] = _rodrigues(tab[TH, :n].T)
    tab[DT, :n] = dt
    tab[A1, :n] = np.where(re_g, 0.0, 1.0 - g1)
    tab[AM, :n] = np.where(re_m, 0.0, 1.0 - gm)
    tab[INC1, :n] = (g1[:, None] * f).T
    tab[INCM, :n] = (gm[:, None] * m).T
    tab[MSUM, :n] = np.where(ms["fresh"][sl, None], m, 0.0).T
    tab[A2, :n] = np.where(re_g, 0.0, 1.0 - g2)
    tab[G2, :n] = g2
    stats = np.c_[w, w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1] + w[:, 2] * w[:, 2], ms["gyro_ok"][sl], f,
                  ms["n2"][sl], ms["f_valid"][sl], dt]
    return tab, stats


class _Layout:
    """Steps regrouped by position in the block: ``take(a)`` turns a per-step array (N+1, ...)
    into (L, ..., B) — position first, blocks last — with the identity step as padding."""

    def __init__(self, starts: np.ndarray, lengths: np.ndarray, n: int):
        pos = np.arange(int(lengths.max()) if len(starts) else 0)[:, None]
        self.valid = pos < lengths[None, :]
        self.idx = np.where(self.valid, starts[None, :] + pos, n)
        self.L, self.B = self.idx.shape

    def take(self, a: np.ndarray) -> np.ndarray:
        g = a[self.idx]
        return np.ascontiguousarray(np.moveaxis(g, 1, -1)) if g.ndim > 2 else g


def _pass1(X: np.ndarray) -> dict:
    """Block maps and sums, vectorised over blocks (module docstring, step 2); X is the step table
    by position, (L, N_COLS, B).  Columns of x: P (3), c1, c2, c_m, Σm; products α1 = Π a1,
    (m21, m22) of the second stage, α_m."""
    B = X.shape[2]
    x = np.zeros((3, 7, B))
    for r in range(3):
        x[r, r] = 1.0
    prod = np.ones((4, B))               # α1, m21, m22, α_m
    prod[1] = 0.0
    for Xp in X:
        x = _rotate(x, Xp[TH], Xp[CO], Xp[SI], Xp[VE])
        x[:, 3] = x[:, 3] * Xp[A1] + Xp[INC1]
        x[:, 4] = x[:, 4] * Xp[A2] + Xp[G2] * x[:, 3]
        x[:, 5] = x[:, 5] * Xp[AM] + Xp[INCM]
        x[:, 6] = x[:, 6] + Xp[MSUM]
        prod[0] = prod[0] * Xp[A1]
        prod[1] = Xp[G2] * prod[0] + Xp[A2] * prod[1]
        prod[2] = prod[2] * Xp[A2]
        prod[3] = prod[3] * Xp[AM]
    return dict(P=x[:, :3].transpose(2, 0, 1), c=x[:, 3:6].transpose(2, 0, 1), sums=x[:, 6].T, prod=prod.T)


def _block_loop(p1: dict, counts: dict, sup: Supervisor, x_start: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sequential block-end logic (module docstring, step 3), compiled
    (``ahrs_supervisor.supervise_blocks``, the per-sample form's ``close_block`` for each block).
    Returns per block the start vectors [x1, x2, x_m] (B, 9) and the decisions in force during it
    (B, ahrs_supervisor.DECISIONS: gravity variant, field variant, at rest, bias, field disturbed),
    and the start vectors of the block after the last (9,)."""
    B = len(p1["prod"])
    table = np.concatenate([p1["P"].reshape(B, 9), p1["c"].reshape(B, 9), p1["sums"], p1["prod"], p1["stats"],
                            np.c_[counts["mag_n"], counts["g_init"], counts["m_init"], counts["reinit_g"],
                                  counts["reinit_m"]]], axis=1).astype(np.float64)
    gain_T = np.array([round(d, 9) for d in table[:, T_DURATION].tolist()])   # as BlockSums.row
    return supervise_blocks(sup.state, sup.cfg, np.ascontiguousarray(table), gain_T, x_start)


def _pass2(X: np.ndarray, lay: _Layout, fl: dict, starts: np.ndarray, decisions: np.ndarray, n: int):
    """Every step from its block's start vectors with the chosen variants (module docstring,
    step 4).  Returns the raw vectors (N, 3, 3: x1, x2, x_m), τ (N,) and the variants (N, 2)."""
    var_b = decisions[:, D_VAR_G:D_VAR_M + 1].astype(int)                   # (B, 2)
    after = [np.logical_or.accumulate(lay.take(_pad(fl[k], False)), axis=0) for k in ("reinit_g", "reinit_m")]
    hold_g = (var_b[:, 0] == REJECT)[None, :] & ~after[0]                   # (L, B)
    hold_m = (var_b[:, 1] == REJECT)[None, :] & ~after[1]
    a2 = np.where(hold_g, 1.0, X[:, A2])                                    # (L, B)
    g2 = np.where(hold_g, 0.0, X[:, G2])
    am = np.where(hold_m, 1.0, X[:, AM])
    incm = np.where(hold_m[:, None], 0.0, X[:, INCM])                       # (L, 3, B)
    x = starts.reshape(-1, 3, 3).transpose(2, 1, 0)                         # (3, 3 vectors, B)
    out = np.empty((lay.L, 3, 3, lay.B))
    for p, Xp in enumerate(X):
        x = _rotate(x, Xp[TH], Xp[CO], Xp[SI], Xp[VE])
        x[:, 0] = x[:, 0] * Xp[A1] + Xp[INC1]
        x[:, 1] = x[:, 1] * a2[p] + g2[p] * x[:, 0]
        x[:, 2] = x[:, 2] * am[p] + incm[p]
        out[p] = x
    tau = np.cumsum(X[:, DT], axis=0)          # sequential along the block, as the per-sample τ
    sel = lay.idx[lay.valid]
    raw, tau_n, var = np.empty((n, 3, 3)), np.empty(n), np.empty((n, 2), int)
    raw[sel] = out.transpose(0, 3, 1, 2)[lay.valid]
    tau_n[sel] = tau[lay.valid]
    var[sel, 0] = np.where(hold_g, REJECT, ACCEPT)[lay.valid]
    var[sel, 1] = np.where(hold_m, REJECT, ACCEPT)[lay.valid]
    return raw, tau_n, var


def run_ahrs(imu: np.ndarray, mag: np.ndarray, settings: AhrsSettings | None = None, *,
             expected_field: ExpectedField | None = None, gyro_bias_rad_s=(0.0, 0.0, 0.0)) -> AhrsResult:
    """Batch AHRS over a log; the same numbers as feeding ``estimators.ahrs.Ahrs`` sample by sample.

    imu: (N, 7) [t_s, gx, gy, gz rad/s, ax, ay, az m/s²];  mag: (M, 4) [t_s, mx, my, mz mG]
    (calibrated), body FRD.  Returns arrays on the IMU time base; outputs are always finite.
    The blocks are processed ``CHUNK_BLOCKS`` at a time (memory stays small and in cache).
    """
    s = settings or AhrsSettings()
    imu = np.asarray(imu, dtype=float).reshape(-1, 7)
    mag = np.asarray(mag, dtype=float).reshape(-1, 4)
    n = len(imu)
    if n == 0:
        z, z3, zb = np.zeros(0), np.zeros((0, 3)), np.zeros(0, bool)
        return AhrsResult(z, z, z, z, z, z3, zb, zb, zb, zb, zb, z3, z3, z3)
    ms = _measurements(imu, mag, s)
    _, starts, lengths = _blocks(ms["t"], s)
    sup = Supervisor(s, expected_field, gyro_bias_rad_s)
    x_start = np.zeros(9)
    parts = []
    for j0 in range(0, len(starts), CHUNK_BLOCKS):
        j1 = min(len(starts), j0 + CHUNK_BLOCKS)
        k0, k1 = int(starts[j0]), int(starts[j1]) if j1 < len(starts) else n
        st, ln = starts[j0:j1] - k0, lengths[j0:j1]
        tab, stats = _table(ms, k0, k1)
        lay = _Layout(st, ln, k1 - k0)
        X = np.ascontiguousarray(tab[:, lay.idx].transpose(1, 0, 2))   # (L, N_COLS, blocks)
        p1 = _pass1(X)
        p1["stats"] = np.add.reduceat(stats, st, axis=0)     # to round-off the per-sample running sums
        fl = {k: ms[k][k0:k1] for k in ("t", "fresh", "m", "latest", "reinit_g", "reinit_m", "g_init", "m_init")}
        ends = st + ln - 1
        bid = np.repeat(np.arange(j1 - j0), ln)
        counts = dict(mag_n=np.add.reduceat(fl["fresh"].astype(int), st), g_init=fl["g_init"][ends],
                      m_init=fl["m_init"][ends], reinit_g=np.add.reduceat(fl["reinit_g"].astype(int), st) > 0,
                      reinit_m=np.add.reduceat(fl["reinit_m"].astype(int), st) > 0)
        starts_x, decisions, x_start = _block_loop(p1, counts, sup, x_start)
        raw, tau, var = _pass2(X, lay, fl, starts_x, decisions, k1 - k0)
        bias = decisions[bid, D_BIAS:D_BIAS + 3]
        flags = decisions[bid][:, [D_AT_REST, D_DISTURBED]] != 0.0
        parts.append(list(_outputs(fl, raw, tau, var, bias, flags)))
    return AhrsResult(*(_joined(parts, j) for j in range(len(parts[0]))))


def _joined(parts: list[list], j: int) -> np.ndarray:
    """Field j of every chunk's outputs in one array; the chunks' copies are freed as it goes
    (the result and one field's chunks at a time, not every chunk beside the result)."""
    out = np.concatenate([p[j] for p in parts])
    for p in parts:
        p[j] = None
    return out


def _outputs(fl: dict, raw: np.ndarray, tau: np.ndarray, var: np.ndarray, bias: np.ndarray,
             flags: np.ndarray) -> tuple:
    """Bias rotation to first order (x + (b̂τ) × x, as ``Ahrs._state``), angles and flags, in the
    order of ``AhrsResult``'s fields."""
    p = bias * tau[:, None]
    px, py, pz = p[:, 0], p[:, 1], p[:, 2]
    v = []
    for col in (1, 2):
        x, y, z = raw[:, 0, col], raw[:, 1, col], raw[:, 2, col]
        v.append(np.stack([x + py * z - pz * y, y + pz * x - px * z, z + px * y - py * x], axis=1))
    g, m = v
    valid = fl["g_init"] & fl["m_init"]
    latest = fl["latest"]
    roll, pitch, yaw, mag_heading = (np.where(valid, a, 0.0) for a in angles_from_vectors(g, m, latest))
    return (fl["t"], roll, pitch, yaw, mag_heading, bias, fl["g_init"] & (var[:, 0] == REJECT),
            var[:, 1] == REJECT, flags[:, 1], flags[:, 0], valid, g, m, latest)


def angles_from_vectors(g: np.ndarray, m: np.ndarray, latest: np.ndarray) -> tuple:
    """Vectorised ``estimators.ahrs_math.attitude_from_vectors`` (same formulas, same order):
    (roll, pitch, heading of m, heading of ``latest``) [rad] from body specific force g (N, 3) and
    fields (N, 3)."""
    roll = np.arctan2(-g[:, 1], -g[:, 2])
    pitch = np.arctan2(g[:, 0], np.hypot(g[:, 1], g[:, 2]))
    sr, cr, sp, cp = np.sin(roll), np.cos(roll), np.sin(pitch), np.cos(pitch)
    spsr, spcr = sp * sr, sp * cr
    heads = [wrap_heading_rad(np.arctan2(-(h[:, 1] * cr - h[:, 2] * sr),
                                         h[:, 0] * cp + h[:, 1] * spsr + h[:, 2] * spcr)) for h in (m, latest)]
    return roll, pitch, heads[0], heads[1]
