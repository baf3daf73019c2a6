"""Closed-loop multirotor flight simulator with magnetic interference (seed 002 section 2).

Pure numpy (no I/O); ``groundstation.sim.scenarios`` turns the result into MAVLink messages.

Physics (seed 002 section 2):
  * translation, eq. (1)/(3): p' = v, v' = g e3 − (f/m) R e3 + drag·(wind − v); altitude held,
    so the horizontal acceleration comes from the tilt of the thrust.
  * the autopilot turns a desired horizontal acceleration into roll/pitch with its *estimated*
    yaw ψ̂, eq. (4); the airframe however sits at its true yaw ψ, so the produced acceleration is
    the desired one rotated by Δψ = ψ̂ − ψ, eq. (5).  The autopilot's INS also rotates its
    accelerometer by ψ̂ before blending with GPS, so its velocity/position estimate drifts
    sideways when ψ̂ is wrong; the position controller then steers the true track off the line.
  * ψ̂ comes from the autopilot's own gyro/magnetometer complementary filter (seed 000 eq. 9/10,
    ``estimators.attitude.FieldVectorFilter``) followed by tilt compensation (seed 000 eq. 11-13).

Sensors: magnetometer m_raw = A (m_body + m_motor) + b + m_interf + noise (soft iron +
misalignment A, hard iron b, motor-current field m_motor = c I(thrust) fixed in the body,
interference on a sensor axis), gyro with bias, accelerometer (specific force), GPS (RTK fix 6
with cm noise or 3-D fix 3 with metre-level correlated error).  Frames: NED navigation,
FRD body, local tangent plane at the origin.  Units: m, m/s, rad, mG.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.attitude import run_vector_filter
from estimators.detection import lla_from_ned, ned_from_lla  # noqa: F401  (re-exported)
from estimators.heading import tilt_compensated_heading_rad
from estimators.rotations import dcm_body_to_ned, euler_from_dcm, wrap_angle_rad

from groundstation.sim.disturbances import (GroundAnomaly, Interference, PayloadLoad, anomaly_field_body_mG,
                                             payload_current_A, payload_field_body_mG)
from groundstation.sim.mission_loop import G, MissionLoop, wrap_pi as _wrap


__all__ = ["Interference", "PayloadLoad", "GroundAnomaly", "MagModel", "SimConfig", "SimResult", "run", "ned_from_lla", "lla_from_ned",
           "G"]


# --------------------------------------------------------------------------- geometry helpers
def _gauss_markov(rng: np.random.Generator, n: int, dt: float, sigma: float, tau_s: float, dims: int) -> np.ndarray:
    """First-order Gauss-Markov process (stationary, std sigma, correlation time tau)."""
    out = np.zeros((n, dims))
    if sigma <= 0 or n == 0:
        return out
    a = math.exp(-dt / tau_s)
    w = rng.normal(0.0, sigma * math.sqrt(1 - a * a), (n, dims))
    x = rng.normal(0.0, sigma, dims)
    # x_k = a x_{k-1} + w_k, evaluated blockwise with powers of a (vectorised, exact)
    blk = 256
    powers = a ** np.arange(1, blk + 1)
    for s in range(0, n, blk):
        ww = w[s:s + blk]
        m = len(ww)
        idx = np.arange(m)
        # lower-triangular convolution within the block
        lag = idx[:, None] - idx[None, :]
        kern = np.where(lag >= 0, a ** np.clip(lag, 0, None), 0.0)
        out[s:s + m] = kern @ ww + powers[:m, None] * x
        x = out[s + m - 1]
    return out


# --------------------------------------------------------------------------- models
@dataclass
class MagModel:
    """m_raw = A (m_body + c·I) + b + interference + noise (issue 3 model; seed 004)."""
    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))       # A (soft iron · misalignment)
    offsets_mG: np.ndarray = field(default_factory=lambda: np.zeros(3))  # b (hard iron)
    misalignment_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    noise_mG: float = 2.0
    motor_mG_per_A: np.ndarray = field(default_factory=lambda: np.zeros(3))  # body-fixed, per amp
    hover_current_A: float = 20.0

    @staticmethod
    def random(rng: np.random.Generator, offset_mG: float = 150.0, soft: float = 0.05,
               misalign_deg: float = 2.0) -> "MagModel":
        s = np.eye(3) + np.diag(rng.uniform(-soft, soft, 3))
        off = rng.uniform(-soft / 2, soft / 2, 3)
        s[0, 1] = s[1, 0] = off[0]
        s[0, 2] = s[2, 0] = off[1]
        s[1, 2] = s[2, 1] = off[2]
        mis = rng.uniform(-misalign_deg, misalign_deg, 3)
        rot = dcm_body_to_ned(*np.radians(mis)).T   # body -> sensor
        return MagModel(matrix=s @ rot, offsets_mG=rng.uniform(-offset_mG, offset_mG, 3), misalignment_deg=mis)


@dataclass
class SimConfig:
    """Everything a run needs.  ``kind``: "dance" | "headings" | "mission"."""
    kind: str = "mission"
    seed: int = 0
    duration_s: float = 300.0
    rate_hz: float = 50.0
    gps_rate_hz: float = 10.0
    origin_lat_deg: float = 30.26
    origin_lon_deg: float = 120.12
    ground_alt_m: float = 20.0
    flight_alt_m: float = 20.0            # above ground
    field_ned_mG: np.ndarray = field(default_factory=lambda: np.array([336.6, -35.8, 353.5]))
    declination_deg: float = -6.07
    mag: MagModel = field(default_factory=MagModel)
    interference: Interference = field(default_factory=Interference)
    gyro_bias_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_noise_rad_s: float = 0.004
    accel_noise_mps2: float = 0.15
    rtk: bool = True
    gps_outage: tuple[float, float] | None = None
    payload: PayloadLoad | None = None    # a payload switched on and off (its current and field)
    anomaly: GroundAnomaly | None = None  # a magnetised mass on the ground (a field tied to a place)
    # mission
    leg_bearing_deg: float = 30.0
    leg_length_m: float = 400.0
    speed_mps: float = 6.0
    hover_s: float = 20.0
    yaw_sweep_deg_s: float = 0.0          # nose turning at this rate through the mission (0: along the leg)
    mean_wind_mps: tuple[float, float] = (1.5, -1.0)     # NE
    gust_sigma_mps: float = 0.3
    gust_tau_s: float = 2.0
    vertical_gust_sigma_mps2: float = 0.8
    drag_per_s: float = 0.45
    autopilot_mag_gain_per_s: float = 0.5
    autopilot_motor_comp: float = 0.8      # fraction of the motor field the autopilot compensates
    pos_gain_per_s: float = 0.25           # cross/along-track position P gain (gentle line tracking)
    vel_gain_per_s: float = 0.8            # velocity P gain
    vel_int_gain_per_s2: float = 0.2      # velocity I gain
    # dance / headings
    dance_rate_deg_s: float = 45.0
    heading_hold_s: float = 5.0


@dataclass
class SimResult:
    """Time series on the 50 Hz step grid (t_s from 0) plus GPS rows at the GPS rate."""
    t_s: np.ndarray
    roll_rad: np.ndarray            # truth
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    est_roll_rad: np.ndarray        # autopilot estimate (ATTITUDE)
    est_pitch_rad: np.ndarray
    est_yaw_rad: np.ndarray
    gyro_rad_s: np.ndarray          # measured (N,3)
    accel_mps2: np.ndarray          # measured specific force (N,3)
    mag_raw_mG: np.ndarray          # measured (N,3), sensor frame
    body_rate_rad_s: np.ndarray     # truth
    pos_ned_m: np.ndarray           # truth (N,3)
    vel_ned_mps: np.ndarray         # truth
    est_pos_ned_m: np.ndarray       # autopilot estimate
    est_vel_ned_mps: np.ndarray
    interference_mG: np.ndarray     # (N,3) sensor frame
    motor_current_A: np.ndarray
    gps_idx: np.ndarray             # indices into the step grid where GPS rows are
    gps_pos_ned_m: np.ndarray
    gps_vel_ned_mps: np.ndarray
    gps_fix_type: np.ndarray
    cross_track_m: np.ndarray       # truth distance to the A-B line (NaN when no mission)
    mission_ned_m: np.ndarray | None = None   # (2,3) A, B
    events: list = field(default_factory=list)


# --------------------------------------------------------------------------- attitude profiles
def _integrate_rates(rates: np.ndarray, dt: float, r0: np.ndarray) -> np.ndarray:
    """Body rates (N,3) -> DCMs (N,3,3) by exact per-step rotation (Rodrigues)."""
    n = len(rates)
    out = np.empty((n, 3, 3))
    r = r0.copy()
    th = rates * dt
    ang = np.linalg.norm(th, axis=1)
    for i in range(n):
        out[i] = r
        a = ang[i]
        if a > 0:
            k = th[i] / a
            kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            r = r @ (np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx)
    return out


def _dance_rates(cfg: SimConfig, rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """Calibration dance: full turns about X, then Y, then Z, then a tumble; pauses between."""
    dt = 1.0 / cfg.rate_hz
    w = math.radians(cfg.dance_rate_deg_s)
    turn_s = 2 * math.pi / w
    segs: list[tuple[str, float, np.ndarray]] = [("still", 5.0, np.zeros(3))]
    for axis, name in ((0, "x"), (1, "y"), (2, "z")):
        rate = np.zeros(3)
        rate[axis] = w
        segs += [(f"turn_{name}", turn_s, rate), ("still", 3.0, np.zeros(3))]
    tumble_total = max(0.0, cfg.duration_s - sum(s[1] for s in segs) - 3.0)
    n_tumble = max(1, int(tumble_total // 4.0))
    for _ in range(n_tumble):
        d = rng.normal(size=3)
        segs.append(("tumble", tumble_total / n_tumble, w * d / np.linalg.norm(d)))
    segs.append(("still", 3.0, np.zeros(3)))
    rates, events, t0 = [], [], 0.0
    for name, dur, rate in segs:
        k = int(round(dur / dt))
        rates.append(np.repeat(rate[None, :], k, axis=0))
        if name != "still":
            events.append({"kind": name, "start_s": round(t0, 3), "end_s": round(t0 + k * dt, 3)})
        t0 += k * dt
    return np.concatenate(rates), events


def _headings_profile(cfg: SimConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Seed 000 table 1: 8 headings 45° apart, at each level then rolled −20° (smooth moves)."""
    dt = 1.0 / cfg.rate_hz
    hold = cfg.heading_hold_s
    move = 2.0
    t = 2.0
    events = []
    pts = [(0.0, 0.0, 0.0)]   # (t, roll, yaw) key points; moves between them are smoothstep
    for i in range(8):
        yaw = math.radians(45.0 * i)
        if i:
            pts.append((t, 0.0, yaw - math.radians(45)))
            t += move
        pts.append((t, 0.0, yaw))
        events.append({"kind": "hold", "heading_deg": 45.0 * i, "roll_deg": 0.0, "start_s": t + 0.5, "end_s": t + hold})
        t += hold
        pts.append((t, 0.0, yaw))
        t += move
        pts.append((t, math.radians(-20), yaw))
        events.append({"kind": "hold", "heading_deg": 45.0 * i, "roll_deg": -20.0, "start_s": t + 0.5, "end_s": t + hold})
        t += hold
        pts.append((t, math.radians(-20), yaw))
        t += move
        pts.append((t, 0.0, yaw))
    t_end = t + 2.0
    pts.append((t_end, 0.0, pts[-1][2]))
    n = int(round(t_end / dt))
    ts = np.arange(n) * dt
    kt = np.array([p[0] for p in pts])
    kr = np.array([p[1] for p in pts])
    ky = np.array([p[2] for p in pts])
    j = np.clip(np.searchsorted(kt, ts, side="right") - 1, 0, len(kt) - 2)
    span = np.maximum(kt[j + 1] - kt[j], 1e-9)
    x = np.clip((ts - kt[j]) / span, 0, 1)
    s = x * x * (3 - 2 * x)
    roll = kr[j] + (kr[j + 1] - kr[j]) * s
    yaw = ky[j] + (ky[j + 1] - ky[j]) * s
    return ts, roll, yaw, events


