"""Loosely coupled INS/GPS error-state Kalman filter with field-vector feedback in GPS outage (seed 003).

Seed 003 sec. 1.1 (indirect, error-model-based loose coupling): error state
    x = [ψ (attitude error, nav frame), δv^n, δp^n (local NED metres), δb_g, δb_a, δH^n, δd^b, δc]
    (24 states; d^b, a body-fixed field, only when ``body_field_sigma_mG`` > 0; c, the motor
    field per ampere, only when the battery current is given)
    ψ'  = −C_b^n δb_g                        (eq. 1 without Earth/transport rate: small UAV, MEMS)
    δv' = −[f^n ×] ψ − C_b^n δb_a            (eq. 2, for our convention C = (I + [ψ×]) Ĉ)
    δp' = δv                                  (eq. 3, local NED metres instead of lat/lon/height)
    δH^n' = 0 (+ a small random walk)         the Earth field in NED
GPS position and velocity (local NED) are the measurements; while GPS is good the magnetometer is
one too (z = H_m^b − Ĉᵀ Ĥ^n = Ĉᵀ[Ĥ^n×] ψ + Ĉᵀ δH^n), so the filter estimates the Earth field
vector in NED together with the attitude (seed 003: "with GPS, integrated navigation estimates
the attitude and the geomagnetic vector").  The field prior comes from the initial alignment
(tilt from the accelerometer, heading = magnetic heading + WMM declination).

When GPS is lost (no fix for ``gps_timeout_s``) the estimated field becomes the set-point of a
feedback loop (seed 003 sec. 2): the predicted body field Ĥ^b = Ĉ_n^b Ĥ^n is compared with the
measured H_m^b and the error
    e = (H_m^b / |H_m^b|) × (Ĥ^b / |Ĥ^b|)
corrects the gyro rates with a proportional–integral law, ω = ω_m − b̂_g + K_P e + K_I ∫e dt,
which holds the attitude instead of letting it drift open loop.  When GPS returns, the integral
(the gyro-bias change learnt in the outage) is moved into b̂_g and the Kalman filter takes over.

The field alone does not observe rotations about the field line (a gyro-bias change along it
drifts freely), so the fixed-gain PI law (``feedback_law="pi"``, seed 003 as published) cannot
stop that drift.  ``feedback_law="kalman"`` (default) feeds back the same field-vector error
through the Kalman gain instead: in the outage the filter keeps its magnetometer update against
Ĥ^n, lets the gyro bias walk faster (``outage_gyro_bias_walk``) and corrects the gyro rates with
the estimated bias, ω = ω_m − b̂_g; ψ' = −C_b^n δb_g couples bias and attitude error, so a
manoeuvring vehicle makes more of the bias observable than PI can use.
The set-point is not exact: a body-fixed field (motor current) seen before the outage is folded
into Ĥ^n and turns with the vehicle, so after a turn the field error pulls the attitude off.
``outage_field_walk_mG`` lets Ĥ^n drift slowly in the outage so the filter does not chase it, and
``outage_gyro_bias_sigma_rad_s`` (widening the bias covariance at the outage start) is 0: both
trade the fastest learning of a sudden bias change for robustness.  Measured: on the idealised
benchmark flight (no body-fixed field) an unseen 0.5°/s bias step gives an attitude error of
RMS 7° with sigma 0.001 and no walk, 25° with the defaults (open loop 35°; 5-seed means,
benchmarks/heading.py); on simulated missions with a
motor-current field that turn 180° in the outage, sigma 0.001 put the heading 21-57° (median)
from the autopilot's, the defaults 1.0-2.5° (PI 0.5-7.3°, open loop 1.1-2.8°).
With the battery current I (``update_current``), the motor-current field is estimated too:
H_m = Ĉᵀ Ĥ^n + d^b + c·I with c [mG/A] as states (prior ``motor_field_sigma_mG_per_A``; inert
without current).  While GPS is good, current changes and turns separate c·I from Ĥ^n, so the
set-point stays clean through the outage.  Measured against the truth of three simulated
gps-outage missions (heading error in the outage, median/max): default filter without current
2.0/3.4°, 0.4/1.0°, 2.5/4.6°; with current 0.4/0.7°, 0.3/0.6°, 3.3/3.7°; the step-tuned setting
(below) goes from 22-57° median to 0.5-5.5° (tests: c recovered to 0.04 mG/A).
``body_field_sigma_mG`` > 0 adds a body-fixed field d^b to the state (the magnetometer model
becomes H_m = Ĉᵀ Ĥ^n + d^b): turns with GPS separate it from Ĥ^n, which removes a constant
residual hard iron (tests: 39 mG -> heading error 0.5° instead of 15°).  It is off by default:
against the truth of three simulated gps-outage missions, whose motor field follows the current,
it helped two (outage heading max 1.4° vs 3.4°, 2.0° vs 1.0° the other way) and not the third.
``gravity_kp_per_s`` > 0 (PI law only) instead adds the missing axis from the gravity-vector
error (accelerometer vs. −g), an extension to seed 003, off by default: manoeuvre accelerations
corrupt it and the high inclination magnifies that into heading (benchmarks/heading.py shows it).

Tilt.  While GPS is good the magnetometer update corrects the heading (ψ_D) and the field states
only (``mag_tilt_gps`` False: its roll/pitch columns and gain rows are zeroed, the Joseph form
keeps P consistent): GPS velocity observes the tilt, and a magnetometer model error (a motor-current
field not learnt yet, residual soft iron) otherwise holds roll/pitch degrees off until the next turn
(measured on a simulated gps-outage mission: 5–7° of roll for 150 s).  In an outage the field is
the only attitude aid and corrects the tilt too (``mag_tilt_outage``, seed 003).  The initial tilt
comes from one accelerometer sample, off by rotor drag and gusts on a hovering multirotor, so its
prior is wide (``init_attitude_sigma_rad``) and the accelerometer-bias prior narrow: with the old
priors the filter explained a 6° tilt error as 1.1 m/s² of accelerometer bias and kept it.
Gating (PX4 EKF2's innovation test, updateAidSourceStatus): every GPS and magnetometer update
records an ``AidStatus`` (innovation, variance, test ratio max z²/(gate²·S)) and is rejected when
the ratio exceeds 1; gates in sigmas: GPS 5 (EKF2_GPS_P/V_GATE), magnetometer 20 — gross outliers
only, since with EKF2's 3 the magnetometer of a flight whose motor field is not learnt yet is
rejected for good (measured: test ratios 3–10 for 150 s on the same mission).

Mode per step: 0 = initialising, 1 = GPS (Kalman), 2 = field-vector feedback, 3 = open loop.
Pure numpy; units m, m/s, m/s^2, rad, rad/s, mG; body FRD, navigation NED.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.attitude import roll_pitch_from_specific_force
from estimators.rotations import (dcm_body_to_ned, euler_from_dcm, rotation_from_vector_rad, skew, wrap_angle_deg,
                                  wrap_heading_rad, wrap_heading_rad_float)
from estimators.heading import tilt_compensated_heading_rad
from estimators.residual_trackers import MOTOR_TIMEOUT_S

__all__ = ["InsGpsSettings", "InsGpsFilter", "InsGpsState", "InsGpsResult", "AidStatus", "run_ins_gps",
           "MODE_INIT", "MODE_GPS", "MODE_FIELD_FEEDBACK", "MODE_OPEN_LOOP", "MODE_NAMES",
           "attitude_errors_deg"]

MODE_INIT, MODE_GPS, MODE_FIELD_FEEDBACK, MODE_OPEN_LOOP = 0, 1, 2, 3
NX = 24   # ψ, δv, δp, δb_g, δb_a, δH^n, δd^b (body-fixed field), δc (motor field per amp)
MODE_NAMES = {0: "init", 1: "gps", 2: "field_feedback", 3: "open_loop"}
GRAVITY_MPS2 = 9.80665


def _finite3(v) -> np.ndarray | None:
    """``v`` as a float 3-vector when it is one with finite entries, else None."""
    try:
        x, y, z = (float(e) for e in v)
    except (TypeError, ValueError):
        return None
    return np.array((x, y, z)) if math.isfinite(x + y + z) else None


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else np.zeros(3)


@dataclass(frozen=True)
class InsGpsSettings:
    gyro_noise_rad_s: float = 0.005          # per-sample gyro noise (1 sigma)
    accel_noise_mps2: float = 0.05
    gyro_bias_walk: float = 2e-5             # rad/s per sqrt(s)
    accel_bias_walk: float = 2e-4            # m/s^2 per sqrt(s)
    gps_pos_sigma_m: float = 1.5
    gps_vel_sigma_mps: float = 0.15
    gps_timeout_s: float = 1.0
    mag_timeout_s: float = 0.5
    mag_update_interval_s: float = 0.2       # magnetometer Kalman updates at most this often
    mag_sigma_mG: float = 3.0                # magnetometer noise + field model error (1 sigma)
    field_walk_mG: float = 0.05              # random walk of the NED field states, mG per sqrt(s)
    init_field_sigma_frac: float = 0.005     # prior on the field (horizontal direction ~0.7°: WMM)
    field_feedback: bool = True              # False: open-loop INS during outages (for comparison)
    feedback_kp_per_s: float = 0.5           # "pi": K_P [rad/s per rad of vector error]
    feedback_ki_per_s2: float = 0.02         # "pi": K_I
    gravity_kp_per_s: float = 0.0            # gravity help for the field-line axis (0 = seed 003 only)
    feedback_law: str = "kalman"             # "kalman" (default) or "pi" (seed 003's fixed gains)
    outage_gyro_bias_sigma_rad_s: float = 0.0    # "kalman": bias change allowed at the outage start (see doc)
    outage_gyro_bias_walk: float = 1e-4      # "kalman": bias random walk in outage, rad/s per sqrt(s)
    body_field_sigma_mG: float = 0.0         # prior of a body-fixed field d^b (0 = not estimated)
    body_field_walk_mG: float = 0.2          # its random walk, mG per sqrt(s)
    motor_field_sigma_mG_per_A: float = 3.0  # prior of the motor-current field c, H_m += c·I (needs current)
    current_timeout_s: float = MOTOR_TIMEOUT_S   # an older battery-current sample is not used (the one timeout)
    outage_field_walk_mG: float = 1.0        # "kalman": the set-point may drift, mG per sqrt(s) (see doc)
    declination_deg: float = 0.0             # initial heading from the magnetometer + declination
    init_attitude_sigma_rad: float = 0.1     # tilt from one accelerometer sample: rotor drag, gusts
    init_yaw_sigma_rad: float = 0.1
    init_gyro_bias_sigma_rad_s: float = 0.005
    init_accel_bias_sigma_mps2: float = 0.03  # tighter than the tilt: else a tilt error hides in b_a
    mag_tilt_gps: bool = False               # the magnetometer corrects roll/pitch while GPS is good (see doc)
    mag_tilt_outage: bool = True             # ... and in a GPS outage (seed 003's field-vector feedback)
    gps_gate_sigma: float = 5.0              # GPS innovation gate [innovation sigmas] (EKF2_GPS_P/V_GATE)
    mag_gate_sigma: float = 20.0             # magnetometer gate [sigmas]: gross outliers only (see doc)
    max_dt_s: float = 0.1                    # longer IMU gaps are not integrated
    covariance_interval_s: float = 0.1       # error covariance propagated in blocks of this length


@dataclass(frozen=True)
class AidStatus:
    """One aiding update, as PX4 EKF2's aid-source status (updateAidSourceStatus, EKF/ekf.h):
    innovation z − H·x̂ and its variance H P Hᵀ + R per component, the test ratio
    max(z²/(gate²·S)) and whether the update was rejected (test ratio > 1: state left as it was)."""
    t_s: float
    innovation: tuple
    variance: tuple
    test_ratio: float
    rejected: bool


@dataclass
class InsGpsState:
    t_s: float
    mode: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    vel_ned_mps: np.ndarray
    pos_ned_m: np.ndarray
    gyro_bias_rad_s: np.ndarray
    field_ned_mG: np.ndarray


@dataclass
class InsGpsResult:
    t_s: np.ndarray
    mode: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    vel_ned_mps: np.ndarray
    pos_ned_m: np.ndarray
    gyro_bias_rad_s: np.ndarray
    field_ned_mG: np.ndarray
    gps_test_ratio: np.ndarray | None = None   # latest GPS update's test ratio at each step (NaN before)
    mag_test_ratio: np.ndarray | None = None   # latest magnetometer update's test ratio (NaN before)


class InsGpsFilter:
    """Per-sample INS/GPS filter (seed 003).  Feed time-ordered ``update_mag``, ``update_gps`` and
    ``update_imu`` calls; ``update_imu`` returns the state after that IMU step."""

    def __init__(self, settings: InsGpsSettings | None = None):
        self.s = settings or InsGpsSettings()
        if self.s.feedback_law not in ("kalman", "pi"):
            raise ValueError(f"feedback_law must be 'kalman' or 'pi', not {self.s.feedback_law!r}")
        self.C = np.eye(3)                 # C_b^n
        self.v = np.zeros(3)
        self.p = np.zeros(3)
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.P = np.zeros((NX, NX))
        self.field_ned = np.zeros(3)
        self.body_field = np.zeros(3)
        self.motor_field = np.zeros(3)         # c [mG/A]
        self._current_A: float | None = None
        self._current_t = -np.inf
        self.field_ready = False
        self.integral = np.zeros(3)
        self.mode = MODE_INIT
        self.t: float | None = None
        s = self.s
        self._eye = np.eye(NX)
        self._q_dt2 = np.r_[[s.gyro_noise_rad_s ** 2] * 3, [s.accel_noise_mps2 ** 2] * 3, [0.0] * 18]
        self._q_dt = np.r_[[0.0] * 9, [s.gyro_bias_walk ** 2] * 3, [s.accel_bias_walk ** 2] * 3,
                           [s.field_walk_mG ** 2] * 3,
                           [s.body_field_walk_mG ** 2 if s.body_field_sigma_mG > 0 else 0.0] * 3,
                           [0.0] * 3]
        self._F = np.zeros((NX, NX))
        self._F[6:9, 3:6] = np.eye(3)
        self._mag = None
        self._mag_t = -np.inf
        self._mag_used_t = -np.inf
        self._gps_t = -np.inf
        self._attitude_ok = False
        self._nav_ok = False
        self._cov_dt, self._cov_f_dt, self._cov_q_dt2 = 0.0, np.zeros(3), 0.0
        self.gps_status: AidStatus | None = None
        self.mag_status: AidStatus | None = None

    # -- measurements -------------------------------------------------------------------------
    def update_mag(self, t_s: float, mag_body_mG) -> None:
        self._set_mag(float(t_s), _finite3(mag_body_mG))

    def _set_mag(self, t_s: float, m: np.ndarray | None) -> None:
        if m is not None and math.isfinite(t_s) and m @ m > 1.0:
            self._mag, self._mag_t = m, t_s

    def update_current(self, t_s: float, current_A: float) -> None:
        """Battery (motor) current [A], for the motor-field states."""
        if math.isfinite(t_s) and math.isfinite(current_A) and current_A >= 0.0:
            self._current_A, self._current_t = float(current_A), float(t_s)

    def _held_current(self) -> float | None:
        """The battery current at the latest magnetometer sample, None when there is none recent."""
        return self._current_A if self._mag_t - self._current_t <= self.s.current_timeout_s else None

    def _mag_bias(self) -> np.ndarray:
        """Body-frame field that is not the Earth's: d^b + c·I (zero when not estimated)."""
        current = self._held_current()
        return self.body_field + (self.motor_field * current if current is not None else 0.0)

    def update_gps(self, t_s: float, pos_ned_m, vel_ned_mps) -> None:
        p = np.asarray(pos_ned_m, dtype=float)
        v = np.asarray(vel_ned_mps, dtype=float)
        if not (np.isfinite(t_s) and np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
            return
        returning = self._nav_ok and float(t_s) - self._gps_t > self.s.gps_timeout_s
        self._gps_t = float(t_s)
        if not self._attitude_ok:
            return
        if not self._nav_ok or returning:
            # first fix, or GPS back after an outage: take position and velocity from GPS and drop
            # their (outage-grown) correlations, so a large innovation cannot tip the attitude
            self.p, self.v, self._nav_ok = p.copy(), v.copy(), True
            self._propagate_covariance()
            self.P[3:9, :] = 0.0
            self.P[:, 3:9] = 0.0
            self.P[3:6, 3:6] = np.eye(3) * self.s.gps_vel_sigma_mps ** 2
            self.P[6:9, 6:9] = np.eye(3) * self.s.gps_pos_sigma_m ** 2
            return
        self._kalman_gps(p, v)

    # -- core -----------------------------------------------------------------------------------
    def _initialise(self, accel: np.ndarray) -> bool:
        if self._mag is None or not np.all(np.isfinite(accel)) or np.linalg.norm(accel) < 1.0:
            return False
        roll, pitch = roll_pitch_from_specific_force(accel)
        yaw = float(tilt_compensated_heading_rad(self._mag, roll, pitch)) + np.radians(self.s.declination_deg)
        self.C = dcm_body_to_ned(roll, pitch, yaw)
        s = self.s
        # Ĉ·H_m has the declination as its horizontal direction by construction (the initial yaw
        # is the magnetic heading + declination), so its error is independent of the yaw error:
        # an independent prior of WMM accuracy fixes the absolute heading.
        self.field_ned = self.C @ self._mag
        h_sigma = s.init_field_sigma_frac * float(np.linalg.norm(self.field_ned))
        self.P = np.diag(np.r_[[s.init_attitude_sigma_rad ** 2] * 2, s.init_yaw_sigma_rad ** 2,
                               [1.0] * 3, [25.0] * 3, [s.init_gyro_bias_sigma_rad_s ** 2] * 3,
                               [s.init_accel_bias_sigma_mps2 ** 2] * 3, [h_sigma ** 2] * 3,
                               [s.body_field_sigma_mG ** 2] * 3, [s.motor_field_sigma_mG_per_A ** 2] * 3])
        self.field_ready = True
        self._attitude_ok = True
        return True

    def _kalman_gps(self, p_meas: np.ndarray, v_meas: np.ndarray) -> None:
        s = self.s
        H = np.zeros((6, NX))
        H[0:3, 6:9] = np.eye(3)
        H[3:6, 3:6] = np.eye(3)
        R = np.diag([s.gps_pos_sigma_m ** 2] * 3 + [s.gps_vel_sigma_mps ** 2] * 3)
        self.gps_status = self._update(H, R, np.r_[p_meas - self.p, v_meas - self.v], s.gps_gate_sigma)

    def _kalman_mag(self, field_is_setpoint: bool = False, outage: bool = False) -> None:
        """Magnetometer update: z = H_m − Ĉᵀ Ĥ^n − d^b − c·I = Ĉᵀ[Ĥ^n×] ψ + Ĉᵀ δH^n + δd^b + I δc.
        While GPS is good the field states are estimated; in an outage (``field_is_setpoint``)
        Ĥ^n is held fixed."""
        H = np.zeros((3, NX))
        Ct = self.C.T
        H[:, 0:3] = Ct @ skew(self.field_ned)
        if not field_is_setpoint:
            H[:, 15:18] = Ct
        H[:, 18:21] = np.eye(3)
        current = self._held_current()
        if current is not None:
            H[:, 21:24] = np.eye(3) * current
        R = np.eye(3) * self.s.mag_sigma_mG ** 2
        no_tilt = not (self.s.mag_tilt_outage if outage else self.s.mag_tilt_gps)
        if no_tilt:
            H[:, 0:2] = 0.0
        self.mag_status = self._update(H, R, self._mag - Ct @ self.field_ned - self._mag_bias(), self.s.mag_gate_sigma,
                                       frozen=slice(0, 2) if no_tilt else None)

    def _update(self, H: np.ndarray, R: np.ndarray, z: np.ndarray, gate_sigma: float,
                frozen: slice | None = None) -> AidStatus:
        """Kalman measurement update z = H δx + v, v ~ N(0, R), on the covariance propagated up to
        now; the estimated error δx is folded into the nominal state.  Innovation gate: rejected
        (no update) when any component has z² > gate²·S (S = H P Hᵀ + R).  ``frozen`` states get no
        correction (their gain rows are zeroed; the Joseph form keeps P consistent for any gain)."""
        self._propagate_covariance()
        PHt = self.P @ H.T
        S = H @ PHt + R
        var = np.diag(S)
        ratio = float(np.max(z * z / (gate_sigma ** 2 * var)))
        status = AidStatus(float(self.t) if self.t is not None else 0.0, tuple(z.tolist()), tuple(var.tolist()),
                           ratio, ratio > 1.0)
        if status.rejected:
            return status
        K = np.linalg.solve(S, PHt.T).T
        if frozen is not None:
            K[frozen, :] = 0.0
        dx = K @ z
        IKH = self._eye - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ R @ K.T     # Joseph form
        self.P = 0.5 * (self.P + self.P.T)
        self.C = rotation_from_vector_rad(dx[0:3]) @ self.C
        self.v += dx[3:6]
        self.p += dx[6:9]
        self.bg += dx[9:12]
        self.ba += dx[12:15]
        self.field_ned = self.field_ned + dx[15:18]
        self.body_field = self.body_field + dx[18:21]
        self.motor_field = self.motor_field + dx[21:24]
        return status

    def update_imu(self, t_s: float, gyro_rad_s, accel_mps2) -> InsGpsState:
        """One IMU step (gyro rad/s, specific force m/s², body FRD); returns the state after it."""
        self._step(float(t_s), _finite3(gyro_rad_s), _finite3(accel_mps2))
        return self.state()

    def _step(self, t_s: float, w_m: np.ndarray | None, f_m: np.ndarray | None) -> None:
        """One IMU step with inputs already checked: finite 3-vectors or None."""
        s = self.s
        good_w, good_f = w_m is not None, f_m is not None
        t = t_s if math.isfinite(t_s) else None
        if t is None or (self.t is not None and t < self.t):
            return                                    # unusable time: no step
        dt = 0.0 if self.t is None else t - self.t
        self.t = t
        if not self._attitude_ok:
            if good_f:
                self._initialise(f_m)
            self.mode = MODE_INIT
            return
        if dt > s.max_dt_s or not (good_w and good_f):
            dt = 0.0
        gps_ok = self._nav_ok and (t - self._gps_t) <= s.gps_timeout_s
        mag_ok = self._mag is not None and 0.0 <= t - self._mag_t <= s.mag_timeout_s
        new_mode = (MODE_GPS if gps_ok else MODE_INIT if not self._nav_ok
                    else MODE_FIELD_FEEDBACK if (s.field_feedback and self.field_ready) else MODE_OPEN_LOOP)
        if new_mode != self.mode:
            if self.mode == MODE_FIELD_FEEDBACK:              # leaving the outage: keep what was learnt
                self.bg -= s.feedback_ki_per_s2 * self.integral
            if new_mode == MODE_FIELD_FEEDBACK and s.feedback_law == "kalman":
                self.P[9:12, 9:12] += np.eye(3) * s.outage_gyro_bias_sigma_rad_s ** 2
            self.integral = np.zeros(3)
            self.mode = new_mode
        if dt == 0.0:
            return

        w = w_m - self.bg
        f = f_m - self.ba
        kalman_outage = self.mode == MODE_FIELD_FEEDBACK and s.feedback_law == "kalman"
        if self.mode == MODE_FIELD_FEEDBACK and not kalman_outage:
            w = w + self._feedback(f, mag_ok, dt)

        C0 = self.C
        f_n = C0 @ f
        a_n = f_n + np.array([0.0, 0.0, GRAVITY_MPS2])
        self.p = self.p + self.v * dt + 0.5 * a_n * dt * dt
        self.v = self.v + a_n * dt
        self.C = C0 @ rotation_from_vector_rad(w * dt)
        self._cov_dt += dt
        self._cov_f_dt += f_n * dt
        self._cov_q_dt2 += dt * dt
        if self._cov_dt >= s.covariance_interval_s:
            self._propagate_covariance()

        if ((self.mode == MODE_GPS or kalman_outage) and mag_ok
                and self._mag_t >= self._mag_used_t + s.mag_update_interval_s):
            self._mag_used_t = self._mag_t
            self._kalman_mag(field_is_setpoint=kalman_outage and s.outage_field_walk_mG <= 0.0, outage=kalman_outage)
        if int(t * 10) % 50 == 0:                             # keep C orthonormal
            u, _, vt = np.linalg.svd(self.C)
            self.C = u @ vt

    def _propagate_covariance(self) -> None:
        """Error-state covariance over the IMU steps since the last call (seed 003 eqs. 1-3):
        Φ = I + F·Δt with F at the current attitude and the block's mean specific force (the
        error dynamics are slow next to the IMU rate, so blocks of tens of ms lose nothing)."""
        dt = self._cov_dt
        if dt <= 0.0:
            return
        C = self.C
        F = self._F
        F[0:3, 9:12] = -C
        F[3:6, 0:3] = -skew(self._cov_f_dt / dt)
        F[3:6, 12:15] = -C
        Phi = self._eye + F * dt
        self.P = Phi @ self.P @ Phi.T
        self.P[np.diag_indices(NX)] += self._q_dt2 * self._cov_q_dt2 + self._q_dt * dt
        if self.mode == MODE_FIELD_FEEDBACK and self.s.feedback_law == "kalman":
            self.P[9:12, 9:12] += np.eye(3) * (self.s.outage_gyro_bias_walk ** 2 * dt)
            self.P[15:18, 15:18] += np.eye(3) * (self.s.outage_field_walk_mG ** 2 * dt)
        self._cov_dt, self._cov_f_dt, self._cov_q_dt2 = 0.0, np.zeros(3), 0.0

    def _feedback(self, f_body: np.ndarray, mag_ok: bool, dt: float) -> np.ndarray:
        """PI correction of the gyro rates from the field-vector error (seed 003 sec. 2).

        e_m = Ĥ_m^b × Ĉ_n^b Ĥ^n (unit vectors) is the seed's error: for an attitude error δ it is
        −δ without its component along the field, so a rotation about the field line is never
        seen.  ``gravity_kp_per_s`` > 0 adds that one missing component from the gravity-vector
        error e_g = f × (−Ĉᵀ z): only e_g's projection on the field direction is used (scaled by
        1/|u_h|², so it equals −α for an error α about the field line); the other axes stay on the
        (acceleration-free) field error.  Returns K_P e + K_I ∫e.
        """
        s = self.s
        if not mag_ok:
            return s.feedback_ki_per_s2 * self.integral
        u = _unit(self.C.T @ self.field_ned)
        e = np.cross(_unit(self._mag - self._mag_bias()), u)
        corr = s.feedback_kp_per_s * e
        if s.gravity_kp_per_s > 0.0:
            down_b = self.C[2, :]                             # nav down axis in body
            uh2 = max(1.0 - float(u @ down_b) ** 2, 0.05)
            e_g = np.cross(_unit(f_body), -down_b)
            e_al = (e_g @ u) / uh2 * u
            corr = corr + s.gravity_kp_per_s * e_al
            e = e + (s.gravity_kp_per_s / max(s.feedback_kp_per_s, 1e-9)) * e_al
        self.integral += e * dt
        return corr + s.feedback_ki_per_s2 * self.integral

    def state(self) -> InsGpsState:
        r, p, y = euler_from_dcm(self.C)
        return InsGpsState(self.t if self.t is not None else 0.0, self.mode, float(r), float(p),
                           wrap_heading_rad_float(float(y)), self.v.copy(), self.p.copy(), self.bg.copy(),
                           self.field_ned.copy())


def run_ins_gps(imu: np.ndarray, gps_ned: np.ndarray, mag: np.ndarray,
                settings: InsGpsSettings | None = None, filt: InsGpsFilter | None = None,
                current: np.ndarray | None = None) -> InsGpsResult:
    """Run ``InsGpsFilter`` over a whole log (per sample: the filter is sequential by nature).

    imu (N,7) [t, gx, gy, gz, ax, ay, az];  gps_ned (G,7) [t, pN, pE, pD m, vN, vE, vD m/s];
    mag (M,4) [t, mx, my, mz mG] calibrated.  Measurements with t equal to an IMU sample are
    applied before it.  Returns arrays on the IMU time base.  ``filt``: continue this filter
    (it is advanced in place) instead of starting a new one with ``settings``.  ``current`` (K,2)
    [t, battery current A] feeds the motor-field states.
    """
    imu = np.asarray(imu, dtype=float).reshape(-1, 7)
    gps_ned = np.asarray(gps_ned, dtype=float).reshape(-1, 7)
    mag = np.asarray(mag, dtype=float).reshape(-1, 4)
    f = filt if filt is not None else InsGpsFilter(settings)
    events = ([(t, 0, i) for i, t in enumerate(mag[:, 0].tolist()) if math.isfinite(t)]
              + [(t, 1, i) for i, t in enumerate(gps_ned[:, 0].tolist()) if math.isfinite(t)])
    cur = np.zeros((0, 2)) if current is None else np.asarray(current, dtype=float).reshape(-1, 2)
    events += [(t, 2, i) for i, t in enumerate(cur[:, 0].tolist()) if math.isfinite(t)]
    events.sort()
    mag_ok = np.all(np.isfinite(mag[:, 1:4]), axis=1)       # input checks vectorised up front
    gyro_ok = np.all(np.isfinite(imu[:, 1:4]), axis=1)
    accel_ok = np.all(np.isfinite(imu[:, 4:7]), axis=1)
    t_imu = imu[:, 0].tolist()
    n = len(imu)
    mode = np.zeros(n, dtype=int)
    dcm = np.zeros((n, 3, 3))
    vel, pos, bg, fld = (np.zeros((n, 3)) for _ in range(4))
    ratios = np.full((n, 2), np.nan)
    j = 0
    for i in range(n):
        ti = t_imu[i]
        while j < len(events) and events[j][0] <= ti:
            te, kind, k = events[j]
            if kind == 0:
                f._set_mag(te, mag[k, 1:4].copy() if mag_ok[k] else None)
            elif kind == 2:
                f.update_current(te, float(cur[k, 1]))
            else:
                f.update_gps(te, gps_ned[k, 1:4], gps_ned[k, 4:7])
            j += 1
        f._step(ti, imu[i, 1:4].copy() if gyro_ok[i] else None, imu[i, 4:7].copy() if accel_ok[i] else None)
        mode[i], dcm[i], vel[i], pos[i], bg[i], fld[i] = f.mode, f.C, f.v, f.p, f.bg, f.field_ned
        if f.gps_status is not None:
            ratios[i, 0] = f.gps_status.test_ratio
        if f.mag_status is not None:
            ratios[i, 1] = f.mag_status.test_ratio
    roll, pitch, yaw = euler_from_dcm(dcm)
    return InsGpsResult(imu[:, 0].copy(), mode, roll, pitch, wrap_heading_rad(yaw), vel, pos, bg, fld,
                        ratios[:, 0], ratios[:, 1])


# --------------------------------------------------------------------------------------------
# Scoring against truth (generators: groundstation.sim.truth)
# --------------------------------------------------------------------------------------------
def attitude_errors_deg(estimate: "InsGpsResult", truth) -> tuple[np.ndarray, np.ndarray]:
    """(total attitude error angle, heading error) [deg] per IMU step: the angle of the rotation
    C_true^T · C_est, and ψ̂ − ψ wrapped to (−180, 180]."""
    c_est = dcm_body_to_ned(estimate.roll_rad, estimate.pitch_rad, estimate.yaw_rad)
    c_true = dcm_body_to_ned(truth.roll_rad, truth.pitch_rad, truth.yaw_rad)
    d = np.einsum("nij,nik->njk", c_true, c_est)
    angle_deg = np.degrees(np.arccos(np.clip((np.trace(d, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return angle_deg, wrap_angle_deg(np.degrees(estimate.yaw_rad - truth.yaw_rad))
