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

``FieldConsistency.update`` (per sample, live) and ``field_consistency`` (batch) run the one compiled
step (estimators.field_consistency_kernel: the state in arrays, the recent-sample windows as ring
buffers of at most estimators.ring_buffers.CAPACITY rows) and give identical numbers.  Units: mG,
rad, rad/s, s, A.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators import field_consistency_kernel as kernel
from estimators.field_consistency_kernel import LEARNING, OFF_ATTITUDE, OFF_LOW_RATE, OFF_NO_FIELD, ON, SETTLING
from estimators.residual_trackers import FieldModelFilter, TiltTracker

__all__ = ["FieldConsistencySettings", "FieldConsistency", "FieldStep", "FieldConsistencyResult",
           "field_consistency", "STATUS", "ON", "LEARNING", "OFF_NO_FIELD", "OFF_LOW_RATE", "OFF_ATTITUDE",
           "SETTLING", "status_text"]

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


class FieldConsistency:
    """Per-sample field-vector consistency test (see module docstring).  Its state is arrays
    (estimators.field_consistency_kernel's layout) and each ``update`` is one call of the compiled
    step that ``field_consistency`` runs over a whole log; the attributes read that state."""

    def __init__(self, settings: FieldConsistencySettings | None = None,
                 earth_field_mG: tuple[float, float, float] | None = None) -> None:
        self.s = settings or FieldConsistencySettings()
        self._cfg = kernel.settings_array(self.s)
        self._state = kernel.new_state(self._cfg)      # (st, P, signal windows ×3, tilt history, ring pointers)
        self._st, self._P = self._state[0], self._state[1]
        self._out = np.zeros(kernel.OUT_SIZE)
        self.set_prior(earth_field_mG)

    def set_prior(self, earth_field_mG) -> None:
        """The WMM prior, known from now on (live: at the first GPS fix); used if the Earth field
        is not yet initialised (at the first tested step)."""
        st = self._st
        known = earth_field_mG is not None
        st[kernel.PRIOR0:kernel.PRIOR2 + 1] = [float(v) for v in earth_field_mG] if known else math.nan
        st[kernel.PRIOR_KNOWN] = 1.0 if known else 0.0

    @property
    def prior(self) -> tuple | None:
        st = self._st
        return tuple(st[kernel.PRIOR0:kernel.PRIOR2 + 1].tolist()) if st[kernel.PRIOR_KNOWN] else None

    @property
    def model(self) -> FieldModelFilter | None:
        """The field model (a view of the state; None before the first tested step of a segment)."""
        st = self._st
        if not st[kernel.MODEL_ON]:
            return None
        return FieldModelFilter.view(st[kernel.TH:kernel.TH + 11], self._P, st[kernel.WALK:kernel.WALK + 11],
                                     st[kernel.MV:kernel.TV])

    @property
    def motor(self) -> FieldModelFilter | None:
        """The one motor-field model (f, its sd, ``significant``): the field model's filter."""
        return self.model

    @property
    def tilt(self) -> TiltTracker:
        """The magnetometer's tilt tracker (a view of the state): ``tilt_rad``."""
        st, ptr = self._st, self._state[6]
        return TiltTracker.view(st[kernel.TV:kernel.ST_SIZE], self._state[5], ptr[kernel.HIST])

    @property
    def h(self) -> list | None:
        """The Earth field (magnetic NED) [mG], None before the first tested step."""
        return self._st[kernel.TH + 2:kernel.TH + 5].tolist() if self._st[kernel.MODEL_ON] else None

    @property
    def b(self) -> list:
        return self._st[kernel.TH + 5:kernel.TH + 8].tolist() if self._st[kernel.MODEL_ON] else [0.0, 0.0, 0.0]

    @property
    def f(self) -> list:
        return self._st[kernel.TH + 8:kernel.TH + 11].tolist() if self._st[kernel.MODEL_ON] else [0.0, 0.0, 0.0]

    def _scalar(self, i: int, none_if_nan: bool = False) -> float | None:
        v = float(self._st[i])
        return None if none_if_nan and math.isnan(v) else v

    psi = property(lambda self: self._scalar(kernel.PSI, True), doc="ψ_f [rad] (None: not started)")
    noise_mG = property(lambda self: self._scalar(kernel.NOISE_MG), doc="σ [mG] (NaN before it is learned)")
    z = property(lambda self: self._scalar(kernel.Z), doc="the CUSUM score")
    S = property(lambda self: self._scalar(kernel.S), doc="the CUSUM [s]")
    learned_s = property(lambda self: self._scalar(kernel.LEARNED_S), doc="data time learned [s]")
    yaw_rate_rad_s = property(lambda self: self._scalar(kernel.YAW_RATE), doc="the last yaw rate [rad/s]")
    settle_until = property(lambda self: self._scalar(kernel.SETTLE_UNTIL), doc="settling until then [s]")
    relearn_until = property(lambda self: self._scalar(kernel.RELEARN_UNTIL), doc="relearning until then [s]")

    def update(self, t_s: float, mag_body_mG, roll_rad: float, pitch_rad: float, attitude_ok: bool,
               gyro_rad_s, motor_signal: float, rate_hz: float, field_ok: bool) -> FieldStep:
        """One IMU step: mag_body_mG the calibrated field held at t (NaN: none), roll and pitch,
        attitude_ok (valid and not steep), gyro bias-corrected [rad/s], motor signal (NaN: unknown),
        the IMU rate and whether the field may be tested at all."""
        out = self._out
        t = float(t_s)
        kernel.step(*self._state, self._cfg, t, float(mag_body_mG[0]), float(mag_body_mG[1]), float(mag_body_mG[2]),
                    float(roll_rad), float(pitch_rad), bool(attitude_ok), float(gyro_rad_s[1]), float(gyro_rad_s[2]),
                    float(motor_signal), float(rate_hz), bool(field_ok), out)
        z, q, r0, r1, r2, status, f0, f1, f2 = out[:kernel.OUT_F_SD].tolist()
        return FieldStep(t, z, q, (r0, r1, r2), int(status), (f0, f1, f2))


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
    """Batch form: ``FieldConsistency.update`` over arrays of length N (the same compiled step,
    identical numbers); the prior ``earth_field_mG`` is known from ``prior_from_s`` on (live: the
    first GPS fix).  The inputs are made contiguous ``chunk`` steps at a time (the memory of a
    chunk, not of the log; any chunk gives the same numbers)."""
    fc = FieldConsistency(settings, None)
    t = np.asarray(t_s, dtype=float)
    n = len(t)
    cols = [np.broadcast_to(np.asarray(a, dtype=float), (n,)) for a in (roll_rad, pitch_rad, motor_signal, rate_hz)]
    ok = np.broadcast_to(np.asarray(attitude_ok, dtype=bool), (n,))
    fok = np.broadcast_to(np.asarray(field_ok, dtype=bool), (n,))
    mag = np.asarray(mag_body_mG, dtype=float).reshape(n, 3)
    gyro = np.asarray(gyro_rad_s, dtype=float).reshape(n, 3)
    prior = np.array([float(v) for v in earth_field_mG]) if earth_field_mG is not None else np.full(3, np.nan)
    z, q, st = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, int)
    res, mot, msd = np.full((n, 3), np.nan), np.zeros((n, 3)), np.full((n, 3), np.inf)
    outs = np.empty((min(chunk, n), kernel.OUT_SIZE))
    for c0 in range(0, n, chunk):
        c1 = min(n, c0 + chunk)
        out = outs[:c1 - c0]
        kernel.run(*fc._state, fc._cfg, *(np.ascontiguousarray(a[c0:c1]) for a in (t, mag, cols[0], cols[1], ok, gyro,
                                                                                     cols[2], cols[3], fok)),
                   prior, float(prior_from_s), out)
        z[c0:c1], q[c0:c1], st[c0:c1] = out[:, kernel.OUT_Z], out[:, kernel.OUT_Q], out[:, kernel.OUT_STATUS]
        res[c0:c1] = out[:, kernel.OUT_R:kernel.OUT_R + 3]
        mot[c0:c1] = out[:, kernel.OUT_F:kernel.OUT_F + 3]
        msd[c0:c1] = out[:, kernel.OUT_F_SD:kernel.OUT_F_SD + 3]
    return FieldConsistencyResult(t, z, q, res, st, mot, fc.noise_mG, tuple(fc.h or (np.nan,) * 3), tuple(fc.b),
                                  tuple(math.degrees(v) for v in fc.tilt.tilt_rad), msd)