# --------------------------------------------------------------------------- main entry
def run(cfg: SimConfig) -> SimResult:
    rng = np.random.default_rng(cfg.seed)
    if cfg.kind == "mission":
        return _run_mission(cfg, rng)
    return _run_static(cfg, rng)


def _sensors_common(cfg, rng, t, dcm, rates, acc_ned, current_A):
    n = len(t)
    field_body = np.einsum("nji,j->ni", dcm, cfg.field_ned_mG)
    motor = current_A[:, None] * np.asarray(cfg.mag.motor_mG_per_A)[None, :]
    interf = cfg.interference.field_sensor_mG(t)
    mag = (field_body + motor) @ cfg.mag.matrix.T + cfg.mag.offsets_mG + interf
    mag += rng.normal(0, cfg.mag.noise_mG, (n, 3))
    # gyro sample i = body rate over the step (i-1 -> i); rates[i] is the rate over (i -> i+1)
    prev = np.vstack([np.zeros((1, 3)), rates[:-1]])
    gyro = prev + cfg.gyro_bias_rad_s + rng.normal(0, cfg.gyro_noise_rad_s, (n, 3))
    f_ned = acc_ned - np.array([0.0, 0.0, G])
    accel = np.einsum("nji,nj->ni", dcm, f_ned) + rng.normal(0, cfg.accel_noise_mps2, (n, 3))
    return mag, gyro, accel, interf


