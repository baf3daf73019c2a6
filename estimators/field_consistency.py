"""Field-vector consistency test: the measured body field against the one the attitude predicts.

Model (body FRD, mG), for each IMU step with a calibrated field m:
    m = R(δ) C(φ, θ, ψ_f)ᵀ h + b + f·(x − x₀) + d + noise
* C = C_b^n (estimators.rotations) from roll φ and pitch θ (the caller's best: the autopilot's
  GPS-aided attitude when fresh, else our AHRS, which tilts by degrees in a sustained acceleration)
  and a heading ψ_f that follows the gyro: ψ_f is propagated by the bias-corrected gyro's yaw rate
  ψ̇ = (q sin φ + r cos φ) / cos θ (ZYX Euler kinematics) less the model's yaw-rate bias, and
  corrected by the model's heading-error state ε (below) — slowly, since a heading difference is
  also what a disturbance makes.  The AHRS heading follows the magnetometer (k_m ≈ 0.2/s), so it
  would turn with a disturbance and hide most of it; ψ_f does not.
* R(δ) ≈ I + [δ×]: the magnetometer's tilt δ = (δ_x, δ_y, 0) [rad] against the attitude's body
  axes, a mounting misalignment that an ArduPilot calibration cannot hold (COMPASS_DIA/ODI is
  symmetric: the rotation part of the fitted matrix is dropped, estimators.calibration.
  polar_decomposition).  A tilt turns part of the horizontal field into the body z axis, a
  residual δ × Cᵀh of up to |δ| H (2° at H = 330 mG: 12 mG, 4 σ) that follows the heading
  round, so a body offset cannot take it.  δ is learned from how the residual changes over
  ``tilt_lag_s`` as the predicted field turns in the body (estimators.residual_trackers.
  TiltTracker: least squares forgetting with ``tilt_memory_s``, held at 0 by ``tilt_reg_mG2_s``
  until the nose has turned enough, at most ``tilt_max_deg``), so a body offset does not teach it a
  tilt; only while the nose turns at a flying vehicle's rates (``tilt_min_turn_deg_s`` to
  ``tilt_max_turn_deg_s``: at hand-held spins of 120-200°/s the 2 s change is dominated by the attitude's
  own lag and noise, and real data — BROAD trial 09 — taught it a wrong tilt that then alarmed over
  a third of the trial), from ``tilt_learn_after_s`` on (the offset learned), not while the test
  suspects a disturbance.
  The tilt about z is a heading offset, ψ_f's.  ψ_f is pulled to the heading of the untilted
  field R(δ)ᵀ(m − b − f·Δx).
* h: the Earth field in the magnetic navigation frame (the AHRS heading is magnetic), WMM as the
  prior (H, 0, Z) (without one, the first field); b: a body-fixed residual offset (calibration
  error, motor field at the first signal value); f: the motor field per unit of the motor signal x
  (current [A], or throttle in % without a current sensor), as ArduPilot's compassmot / PX4's
  mag_compensation fit it offline (estimators.motor_field).  ε, the yaw-rate bias, h, b and f are
  one Kalman state (estimators.residual_trackers.FieldModelFilter, the one motor-field model):
  what the flight so far cannot separate (h against b on one heading, f against b on a steady
  current) keeps its variance, so the first turn or current change is learned at once, in turns
  too, and the model's own uncertainty H P Hᵀ enters the test's σ instead of alarming.
* d: the disturbance.  The residual e = m − C ᵀh − b − f(x − x_ref) is low-passed (``smooth_s``),
  r̄; its size in noise units q = |r̄| / σ (σ: RMS of |r̄| over the last quarter of the learning
  time, then following it with ``noise_track_s`` while the test is quiet; at least
  ``noise_floor_mG``) feeds a one-sided CUSUM (Page, Biometrika 41, 1954):
  S ← max(0, S + Δt (q − κ)), alarm at S ≥ ``cusum_threshold_s``; score z = S / threshold (z ≥ 1:
  the test's alarm); S is capped at ``cusum_cap`` thresholds so the score falls within about a
  second of the residual.  A disturbance in any direction counts, long before it turns the heading
  by 5°.  Learning (h, b, f and the pull of ψ_f) pauses while z ≥ ``freeze_z`` (at most
  ``freeze_max_s``) so a slow ramp is not learned away; when the residual of a large alarm falls
  back to the noise apart from a heading error of ψ_f (``_reanchor``) the disturbance has ended:
  the model learns again for ``relearn_s`` and the score restarts from 0.  A relearning (the
  first big turn's, or the one after an alarm) ends at once when the residual reaches
  ``unexplained_q`` σ (``fast_turn_q`` σ while the nose turns over ``first_turn_hold_deg_s``): a
  model error left by a turn is a few σ, a disturbance starting in it is tens (population fast
  ramps 40 and 49), and then the CUSUM summed apart over the fast turn counts (``turn_evidence``:
  a ramp starting in a turn has been over κ for a second before it reaches ``fast_turn_q``,
  population fast 32); σ does not follow such a residual either (it did while
  the CUSUM is held in a fast turn, and a step that spins a compass-following vehicle raised σ
  from 4 to 125 mG, population step 43).

Switch-off (status per step, reason in words): no field (no calibrated field, field test off),
IMU rate below ``min_rate_hz`` (telemetry), attitude not valid or too steep, learning, settling
after an IMU gap over ``max_gap_s``.  A gap over ``segment_gap_s`` or time going backwards (a
replay seek, a reset) starts again from scratch.  A GPS outage changes nothing here.

``FieldConsistency.update`` (per sample, live) and ``field_consistency`` (batch: the same steps in
a loop, plain floats) give identical numbers.  Units: mG, rad, rad/s, s, A.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from estimators.residual_trackers import FieldModelFilter, TiltTracker, quad_inv3
from estimators.rotations import dcm_body_to_ned_float

__all__ = ["FieldConsistencySettings", "FieldConsistency", "FieldStep", "FieldConsistencyResult",
           "field_consistency", "STATUS", "ON", "LEARNING", "OFF_NO_FIELD", "OFF_LOW_RATE", "OFF_ATTITUDE",
           "SETTLING", "status_text"]

ON, LEARNING, OFF_NO_FIELD, OFF_LOW_RATE, OFF_ATTITUDE, SETTLING = range(6)
STATUS = ("on", "learning", "off: no calibrated field", "off: IMU rate below the minimum",
          "off: attitude not valid or too steep", "settling after a telemetry gap")


@dataclass(frozen=True)
class FieldConsistencySettings:
    """One default for every vehicle; units in the names."""
    learn_s: float = 20.0               # data time before the test is armed (field, offset, noise learned)
    model_field_sd_mG: float = 5.0      # the model's prior sd: Earth field h about the WMM ...
    model_offset_sd_mG: float = 50.0    # ... body offset b ...
    model_motor_sd: float = 3.0         # ... motor field f [mG per A, or per %]
    model_field_tau_s: float = 2000.0   # once known, h follows with this time constant ...
    model_offset_tau_s: float = 20.0    # ... b ...
    model_motor_tau_s: float = 300.0    # ... f
    model_corr_s: float = 1.0           # the residual's noise is correlated over this long
    model_clip_sigma: float = 3.0       # the model learns from innovations clipped at this many σ (Huber)
    model_max_turn_deg_s: float = 20.0  # ... and not in turns faster than this (ψ_f lags the gyro's scale)
    signal_lag_s: float = 1.5           # the motor signal may lag the field this long (sensor lag, 1 Hz telemetry)
    relearn_sd_mG: float = 10.0         # after a disturbance, h and b are this much less known
    turn_deg: float = 45.0              # the first turn this far from the learning heading ...
    turn_learn_s: float = 10.0
    first_turn_hold_deg_s: float = 20.0  # the CUSUM holds in turns faster than this ...
    post_turn_s: float = 1.0            # ... and this long after them, then ψ_f drops a heading error
    tilt_learn_after_s: float = 5.0     # the tilt δ learns from then on (the offset has settled) ...
    tilt_min_turn_deg_s: float = 3.0    # ... while the nose turns at least this fast ...
    tilt_max_turn_deg_s: float = 90.0   # ... and no faster than a vehicle's turns (the dance: 45°/s) ...
    tilt_lag_s: float = 2.0             # ... from the residual's change over this lag ...
    tilt_memory_s: float = 300.0        # ... least squares forgetting with this time constant ...
    tilt_reg_mG2_s: float = 1.0e4       # ... held at 0 with this weight [mG² s] until the nose turns ...
    tilt_max_deg: float = 5.0           # ... at most this (per axis)
    model_start_s: float = 5.0          # the model (and ψ_f) start after the attitude has been valid this long
    model_heading_sd_deg: float = 3.0   # ψ_f's error at its start (the first field's heading) ...
    model_yaw_bias_sd_deg_s: float = 0.1    # ... growing by the yaw-rate bias left in the gyro (learned) ...
    model_gyro_scale: float = 0.02      # ... and by this fraction of the yaw rate in turns
    freeze_max_s: float = 120.0         # learning resumes after this long frozen (a lasting change is learned)
    reanchor_peak: float = 8.0          # after an alarm whose residual reached this many σ, ...
    reanchor_margin: float = 2.5        # ... the residual below (κ + this) σ ...
    reanchor_heading_deg: float = 10.0  # (a heading error of ψ_f up to this much is not counted) ...
    reanchor_s: float = 1.5             # ... for this long ends the episode: ...
    relearn_s: float = 5.0              # ... the model learns again this long (as in a turn)
    unexplained_q: float = 8.0          # a residual this many σ is no turn's model error: it ends a relearning
                                        # (the first turn's or after an alarm), is not held in a fast turn and
                                        # σ does not follow it (clean population flights: ≤ 4.5σ in a
                                        # relearning, ≤ 5.4σ in a held turn; a 250 mG ramp: 40σ)
    fast_turn_q: float = 5.0            # in a fast turn (over ``first_turn_hold_deg_s``; held: and ``post_turn_s``
                                        # after it) a residual this many σ is no turn's model error either: the
                                        # CUSUM is not held and a relearning ends (clean population flights, seed 0,
                                        # the tilt brought forward from agreement: ≤ 3.76σ in a held turn, ≤ 3.25σ
                                        # in a relearning in a fast turn; with the tilt of before, 6σ). ArduPilot
                                        # SITL's turns left over 5σ (2 of 15 clean flights alarmed) until the
                                        # 10 Hz compass reading was turned to each step (jobs/field_forward.py)
    turn_evidence: bool = True          # ... and then the CUSUM summed over that turn counts (held apart before)
    smooth_s: float = 0.5               # low-pass of the residual vector
    noise_floor_mG: float = 4.0         # σ is at least this
    noise_track_s: float = 60.0         # σ² follows the residual's mean square this slowly after learning
    cusum_drift: float = 3.0            # κ: residual below κσ never accumulates
    cusum_threshold_s: float = 1.0      # alarm when S (σ-units × s above κ) reaches this
    cusum_cap: float = 3.0              # S is capped at this many thresholds (it ends soon after the residual)
    freeze_z: float = 0.2               # learning pauses at this score
    min_rate_hz: float = 10.0           # slower IMU data (telemetry): off
    max_gap_s: float = 0.5              # a longer IMU step: heading re-started, settle before testing
    settle_s: float = 2.0
    segment_gap_s: float = 4.5          # a longer gap (or time going back) starts from scratch


def status_text(code: int) -> str:
    return STATUS[int(code)] if 0 <= int(code) < len(STATUS) else "unknown"


@dataclass
class FieldStep:
    t_s: float
    z: float                            # CUSUM / threshold (NaN when off or settling; 0 while learning)
    q: float                            # |r̄| / σ (NaN when off)
    residual_mG: tuple                  # r̄, body frame (NaN when off)
    status: int
    motor_mG_per_unit: tuple            # f


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _noise_cov(hph: list, lag_cov: list | None, sigma_mG: float) -> list:
    """Σ = σ²/3 I + H P Hᵀ (+ the signal's lag term) [mG², nine floats row by row]."""
    cov = [a + b for a, b in zip(hph, lag_cov)] if lag_cov is not None else list(hph)
    v = sigma_mG * sigma_mG / 3.0
    cov[0] += v
    cov[4] += v
    cov[8] += v
    return cov


class FieldConsistency:
    """Per-sample field-vector consistency test (see module docstring)."""

    def __init__(self, settings: FieldConsistencySettings | None = None,
                 earth_field_mG: tuple[float, float, float] | None = None) -> None:
        self.s = s = settings or FieldConsistencySettings()
        self.prior = tuple(float(v) for v in earth_field_mG) if earth_field_mG is not None else None
        # the settings' angles in radians, once (every step compares with them)
        self._turn_rad = math.radians(s.turn_deg)
        self._tilt_turn_rad_s = (math.radians(s.tilt_min_turn_deg_s), math.radians(s.tilt_max_turn_deg_s))
        self._model_max_turn_rad_s = math.radians(s.model_max_turn_deg_s)
        self._hold_turn_rad_s = math.radians(s.first_turn_hold_deg_s)
        self._reanchor_heading_rad = math.radians(s.reanchor_heading_deg)
        self._reset()

    def set_prior(self, earth_field_mG) -> None:
        """The WMM prior, known from now on (live: at the first GPS fix); used if the Earth field
        is not yet initialised (at the first tested step)."""
        self.prior = tuple(float(v) for v in earth_field_mG) if earth_field_mG is not None else None

    def _reset(self) -> None:
        self.model: FieldModelFilter | None = None   # made with the Earth field's first value
        self.tilt = TiltTracker(self.s.tilt_lag_s, self.s.tilt_memory_s, self.s.tilt_reg_mG2_s,
                                math.radians(self.s.tilt_max_deg))
        self._recent_x: deque = deque()              # times of the signal's values over the last ``signal_lag_s``
        self._recent_hi: deque = deque()             # (t, signal): the window's maximum first, then later
        self._recent_lo: deque = deque()             # ... and its minimum (each value falls out when passed)
        self._att_since: float | None = None         # the attitude valid since then
        self.psi_learned: float | None = None      # heading at the end of learning
        self.turn_until: float | None = None        # the first turn is learned again until then
        self.learned_s = 0.0
        self.yaw_rate_rad_s = 0.0
        self._dx = 0.0
        self._frozen_since: float | None = None
        self._noise_sum = 0.0
        self._noise_n = 0
        self._noise_ms = 0.0
        self.noise_mG = float("nan")
        self._t: float | None = None
        self._restart(-math.inf)

    def _restart(self, settle_until: float) -> None:
        self.psi: float | None = None
        self.r = None
        self.S = 0.0
        self.z = 0.0
        self._frozen_since = None
        self._peak_q, self._low_since = 0.0, None
        self._q = 0.0                                # the last step's q
        self._S_turn = 0.0                           # the CUSUM over the current fast turn, held apart
        self.relearn_until = -math.inf
        self._turn_hold_until = -math.inf
        self.settle_until = settle_until
        self._recent_x.clear()
        self._recent_hi.clear()
        self._recent_lo.clear()
        self.tilt.clear_history()
        if getattr(self, "model", None) is not None:     # ψ_f starts again at the magnetic heading
            self.model.restart_heading(math.radians(self.s.model_heading_sd_deg))

    @property
    def h(self) -> list | None:
        """The Earth field (magnetic NED) [mG], None before the first tested step."""
        return None if self.model is None else self.model.h

    @property
    def b(self) -> list:
        return [0.0, 0.0, 0.0] if self.model is None else self.model.b

    @property
    def f(self) -> list:
        return [0.0, 0.0, 0.0] if self.model is None else self.model.f

    @property
    def motor(self) -> FieldModelFilter | None:
        """The one motor-field model (f, its sd, ``significant``): the field model's filter."""
        return self.model

    def _signal(self, x: float) -> float:
        return 0.0 if self.model is None else self.model.signal(x)

    # ------------------------------------------------------------------ one step
    def update(self, t_s: float, mag_body_mG, roll_rad: float, pitch_rad: float, attitude_ok: bool,
               gyro_rad_s, motor_signal: float, rate_hz: float, field_ok: bool) -> FieldStep:
        """One IMU step: mag_body_mG the calibrated field held at t (NaN: none), roll and pitch,
        attitude_ok (valid and not steep), gyro bias-corrected [rad/s], motor signal (NaN: unknown),
        the IMU rate and whether the field may be tested at all."""
        s = self.s
        t = float(t_s)
        if self._t is not None and (t < self._t or t - self._t > s.segment_gap_s):
            self._reset()
        dt = 0.0 if self._t is None else t - self._t
        self._t = t
        if dt > s.max_gap_s:
            self._restart(t + s.settle_s)
        mx, my, mz = mag_body_mG
        mx, my, mz = float(mx), float(my), float(mz)
        have_field = field_ok and math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz)
        if attitude_ok and have_field:
            if self._att_since is None:
                self._att_since = t
            dx = self._signal(float(motor_signal))
            th = self.model.th if self.model is not None else (0.0,) * 11
            b, f = th[5:8], th[8:11]
            m_earth = self._untilt((mx - b[0] - f[0] * dx, my - b[1] - f[1] * dx, mz - b[2] - f[2] * dx))
            self._track_heading(dt, roll_rad, pitch_rad, m_earth, gyro_rad_s)
        else:
            self.psi = None
            self._att_since = None
        if not have_field:
            return self._off(t, OFF_NO_FIELD)
        if not rate_hz >= s.min_rate_hz:
            return self._off(t, OFF_LOW_RATE)
        if self.psi is None:
            return self._off(t, SETTLING if t < self.settle_until else OFF_ATTITUDE)
        c = dcm_body_to_ned_float(roll_rad, pitch_rad, self.psi)
        if self.model is None:
            if t - self._att_since < s.model_start_s:
                # the attitude settles first: ψ_f starts from the field's heading on a settled tilt
                # (a first AHRS tilt 19° off made ψ_f 105° off at 75° inclination, far outside
                # what the model's linear ε can take back)
                self.psi = None
                return self._off(t, SETTLING)
            if self.prior is not None and all(map(math.isfinite, self.prior)):
                h0 = list(self.prior)
            else:                                            # no prior: the first field is the Earth field
                h0 = [c[0] * mx + c[1] * my + c[2] * mz, c[3] * mx + c[4] * my + c[5] * mz,
                      c[6] * mx + c[7] * my + c[8] * mz]
            s_ = self.s
            self.model = FieldModelFilter(h0, s_.model_field_sd_mG, s_.model_offset_sd_mG, s_.model_motor_sd,
                                          s_.model_field_tau_s, s_.model_offset_tau_s, s_.model_motor_tau_s,
                                          s_.model_corr_s, math.radians(s_.model_heading_sd_deg),
                                          math.radians(s_.model_yaw_bias_sd_deg_s), 1.0e-4, s_.model_gyro_scale)
        return self._test(t, dt, c, (mx, my, mz), motor_signal)

    def _untilt(self, v: tuple) -> tuple:
        """R(δ)ᵀ v ≈ v − δ × v (δ_z = 0): a body vector in the attitude's axes."""
        tx, ty = self.tilt.tilt_rad
        return (v[0] - ty * v[2], v[1] + tx * v[2], v[2] - tx * v[1] + ty * v[0])

    def _tilted(self, p: list) -> list:
        """R(δ) p ≈ p + δ × p (δ_z = 0): the predicted field as the tilted magnetometer sees it."""
        tx, ty = self.tilt.tilt_rad
        return [p[0] + ty * p[2], p[1] - tx * p[2], p[2] + tx * p[1] - ty * p[0]]

    def _track_heading(self, dt: float, roll: float, pitch: float, m: tuple, gyro) -> None:
        """ψ_f: started at the tilt-compensated magnetic heading (seed 000 eqs. 11-13) of the Earth
        part of the field (m − b − f·Δx), then the bias-corrected gyro's yaw rate less the model's
        β; its error ε is a state of the field model (``_test`` folds the model's ε into it), so
        after learning the field pulls it only as far as the model can tell a heading error from a
        body offset."""
        if self.psi is None:
            if self.model is not None and self._t < self.settle_until:
                # after a gap the field held may be from before it, the tilt is not: at 72°
                # inclination a 6° pitch change made ψ_f 26° off (population clean flight 150);
                # ψ_f starts again once the field has come back (the end of settling)
                return
            c = dcm_body_to_ned_float(roll, pitch, 0.0)     # tilt only: the field levelled
            self.psi = float(-math.atan2(c[3] * m[0] + c[4] * m[1] + c[5] * m[2],
                                         c[0] * m[0] + c[1] * m[1] + c[2] * m[2]))
            if self.model is not None:
                # a restart after a gap: the heading at which the model's own Earth field h fits
                # (the levelled field's direction turned onto h's: ψ = atan2(h_E, h_N) − atan2(v_E, v_N)),
                # so a heading error the model had taken into h_E carries over the gap and, on the
                # heading flown before it, ψ_f goes on where it was
                h = self.model.h
                self.psi = _wrap(self.psi + math.atan2(h[1], h[0]))
            return
        q, r = float(gyro[1]), float(gyro[2])
        cos_p = math.cos(pitch)
        rate = (q * math.sin(roll) + r * math.cos(roll)) / cos_p if abs(cos_p) > 1e-3 else 0.0
        if not math.isfinite(rate):
            rate = 0.0
        self.yaw_rate_rad_s = rate
        beta = self.model.yaw_bias_rad_s if self.model is not None else 0.0
        self.psi = _wrap(self.psi + (rate - beta) * dt)

    def _learning_allowed(self) -> bool:
        """Learning pauses while the score is at ``freeze_z`` or more, for ``freeze_max_s`` at most."""
        if self.z < self.s.freeze_z or self._frozen_since is None:
            return True
        return self._t - self._frozen_since > self.s.freeze_max_s

    def _off(self, t: float, status: int) -> FieldStep:
        self.r = None
        self.S = self.z = 0.0
        self._frozen_since = None
        nan = float("nan")
        return FieldStep(t, nan, nan, (nan, nan, nan), status, tuple(self.f))

    def _relearning_turn(self, t: float, learning: bool) -> bool:
        """True while the first big turn after learning is being learned again."""
        if learning or self.psi is None:
            return False
        if self.psi_learned is None:
            self.psi_learned = self.psi
        if (self.turn_until is None and self.z < self.s.freeze_z
                and abs(_wrap(self.psi - self.psi_learned)) > self._turn_rad):
            self.turn_until = t + self.s.turn_learn_s
        return self.turn_until is not None and t < self.turn_until

    def _tilt_learns(self, allowed: bool) -> bool:
        """The tilt learns while the nose turns at a vehicle's rates (``tilt_min_turn_deg_s`` to
        ``tilt_max_turn_deg_s``): the horizontal field turning through the body is its signature; a
        roll or pitch wobble alone would correlate it with whatever else changes (the current, the
        offset settling), and hand-held spins teach it the attitude's lag instead."""
        s = self.s
        return (allowed and self.learned_s >= s.tilt_learn_after_s
                and self._tilt_turn_rad_s[0] <= abs(self.yaw_rate_rad_s) <= self._tilt_turn_rad_s[1])

    def _clip_mG(self) -> float:
        """The tilt learns from changes clipped at ``model_clip_sigma`` σ (Huber)."""
        s = self.s
        return s.model_clip_sigma * (self.noise_mG if math.isfinite(self.noise_mG) else s.noise_floor_mG)

    def _signal_spread(self, t: float, x: float) -> float:
        """Half the range of the motor signal over the last ``signal_lag_s`` [A or %]: how far the
        signal as received (lagging, held between 1-2 Hz samples) may be from the one the field
        follows now; f·that is part of the model's uncertainty."""
        q, hi, lo = self._recent_x, self._recent_hi, self._recent_lo
        if math.isfinite(x):        # the window's maximum and minimum as monotone queues (time order)
            q.append(t)
            while hi and hi[-1][1] <= x:
                hi.pop()
            hi.append((t, x))
            while lo and lo[-1][1] >= x:
                lo.pop()
            lo.append((t, x))
        t0 = t - self.s.signal_lag_s
        while q and q[0] < t0:
            q.popleft()
        while hi and hi[0][0] < t0:
            hi.popleft()
        while lo and lo[0][0] < t0:
            lo.popleft()
        if len(q) < 2:
            return 0.0
        return 0.5 * (hi[0][1] - lo[0][1])

    def _test(self, t: float, dt: float, c: tuple, m: tuple, x: float) -> FieldStep:
        s = self.s
        learning = self.learned_s < s.learn_s
        self.learned_s += min(dt, s.max_gap_s)
        model = self.model
        xt = self._dx = model.signal(float(x))
        spread = self._signal_spread(t, float(x))
        th = model.th
        h0, h1, h2 = th[2], th[3], th[4]
        c0, c1, c2, c3, c4, c5, c6, c7, c8 = c
        p = [c0 * h0 + c3 * h1 + c6 * h2, c1 * h0 + c4 * h1 + c7 * h2, c2 * h0 + c5 * h1 + c8 * h2]
        tx, ty = self.tilt.tilt_rad
        cbt = ((c0 + ty * c2, c3 + ty * c5, c6 + ty * c8),                 # R(δ)Cᵀ, R(δ) ≈ I + [δ×]
               (c1 - tx * c2, c4 - tx * c5, c7 - tx * c8),
               (c2 - ty * c0 + tx * c1, c5 - ty * c3 + tx * c4, c8 - ty * c6 + tx * c7))
        f0, f1, f2 = th[8], th[9], th[10]
        if spread > 0.0:                # the signal's timing: f·(x_true − x_seen), f fᵀ spread² [mG², row by row]
            s2 = spread * spread
            lag_cov = [s2 * (f0 * f0), s2 * (f0 * f1), s2 * (f0 * f2), s2 * (f1 * f0), s2 * (f1 * f1),
                       s2 * (f1 * f2), s2 * (f2 * f0), s2 * (f2 * f1), s2 * (f2 * f2)]
        else:
            lag_cov = None
        turn = self._relearning_turn(t, learning) or t < self.relearn_until
        allowed = self._learning_allowed()
        sigma = self.noise_mG if math.isfinite(self.noise_mG) else s.noise_floor_mG
        learn = (turn or allowed) and abs(self.yaw_rate_rad_s) <= self._model_max_turn_rad_s
        # the model's random walks, its prediction and (learning) its update; HPHt: the model's
        # uncertainty on this step [mG²]
        pred, HPHt = model.step(dt, sigma, self.yaw_rate_rad_s, cbt, xt, m, learn, s.model_clip_sigma, lag_cov)
        e = [m[0] - pred[0], m[1] - pred[1], m[2] - pred[2]]
        if learn:
            self.psi = _wrap(self.psi - model.take_heading())
        th = model.th
        self.tilt.update(t, p, [m[0] - p[0] - th[5] - th[8] * xt, m[1] - p[1] - th[6] - th[9] * xt,
                                m[2] - p[2] - th[7] - th[10] * xt], dt,
                         self._tilt_learns(turn or allowed), self._clip_mG())
        a = 1.0 - math.exp(-dt / s.smooth_s) if self.r is not None else 1.0
        r = self.r = e if self.r is None else [self.r[k] + a * (e[k] - self.r[k]) for k in range(3)]
        size = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        if learning and self.learned_s >= 0.75 * s.learn_s:
            self._noise_sum += size * size
            self._noise_n += 1
            self._noise_ms = self._noise_sum / self._noise_n
        elif not (learning or turn) and self._noise_n and self.z < s.freeze_z and self._q < s.unexplained_q:
            # follows the noise, slowly (not a residual no turn explains: held in a fast turn, it
            # raised σ from 4 to 125 mG under a 276 mG step, population step 43), and only the part
            # of |r̄|² the model's own uncertainty H P Hᵀ does not explain: σ² follows
            # min(|r̄|², σ² r̄ᵀ Σ⁻¹ r̄ / 3) with Σ = σ²/3 I + H P Hᵀ (+ lag), = |r̄|² when P = 0.
            # In a fast turn ψ_f's uncertainty (the gyro's scale) is in Σ; counted in σ too, a
            # payload switched on in a 40°/s turn raised σ 7 -> 21 mG and was never scored
            # (population payload 9), a fast ramp starting in one 7 -> 85 mG (fast 38).
            self._noise_ms += (1.0 - math.exp(-dt / s.noise_track_s)) * (
                self._noise_sample(r, size, HPHt, lag_cov) - self._noise_ms)
        if self._noise_n:
            self.noise_mG = max(s.noise_floor_mG, math.sqrt(self._noise_ms))
        sigma = self.noise_mG if math.isfinite(self.noise_mG) else s.noise_floor_mG
        # q: r̄ against the noise and the model's own uncertainty, Σ = σ²/3 I + H P Hᵀ + lag term
        # (q = |r̄|/σ when the model is known exactly)
        q = self._q = math.sqrt(max(quad_inv3(r, _noise_cov(HPHt, lag_cov, sigma)) / 3.0, 0.0))
        fast = abs(self.yaw_rate_rad_s) > self._hold_turn_rad_s
        q_other, eps = self._non_heading_q(c, r, sigma)
        if fast and not learning and t >= self.settle_until:
            # a fast turn's evidence is summed apart (held, or relearning), less what a heading error
            # of ψ_f explains: it counts once the residual shows in the turn that it is no turn's
            # error (q ≥ ``fast_turn_q``), else it is dropped.  Not in the second after the turn:
            # there a gyro reading 4 % high leaves 5.0σ after 180° (tests/test_field_consistency.py)
            qt = min(q, q_other)
            self._S_turn = min(max(0.0, self._S_turn + dt * (qt - s.cusum_drift)), s.cusum_cap * s.cusum_threshold_s)
        else:
            self._S_turn = 0.0
        if turn and not learning and q >= (s.fast_turn_q if fast else s.unexplained_q):
            # a residual no turn explains: the relearning ends and the test judges it
            turn = False
            self.turn_until = self.relearn_until = t
        if learning or turn or t < self.settle_until:
            # learning or relearning a turn, the test is on but blind: score 0, not NaN (so a
            # heading difference alone does not alarm while the field-vector test cannot judge)
            self.S = self.z = 0.0
            z = 0.0 if (turn or learning) else float("nan")
            return FieldStep(t, z, q, tuple(r), LEARNING if (learning or turn) else SETTLING, tuple(model.th[8:11]))
        first_turn = self._fast_turn(t, q, q_other, eps)
        if not first_turn:
            self.S = min(max(0.0, self.S + dt * (q - s.cusum_drift)), s.cusum_cap * s.cusum_threshold_s)
            if s.turn_evidence and fast and q >= s.fast_turn_q:   # released by the residual in the turn
                self.S = max(self.S, self._S_turn)
        self.z = self.S / s.cusum_threshold_s
        frozen = self.z >= s.freeze_z
        self._frozen_since = (self._frozen_since if self._frozen_since is not None else t) if frozen else None
        self._reanchor(t, q_other, frozen)
        return FieldStep(t, self.z, q, tuple(r), ON, tuple(model.th[8:11]))

    def _noise_sample(self, r: list, size_mG: float, HPHt: list, lag_cov: list | None) -> float:
        """The residual's square σ² follows [mG²]: |r̄|², less what the model's uncertainty
        explains, min(|r̄|², σ² · r̄ᵀ Σ⁻¹ r̄ / 3) with Σ = σ²/3 I + H P Hᵀ (+ the signal's lag term)
        and σ the current noise (so with P = 0 it is |r̄|², the mean square of before)."""
        sigma = self.noise_mG if math.isfinite(self.noise_mG) else self.s.noise_floor_mG
        return min(size_mG * size_mG, max(quad_inv3(r, _noise_cov(HPHt, lag_cov, sigma)) / 3.0, 0.0) * sigma * sigma)

    def _fast_turn(self, t: float, q: float, q_other: float, eps: float) -> bool:
        """True while the CUSUM holds for a fast turn (over ``first_turn_hold_deg_s``) and
        ``post_turn_s`` after it, unless the residual is ``fast_turn_q`` σ or more (clean
        population turns leave at most 3.76σ since the autopilot's tilt is brought forward, 6σ
        before; a step that spins a compass-following vehicle at 40°/s for its whole 13 s leaves
        10-13σ, population step 8; a slow ramp starting 1.5 s before a turn 4.4-5.4σ, population
        slow 37).  A fast turn leaves ψ_f a few
        degrees off (the gyro's scale and timing over 100°+): when the hold ends, a residual that
        is a heading error ε alone (the rest under (κ + ``reanchor_margin``) σ, |ε| ≤
        ``reanchor_heading_deg``) is taken out of ψ_f."""
        s = self.s
        if abs(self.yaw_rate_rad_s) > self._hold_turn_rad_s:
            self._turn_hold_until = t + s.post_turn_s
            return q < s.fast_turn_q
        if t < self._turn_hold_until:
            return q < s.fast_turn_q
        if self._turn_hold_until > -math.inf:
            self._turn_hold_until = -math.inf
            if q_other < s.cusum_drift + s.reanchor_margin and math.isfinite(eps):
                self.psi = _wrap(self.psi - eps)
        return False

    def _non_heading_q(self, c: tuple, r: list, sigma: float) -> tuple[float, float]:
        """(|r̄| without the part a heading error ε of ψ_f explains, in σ; ε [rad]) (∞ and NaN
        beyond ``reanchor_heading_deg``): with ψ_f = ψ + ε the predicted field is turned about the
        vertical, a residual ε (−h_E, h_N, 0) in the navigation frame."""
        h = self.h
        rn = [c[0] * r[0] + c[1] * r[1] + c[2] * r[2], c[3] * r[0] + c[4] * r[1] + c[5] * r[2],
              c[6] * r[0] + c[7] * r[1] + c[8] * r[2]]
        hh = math.hypot(h[0], h[1])
        if not hh > 0:
            return math.sqrt(rn[0] ** 2 + rn[1] ** 2 + rn[2] ** 2) / sigma, float("nan")
        along = (-h[1] * rn[0] + h[0] * rn[1]) / hh
        if abs(along) > self._reanchor_heading_rad * hh:
            return math.inf, float("nan")
        return math.sqrt(max(rn[0] ** 2 + rn[1] ** 2 + rn[2] ** 2 - along * along, 0.0)) / sigma, along / hh

    def _reanchor(self, t: float, q: float, frozen: bool) -> None:
        """The end of a disturbance: after an alarm whose residual reached ``reanchor_peak`` σ, the
        residual back below (κ + ``reanchor_margin``) σ for ``reanchor_s``, apart from a heading
        error (ψ_f drifted on the gyro alone meanwhile), is what is left of the model: learn again
        for ``relearn_s`` as in a turn, ψ_f as fast as while learning (score 0), so the alarm ends
        with the disturbance instead of when the drift is learned."""
        s = self.s
        if not frozen:
            self._peak_q, self._low_since = 0.0, None
            return
        self._peak_q = max(self._peak_q, q) if self.z >= 1.0 else self._peak_q
        low = q < s.cusum_drift + s.reanchor_margin
        self._low_since = (self._low_since if self._low_since is not None else t) if low else None
        if self._peak_q >= s.reanchor_peak and low and t - self._low_since >= s.reanchor_s:
            self.relearn_until = t + s.relearn_s
            self.model.inflate(s.relearn_sd_mG, s.relearn_sd_mG)
            self.S = self.z = 0.0
            self._frozen_since, self._peak_q, self._low_since = None, 0.0, None


