"""Block-end logic of the AHRS (estimators/ahrs.py): rest detection, gyro-bias update, acceleration
and magnetic rejection, field reference.  One implementation, run by both the per-sample ``Ahrs``
and the batch ``run_ahrs`` once per block, so both forms take the same decisions.

Inputs per block (``BlockSums``) are in the raw-gyro frame of the block end: the filter vectors at
the block end (before the bias rotation), the sum of the fresh magnetometer samples rotated to the
block end, and plain sums of the gyro and specific force for the rest test.  Plain floats: this
runs ~20 times a second of data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from estimators.ahrs_math import ACCEPT, REJECT, rodrigues

__all__ = ["BlockSums", "Supervisor"]


@dataclass(slots=True)
class BlockSums:
    duration_s: float
    fast_end: list              # x1 (first gravity stage) at the block end, raw-gyro frame; rotated
    gravity_end: list           # x2 (tilt) likewise                                  in place by
    field_end: list             # x_m likewise                                        ``close``
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


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


class Supervisor:
    """State of the block-end logic; ``close`` consumes one block and decides the next."""

    def __init__(self, s, expected_field=None, bias_rad_s=(0.0, 0.0, 0.0)):
        self.s = s
        self.bias = [float(b) for b in bias_rad_s]
        self.var_g, self.var_m = ACCEPT, ACCEPT
        self.acc_trig = self.mag_trig = self.dist_t = self.rest_t = 0.0
        self.cand_norm = self.cand_dip = None         # candidate new field (VQF's new-field acceptance)
        self.gyro_norm = 0.0                          # |block-mean gyro| [rad/s]
        self.acc_recovering = self.mag_recovering = False
        self.at_rest = False
        self.acc_quiet = False                       # the block's specific force is near g and steady
        self.field_disturbed = False                 # the latest block-mean field departs from the reference
        self.ref_norm = expected_field.strength_mG if expected_field else None
        self.ref_dip = math.radians(expected_field.inclination_deg) if expected_field else 0.0
        self.lp_w: list | None = None
        self.lp_f: list | None = None
        self.knock = self.reset_x1 = False            # a knock from rest is being held; x1 := x2 due
        self.knock_t = 0.0                           # time since the knock [s]
        self.sus_t = 0.0                             # time x1 has been over acc_sustained_deg from x2 [s]
        self._cos_acc = math.cos(math.radians(s.acc_reject_deg))
        self._cos_sus = math.cos(math.radians(s.acc_sustained_deg))
        self._cos_rest_dir = math.cos(math.radians(s.rest_dir_deg))
        self._psi_max = math.radians(s.mag_reject_deg)
        self._dip_tol = math.radians(s.field_dip_tol_deg)
        self._g2, self._a2 = s.rest_gyro_rad_s ** 2, s.rest_acc_mps2 ** 2
        self._q2 = s.bias_acc_spread_mps2 ** 2
        self._gd2, self._ad2 = s.rest_gyro_drift_rad_s ** 2, s.rest_acc_drift_mps2 ** 2
        self._T = None                               # block duration the cached gains are for

    def _gains(self, T: float) -> None:
        """Per-block gains (cached: most blocks have the same duration)."""
        s = self.s
        self._T = T
        self._k_rest_lp = -math.expm1(-T / s.rest_filter_s)
        self._k_bias_rest = -math.expm1(-T / s.bias_rest_time_s)
        self._k_ref = -math.expm1(-T / s.field_ref_time_s)
        self._k_rest_tilt = -math.expm1(-T / s.rest_tilt_time_s)
        self._k_rest_field = -math.expm1(-T / s.rest_field_time_s)
        self._k_tilt = T / s.bias_tilt_time_s * s.gravity_smoothing_per_s
        self._k_head = T / s.bias_heading_time_s * s.field_gain_per_s

    def close(self, b: BlockSums) -> tuple[list, list, list]:
        """Decide the next block from block ``b``.  Returns the start vectors (x1, x2, x_m) of the
        next block: the block-end vectors rotated by the bias that was in effect, R(b̂·T)."""
        T = b.duration_s
        if round(T, 9) != self._T:             # block durations repeat up to round-off
            self._gains(round(T, 9))
        was_rest = self.at_rest
        self._rest(b, T)
        r_g = self._gravity(b, T, was_rest)
        psi, up = self._field(b, T)
        bx, by, bz = self.bias
        if self.at_rest and b.gyro_n:
            k, n = self._k_bias_rest, b.gyro_n
            gs = b.gyro_sum
            nb = (bx + k * (gs[0] / n - bx), by + k * (gs[1] / n - by), bz + k * (gs[2] / n - bz))
        else:
            kg, km = (self._k_tilt if self.acc_quiet else 0.0), self._k_head * psi
            nb = (bx + kg * r_g[0] + km * up[0], by + kg * r_g[1] + km * up[1], bz + kg * r_g[2] + km * up[2])
        lim = self.s.bias_max_rad_s
        n0, n1, n2 = nb
        self.bias = [min(lim, max(-lim, n0)), min(lim, max(-lim, n1)), min(lim, max(-lim, n2))]
        tx, ty, tz = -bx * T, -by * T, -bz * T            # rotation by +b̂·T (ahrs_math.rotate, inlined)
        c, sn, q = rodrigues(tx, ty, tz)
        for v in (b.fast_end, b.gravity_end, b.field_end):   # in place: the caller passes fresh lists
            vx, vy, vz = v
            d = q * (tx * vx + ty * vy + tz * vz)
            v[0] = c * vx - sn * (ty * vz - tz * vy) + d * tx
            v[1] = c * vy - sn * (tz * vx - tx * vz) + d * ty
            v[2] = c * vz - sn * (tx * vy - ty * vx) + d * tz
        if self.reset_x1:                                  # the knock is over: x1 restarts from x2
            self.reset_x1 = False
            b.fast_end[:] = b.gravity_end
        if self.at_rest:
            self._pull_at_rest(b)
        return b.fast_end, b.gravity_end, b.field_end

    def _pull_at_rest(self, b: BlockSums) -> None:
        """At rest the specific force is gravity and the body does not turn: the gravity stages
        are pulled to the block-mean specific force and the field vector to the block-mean field
        (when it is accepted) with the short time constants ``rest_tilt_time_s`` and
        ``rest_field_time_s``, so tilt and heading settle within a hold instead of over the
        motion time constants (1/k)."""
        if b.force_n and self.var_g == ACCEPT:
            n, k = b.force_n, self._k_rest_tilt
            f = (b.force_sum[0] / n, b.force_sum[1] / n, b.force_sum[2] / n)
            for v in (b.fast_end, b.gravity_end):
                v[0] += k * (f[0] - v[0]); v[1] += k * (f[1] - v[1]); v[2] += k * (f[2] - v[2])  # noqa: E702
        if b.mag_n and b.field_init and self.var_m == ACCEPT and not self.field_disturbed:
            n, k, v = b.mag_n, self._k_rest_field, b.field_end
            m = (b.mag_sum[0] / n, b.mag_sum[1] / n, b.mag_sum[2] / n)
            v[0] += k * (m[0] - v[0]); v[1] += k * (m[1] - v[1]); v[2] += k * (m[2] - v[2])  # noqa: E702

    def _rest(self, b: BlockSums, T: float) -> None:
        """Still: the gyro and specific-force spread inside the block (vibration, shocks), |f̄| within
        ``acc_norm_tol_mps2`` of g (a steady acceleration is not rest), and the
        drift of the block means from their low-pass (a slow rotation about a horizontal axis turns
        the specific force) under the thresholds, and f̄ within ``rest_dir_deg`` of the gyro-tracked
        tilt x2 (a specific force that turned without the gyro turning is a steady acceleration); at
        rest after ``rest_time_s`` still (VQF's rest detection on block means).  A slow turn about
        the vertical below ``bias_max_rad_s`` is not seen: a platform yawing slowly while otherwise
        still is taken for a gyro bias."""
        if not (b.gyro_n and b.force_n):
            self.rest_t, self.at_rest, self.acc_quiet = 0.0, False, False
            return
        s = self.s
        ng, nf = b.gyro_n, b.force_n
        w = (b.gyro_sum[0] / ng, b.gyro_sum[1] / ng, b.gyro_sum[2] / ng)
        f = (b.force_sum[0] / nf, b.force_sum[1] / nf, b.force_sum[2] / nf)
        self.gyro_norm = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        if self.lp_w is None:
            self.lp_w, self.lp_f = list(w), list(f)
        f2 = f[0] * f[0] + f[1] * f[1] + f[2] * f[2]
        f_spread2 = b.force_sq / nf - f2
        self.acc_quiet = (f_spread2 < self._q2 and abs(math.sqrt(f2) - s.gravity_mps2) < s.bias_acc_norm_mps2)
        still = (b.gyro_sq / ng - (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) < self._g2
                 and f_spread2 < self._a2 and abs(math.sqrt(f2) - s.gravity_mps2) < s.acc_norm_tol_mps2
                 and max(abs(w[0]), abs(w[1]), abs(w[2])) < s.bias_max_rad_s)
        c = b.gravity_end
        cn = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]) * math.sqrt(f2)
        if b.gravity_init and cn > 0.0:      # f̄ turned away from the gyro-tracked tilt: not gravity
            still = still and (f[0] * c[0] + f[1] * c[1] + f[2] * c[2]) / cn > self._cos_rest_dir
        k = self._k_rest_lp
        for x, lp, lim2 in ((w, self.lp_w, self._gd2), (f, self.lp_f, self._ad2)):
            d0, d1, d2 = x[0] - lp[0], x[1] - lp[1], x[2] - lp[2]
            still = still and d0 * d0 + d1 * d1 + d2 * d2 < lim2
            lp[0] += k * d0; lp[1] += k * d1; lp[2] += k * d2  # noqa: E702
        if not still:                       # moving: the low-pass starts again from this block, so
            self.lp_w[:], self.lp_f[:] = w, f   # a hold after a move is seen within rest_time_s
        self.rest_t = self.rest_t + T if still else 0.0
        self.at_rest = self.rest_t >= s.rest_time_s

    def _trigger(self, trig: float, bad: bool, T: float, limit: float) -> float:
        trig = trig + T if bad else trig - self.s.recovery_ratio * T
        return min(max(trig, 0.0), limit)

    def _gravity(self, b: BlockSums, T: float, was_rest: bool) -> tuple:
        """Acceleration rejection on the low-passed stages: an acceleration shows as |x1| departing
        from g or x1 turning away from x2 (at once over ``acc_reject_deg``, or over
        ``acc_sustained_deg`` for ``acc_sustained_s``), a knock right after rest as the block's RMS
        |f| departing from g; then x2 holds on the gyro.  Returns the
        tilt-bias measurement r = x̂2 × x̂1 (times k2 in ``_gains``; zero when not usable): the
        second stage lags the first by β⊥/k2 under a residual bias β."""
        s = self.s
        zero = (0.0, 0.0, 0.0)
        if b.reinit_gravity or not b.gravity_init:
            self.acc_trig, self.acc_recovering, self.var_g, self.sus_t = 0.0, False, ACCEPT, 0.0
            self.knock = False
            return zero
        used = self.var_g == ACCEPT
        a0, a1, a2 = b.fast_end
        c0, c1, c2 = b.gravity_end
        n1 = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        n2 = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if n1 == 0.0 or n2 == 0.0:
            return zero
        u1 = (a0 / n1, a1 / n1, a2 / n1)
        u2 = (c0 / n2, c1 / n2, c2 / n2)
        cos12 = u1[0] * u2[0] + u1[1] * u2[1] + u1[2] * u2[2]
        # a sustained acceleration (the second detector): x1 more than acc_sustained_deg from x2 for
        # acc_sustained_s in a row; with k2 > k1 a 0.5 g step peaks at ~7° of x1-x2 angle, under the
        # immediate acc_reject_deg, while the oscillating translations of BROAD's trial 15 stay shorter
        self.sus_t = self.sus_t + T if cos12 < self._cos_sus else 0.0
        # a knock on a body at rest (the third detector): the block's RMS |f| (rotation-invariant)
        # departs from g by over acc_knock_mps2 right after rest; x2 holds until a block is back
        # within acc_knock_end_mps2 (at most acc_knock_hold_s), then x1, which low-passed the knock,
        # restarts from x2 (``close``) instead of handing the knock's residue to the tilt
        dev = abs(math.sqrt(b.force_sq / b.force_n) - s.gravity_mps2) if b.force_n else 0.0
        if was_rest and dev > s.acc_knock_mps2:
            self.knock, self.knock_t = True, 0.0
        elif self.knock:
            self.knock_t += T
        if self.knock and (dev < s.acc_knock_end_mps2 or self.knock_t >= s.acc_knock_hold_s):
            self.knock, self.reset_x1 = False, True
        bad = (cos12 < self._cos_acc or abs(n1 - s.gravity_mps2) > s.acc_norm_tol_mps2
               or self.sus_t >= s.acc_sustained_s or self.knock)
        self.acc_trig = trig = self._trigger(self.acc_trig, bad, T, s.acc_recovery_s)
        if trig >= s.acc_recovery_s:
            self.acc_recovering = True
        elif trig <= 0.0:
            self.acc_recovering = False
        self.var_g = ACCEPT if (self.acc_recovering or not bad) else REJECT
        return zero if (not used or bad) else _cross(u2, u1)

    def _field(self, b: BlockSums, T: float) -> tuple[float, tuple]:
        """Magnetic rejection and reference.  Returns (ψ, up): the heading innovation of the block
        mean field about the up direction (ψ = 0 when not usable), for the heading-bias path."""
        s = self.s
        none = (0.0, (0.0, 0.0, 0.0))
        if b.reinit_field:
            self.mag_trig, self.dist_t, self.mag_recovering, self.var_m = 0.0, 0.0, False, ACCEPT
            self.cand_norm = None
            self.field_disturbed = False
        if not (b.mag_n and b.field_init and b.gravity_init):
            return none
        c0, c1, c2 = b.gravity_end                               # x2 points up (−down)
        gn = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if gn == 0.0:
            return none
        ux, uy, uz = c0 / gn, c1 / gn, c2 / gn
        n = b.mag_n
        mx, my, mz = b.mag_sum[0] / n, b.mag_sum[1] / n, b.mag_sum[2] / n
        norm = math.sqrt(mx * mx + my * my + mz * mz)
        if norm == 0.0:
            return none
        q = ux * mx + uy * my + uz * mz
        dip = math.asin(max(-1.0, min(1.0, -q / norm)))
        if self.ref_norm is None:
            self.ref_norm, self.ref_dip = norm, dip
        xm = b.field_end
        p = ux * xm[0] + uy * xm[1] + uz * xm[2]
        h1 = (xm[0] - p * ux, xm[1] - p * uy, xm[2] - p * uz)
        h2 = (mx - q * ux, my - q * uy, mz - q * uz)
        cr = _cross(h1, h2)
        psi = math.atan2(ux * cr[0] + uy * cr[1] + uz * cr[2], h1[0] * h2[0] + h1[1] * h2[1] + h1[2] * h2[2])
        dist = abs(norm - self.ref_norm) > s.field_norm_tol * self.ref_norm or abs(dip - self.ref_dip) > self._dip_tol
        # a new field: its strength and dip steady (within the tolerances of their own low-pass)
        # for field_relearn_s counted while turning faster than relearn_min_gyro_rad_s (a field
        # that stays the same while the body turns is homogeneous); then it is the reference
        if (self.cand_norm is not None and abs(norm - self.cand_norm) <= s.field_norm_tol * self.cand_norm
                and abs(dip - self.cand_dip) <= self._dip_tol):
            if self.gyro_norm >= s.relearn_min_gyro_rad_s:
                self.dist_t += T
            k = self._k_ref
            self.cand_norm += k * (norm - self.cand_norm)
            self.cand_dip += k * (dip - self.cand_dip)
        else:
            self.cand_norm, self.cand_dip, self.dist_t = norm, dip, 0.0
        if dist and self.dist_t >= s.field_relearn_s:       # a new, lasting field: take it
            self.ref_norm, self.ref_dip, dist = self.cand_norm, self.cand_dip, False
        self.field_disturbed = dist
        bad = dist or abs(psi) > self._psi_max
        self.mag_trig = trig = self._trigger(self.mag_trig, bad, T, s.mag_recovery_s)
        if trig >= s.mag_recovery_s:
            self.mag_recovering = True
        elif trig <= 0.0:
            self.mag_recovering = False
        used = self.var_m == ACCEPT
        if not bad:
            k = self._k_ref
            self.ref_norm += k * (norm - self.ref_norm)
            self.ref_dip += k * (dip - self.ref_dip)
        self.var_m = ACCEPT if (self.mag_recovering or not bad) else REJECT
        return (psi, (ux, uy, uz)) if (used and not bad) else none