def _gps_errors(cfg, rng, n):
    """GPS rows (every step-th grid step): position/velocity errors and fix type.

    RTK (fix 6): 1.2 cm white + 0.8 cm slowly wandering; 3-D fix (fix 3): 0.3 m white + 1.2 m
    Gauss-Markov (30 s).  During ``gps_outage`` the fix type is 1 (no fix)."""
    dt = 1.0 / cfg.rate_hz
    step = max(1, int(round(cfg.rate_hz / cfg.gps_rate_hz)))
    idx = np.arange(0, n, step)
    m = len(idx)
    if cfg.rtk:
        err = rng.normal(0, 0.012, (m, 3)) + _gauss_markov(rng, m, step * dt, 0.008, 20.0, 3)
        verr = rng.normal(0, 0.03, (m, 3))
        fix = np.full(m, 6)
    else:
        err = rng.normal(0, 0.3, (m, 3)) + _gauss_markov(rng, m, step * dt, 1.2, 30.0, 3)
        verr = rng.normal(0, 0.12, (m, 3))
        fix = np.full(m, 3)
    if cfg.gps_outage is not None:
        t = idx * dt
        fix[(t >= cfg.gps_outage[0]) & (t < cfg.gps_outage[1])] = 1
    return idx, step, err, verr, fix