@dataclass
class FieldConsistencyResult:
    """Per-step arrays (length N) of ``field_consistency``."""
    t_s: np.ndarray
    z: np.ndarray                  # CUSUM score (≥ 1: alarm); NaN unless on
    q: np.ndarray                  # |r̄| / σ
    residual_mG: np.ndarray        # (N, 3) r̄, body frame
    status: np.ndarray             # (N,) int, STATUS codes
    motor_mG_per_unit: np.ndarray  # (N, 3) f as learned up to each step (its trend)
    noise_mG: float
    earth_field_mG: tuple          # h at the end (magnetic NED)
    offset_mG: tuple               # b at the end (body)
    tilt_deg: tuple = (float("nan"), float("nan"))   # δ_x, δ_y at the end: the magnetometer's tilt
    motor_sd_mG_per_unit: np.ndarray | None = None    # (N, 3) f's standard error at each step (inf: unknown)


def field_consistency(t_s, mag_body_mG, roll_rad, pitch_rad, attitude_ok, gyro_rad_s, motor_signal,
                      rate_hz, field_ok, settings: FieldConsistencySettings | None = None,
                      earth_field_mG=None, prior_from_s: float = -math.inf,
                      chunk: int = 8192) -> FieldConsistencyResult:
    """Batch form: ``FieldConsistency.update`` over arrays of length N (identical numbers); the
    prior ``earth_field_mG`` is known from ``prior_from_s`` on (live: the first GPS fix).  The
    arrays are turned into plain floats ``chunk`` steps at a time (the memory of a chunk, not of
    the log; any chunk gives the same numbers)."""
    fc = FieldConsistency(settings, None)
    t = np.asarray(t_s, dtype=float)
    n = len(t)
    cols = [np.broadcast_to(np.asarray(a, dtype=float), (n,)) for a in (roll_rad, pitch_rad, motor_signal, rate_hz)]
    ok = np.broadcast_to(np.asarray(attitude_ok, dtype=bool), (n,))
    fok = np.broadcast_to(np.asarray(field_ok, dtype=bool), (n,))
    mag = np.asarray(mag_body_mG, dtype=float).reshape(n, 3)
    gyro = np.asarray(gyro_rad_s, dtype=float).reshape(n, 3)
    z, q, st = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, int)
    res, mot, msd = np.full((n, 3), np.nan), np.zeros((n, 3)), np.full((n, 3), np.inf)
    for c0 in range(0, n, chunk):      # plain floats a chunk at a time: memory bounded by the chunk
        c1 = min(n, c0 + chunk)
        tl, ml, gl = t[c0:c1].tolist(), mag[c0:c1].tolist(), gyro[c0:c1].tolist()
        rl, pl, xl, hl = (c[c0:c1].tolist() for c in cols)
        okl, fokl = ok[c0:c1].tolist(), fok[c0:c1].tolist()
        zs, qs, sts, rs, ms, sds = [], [], [], [], [], []
        for i in range(c1 - c0):
            if fc.prior is None and earth_field_mG is not None and tl[i] >= prior_from_s:
                fc.set_prior(earth_field_mG)
            step = fc.update(tl[i], ml[i], rl[i], pl[i], okl[i], gl[i], xl[i], hl[i], fokl[i])
            zs.append(step.z)
            qs.append(step.q)
            sts.append(step.status)
            rs.append(step.residual_mG)
            ms.append(step.motor_mG_per_unit)
            sds.append(tuple(fc.model.sd) if fc.model is not None else (math.inf,) * 3)
        z[c0:c1], q[c0:c1], st[c0:c1] = zs, qs, sts
        res[c0:c1], mot[c0:c1], msd[c0:c1] = rs, ms, sds
    return FieldConsistencyResult(t, z, q, res, st, mot, fc.noise_mG, tuple(fc.h or (np.nan,) * 3), tuple(fc.b),
                                  tuple(math.degrees(v) for v in fc.tilt.tilt_rad), msd)