def _autopilot_corrected_field(cfg, mag_raw, motor_body):
    """The field the autopilot's heading filter sees: its own calibration (exact) and partial
    motor-current compensation applied to the raw magnetometer."""
    a_inv = np.linalg.inv(cfg.mag.matrix)
    return (mag_raw - cfg.mag.offsets_mG) @ a_inv.T - cfg.autopilot_motor_comp * motor_body


def _run_static(cfg: SimConfig, rng) -> SimResult:
    dt = 1.0 / cfg.rate_hz
    if cfg.kind == "dance":
        rates, events = _dance_rates(cfg, rng)
        r0 = dcm_body_to_ned(0.0, 0.0, math.radians(cfg.leg_bearing_deg))
        dcm = _integrate_rates(rates, dt, r0)
        n = len(rates)
        t = np.arange(n) * dt
        roll, pitch, yaw = euler_from_dcm(dcm)
    else:
        t, roll, yaw, events = _headings_profile(cfg)
        # headings are absolute (from true north)
        n = len(t)
        pitch = np.zeros(n)
        dcm = dcm_body_to_ned(roll, pitch, yaw)
        # body rates from Euler rates (pitch = 0): p = roll', q = yaw' sin(roll), r = yaw' cos(roll)
        droll = np.gradient(roll, dt)
        dyaw = np.gradient(yaw, dt)
        rates = np.stack([droll, dyaw * np.sin(roll), dyaw * np.cos(roll)], axis=1)
    current = np.zeros(n)
    mag, gyro, accel, interf = _sensors_common(cfg, rng, t, dcm, rates, np.zeros((n, 3)), current)
    # autopilot estimate: roll/pitch near truth, yaw from its field-vector filter on corrected mag
    est_roll = roll + rng.normal(0, 0.002, n)
    est_pitch = pitch + rng.normal(0, 0.002, n)
    m_cor = _autopilot_corrected_field(cfg, mag, np.zeros((n, 3)))
    dts = np.diff(t, prepend=t[0])
    reinit = np.zeros(n, bool)
    reinit[0] = True
    hb = run_vector_filter(dts, gyro, m_cor, np.ones(n, bool), reinit, cfg.autopilot_mag_gain_per_s)
    est_yaw = wrap_angle_rad(tilt_compensated_heading_rad(hb, est_roll, est_pitch) + math.radians(cfg.declination_deg))
    pos = np.zeros((n, 3))
    pos[:, 2] = -1.0   # held about 1 m above the ground
    vel = np.zeros((n, 3))
    gidx, _, gerr, gverr, gfix = _gps_errors(cfg, rng, n)
    gpos, gvel = pos[gidx] + gerr, vel[gidx] + gverr
    return SimResult(t, roll, pitch, yaw, est_roll, est_pitch, est_yaw, gyro, accel, mag, rates,
                     pos, vel, pos.copy(), vel.copy(), interf, current, gidx, gpos, gvel, gfix,
                     np.full(n, np.nan), None, events)


def _add_after_loop(cfg: SimConfig, res_t: np.ndarray, current_A: np.ndarray, mag_raw_mG: np.ndarray,
                    interf_mG: np.ndarray, pos_ned_m: np.ndarray, att_true: np.ndarray) -> None:
    """The payload's current and field and the ground anomaly's field, in place (``disturbances``):
    the body fields go through the sensor model A like the motor field.  A payload on its own lead
    and the anomaly count as interference (``interf_mG``, sensor frame); a payload in the motor
    wires does not (its field is the motor's c·ΔI)."""
    extra_body = np.zeros_like(mag_raw_mG)
    foreign_body = np.zeros_like(mag_raw_mG)
    if cfg.payload is not None and cfg.payload.current_A:
        current_A += payload_current_A(cfg.payload, res_t)
        f = payload_field_body_mG(cfg.payload, res_t, cfg.mag.motor_mG_per_A)
        if cfg.payload.mG_per_A is None:
            extra_body += f
        else:
            foreign_body += f
    if cfg.anomaly is not None:
        foreign_body += anomaly_field_body_mG(cfg.anomaly, pos_ned_m, att_true[:, 0], att_true[:, 1], att_true[:, 2])
    mag_raw_mG += (extra_body + foreign_body) @ cfg.mag.matrix.T
    interf_mG += foreign_body @ cfg.mag.matrix.T


def _mission_profile(cfg: SimConfig):
    """Legs A->B->A->... at cfg.speed until the duration; returns a function t -> (s_target, v_ff, leg)."""
    v, amax = cfg.speed_mps, 1.0
    t_acc = v / amax
    leg_t = cfg.leg_length_m / v + t_acc          # trapezoid duration
    turn_t = 8.0                                   # hover + yaw turn at the leg ends
    legs = []
    t = cfg.hover_s
    while t + leg_t <= cfg.duration_s - 2.0:
        legs.append((t, t + leg_t))
        t += leg_t + turn_t
    return legs, leg_t, t_acc


def _mission_targets(cfg: SimConfig, t: np.ndarray):
    """Per-step target along-track position, feed-forward speed along the line (sign per leg) and
    commanded yaw (face along the leg from its start until the next leg)."""
    brg = math.radians(cfg.leg_bearing_deg)
    legs, leg_t, t_acc = _mission_profile(cfg)
    v, amax = cfg.speed_mps, 1.0
    n = len(t)
    s_tgt = np.zeros(n)
    v_ff = np.zeros(n)
    yaw_cmd = np.full(n, brg)
    for k, (t0, t1) in enumerate(legs):
        direction = 1.0 if k % 2 == 0 else -1.0
        tau = np.clip(t - t0, 0, leg_t)
        # trapezoid distance covered
        dist = np.where(tau < t_acc, 0.5 * amax * tau ** 2,
                        np.where(tau < leg_t - t_acc, 0.5 * amax * t_acc ** 2 + v * (tau - t_acc),
                                 cfg.leg_length_m - 0.5 * amax * (leg_t - tau) ** 2))
        spd = np.where(tau < t_acc, amax * tau, np.where(tau < leg_t - t_acc, v, amax * (leg_t - tau)))
        sel = t >= t0
        start = 0.0 if direction > 0 else cfg.leg_length_m
        s_tgt[sel] = start + direction * dist[sel]
        v_ff[sel] = np.where((t[sel] <= t1), direction * spd[sel], 0.0)
        yaw_cmd[sel] = brg if direction > 0 else _wrap(brg + math.pi)
    if cfg.yaw_sweep_deg_s:
        yaw_cmd = wrap_angle_rad(yaw_cmd + math.radians(cfg.yaw_sweep_deg_s) * np.maximum(t - cfg.hover_s, 0.0))
    return legs, s_tgt, v_ff, yaw_cmd


def _run_mission(cfg: SimConfig, rng) -> SimResult:
    """The closed-loop mission (``mission_loop.MissionLoop``) on prepared targets and noise."""
    dt = 1.0 / cfg.rate_hz
    n = int(round(cfg.duration_s * cfg.rate_hz))
    t = np.arange(n) * dt
    brg = math.radians(cfg.leg_bearing_deg)
    u = np.array([math.cos(brg), math.sin(brg)])
    legs, s_tgt, v_ff, yaw_cmd = _mission_targets(cfg, t)
    wind = np.asarray(cfg.mean_wind_mps)[None, :] + _gauss_markov(rng, n, dt, cfg.gust_sigma_mps, cfg.gust_tau_s, 2)
    wz = _gauss_markov(rng, n, dt, cfg.vertical_gust_sigma_mps2, 0.5, 1)[:, 0]
    gps_idx, gps_step, gerr, gverr, gfix = _gps_errors(cfg, rng, n)
    gps_valid_step = np.zeros(n, bool)
    gps_valid_step[gps_idx[gfix >= 3]] = True
    gps_row = np.full(n, -1)
    gps_row[gps_idx] = np.arange(len(gps_idx))
    gyro_noise = rng.normal(0, cfg.gyro_noise_rad_s, (n, 3)) + cfg.gyro_bias_rad_s
    mag_noise = rng.normal(0, cfg.mag.noise_mG, (n, 3))
    acc_noise = rng.normal(0, cfg.accel_noise_mps2, (n, 3))
    att_noise = rng.normal(0, 0.002, (n, 2))
    interf = cfg.interference.field_sensor_mG(t)
    inputs = {"s_target": s_tgt.tolist(), "v_ff": v_ff.tolist(), "yaw_cmd": yaw_cmd.tolist(),
              "wind": wind.tolist(), "wind_z": wz.tolist(), "acc_noise": acc_noise.tolist(),
              "mag_noise": mag_noise.tolist(), "gyro_noise": gyro_noise.tolist(),
              "att_noise": att_noise.tolist(), "interference": interf.tolist(),
              "gps_valid": gps_valid_step.tolist(), "gps_row": gps_row.tolist(),
              "gps_err": gerr, "gps_vel_err": gverr, "gps_dt": gps_step * dt,
              "u": (float(u[0]), float(u[1]))}
    loop = MissionLoop(cfg, inputs, n).run()
    out, out_att = loop.out, loop.out_att
    pos, vel = out["pos"], out["vel"]
    interf = interf.copy()
    _add_after_loop(cfg, t, loop.current, out["mag"], interf, pos, out_att)
    d = np.abs(pos[:, 0] * u[1] - pos[:, 1] * u[0])          # distance from the line through A = origin
    gpos = pos[gps_idx] + gerr
    gvel = vel[gps_idx] + gverr
    alt = loop.alt
    b_pt = cfg.leg_length_m * u
    mission = np.array([[0.0, 0.0, alt], [b_pt[0], b_pt[1], alt]])
    events = [{"kind": "leg", "start_s": round(a, 3), "end_s": round(b, 3)} for a, b in legs]
    return SimResult(t, out_att[:, 0], out_att[:, 1], out_att[:, 2], out_att[:, 3], out_att[:, 4], out_att[:, 5],
                     out["gyro"], out["acc"], out["mag"], out["rates"], pos, vel, out["epos"], out["evel"], interf,
                     loop.current, gps_idx, gpos, gvel, gfix, d, mission, events)
