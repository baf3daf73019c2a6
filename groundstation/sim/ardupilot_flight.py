"""Flight and sensor truth for the ArduPilot-realistic simulator (pure numpy, no MAVLink, no files).

Timeline (seconds from the log start, on the ``log_rate_hz`` grid):
  ground (level, disarmed) → handheld calibration dance (random smooth rotations covering the
  sphere, motors off) → back on the ground → take-off → a polygon mission (one heading per leg,
  45 °/s yaw turns at the corners, the vehicle facing its track, altitude changed on every other
  leg) → descent and landing.

Per compass k (sensor frame s, rotated-raw frame r as ArduPilot's rotate_field gives it):
    m_s = A_k R_mount_kᵀ (h_body + f_k I) + b_k + noise,    m_r = R_param_k m_s
with h_body = C_bnᵀ H_ned (WMM), f_k the motor field per ampere (body frame) and I the battery
current.  The attitude the autopilot reports: roll/pitch with 0.2° noise; yaw either from compass 0
(its corrected field, tilt compensated, declination added, low-passed like an EKF heading
(``yaw_source`` "compass")) or the true yaw with 0.3° noise ("independent", e.g. GPS yaw).
Units: m, m/s, rad, mG, A.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.rotations import dcm_body_to_ned, euler_from_dcm, rotation_from_vector_rad, wrap_angle_rad

__all__ = ["FlightPlan", "FlightTruth", "fly", "G_MPS2"]

G_MPS2 = 9.80665


@dataclass(frozen=True)
class FlightPlan:
    log_rate_hz: float = 10.0
    ground_s: float = 20.0
    dance: bool = True
    dance_s: float = 30.0
    dance_rate_deg_s: float = 80.0
    settle_s: float = 20.0
    legs: int = 5
    first_bearing_deg: float = 20.0
    leg_length_m: float = 220.0
    speed_mps: float = 8.0
    cruise_alt_m: float = 30.0
    high_alt_m: float = 60.0
    climb_rate_mps: float = 2.0
    turn_rate_deg_s: float = 45.0
    corner_hover_s: float = 3.0
    wind_ne_mps: tuple[float, float] = (2.0, -1.0)
    drag_per_s: float = 0.3
    hover_current_A: float = 16.0
    ground_current_A: float = 0.4
    climb_current_A_per_mps: float = 4.0


@dataclass
class FlightTruth:
    t_s: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    current_A: np.ndarray
    throttle: np.ndarray
    armed: np.ndarray
    events: dict = field(default_factory=dict)     # name -> [start_s, end_s]

    def dcm(self) -> np.ndarray:
        return dcm_body_to_ned(self.roll_rad, self.pitch_rad, self.yaw_rad)


def _dance(n: int, dt: float, rate_rad_s: float, rng: np.random.Generator, R0: np.ndarray) -> np.ndarray:
    """(n,3,3) body->NED DCMs of a handheld dance: angular velocity of constant magnitude whose
    axis wanders smoothly (new random axis every 2 s, blended)."""
    axes = rng.normal(size=(max(2, int(n * dt / 2.0) + 2), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    out = np.empty((n, 3, 3))
    R = R0.copy()
    for i in range(n):
        x = i * dt / 2.0
        k = int(x)
        a = axes[k] * (1 - (x - k)) + axes[k + 1] * (x - k)
        out[i] = R
        R = R @ rotation_from_vector_rad(a / np.linalg.norm(a) * rate_rad_s * dt)
    return out


def _mission_keys(p: FlightPlan, t0: float) -> tuple[list[tuple], dict]:
    """Keyframes (t, yaw_rad, speed_mps, climb_mps) of take-off, legs, turns, landing."""
    keys, ev = [], {}
    brg = math.radians(p.first_bearing_deg)
    t = t0
    keys.append((t, brg, 0.0, 0.0))
    climb_s = p.cruise_alt_m / p.climb_rate_mps
    keys += [(t + 1.0, brg, 0.0, p.climb_rate_mps), (t + climb_s, brg, 0.0, p.climb_rate_mps),
             (t + climb_s + 1.0, brg, 0.0, 0.0)]
    t += climb_s + 1.0
    ev["takeoff"] = [t0, t]
    acc_s = 3.0
    cruise_s = p.leg_length_m / p.speed_mps - acc_s
    alt = p.cruise_alt_m
    for k in range(p.legs):
        b = brg + k * 2 * math.pi / p.legs
        if k:
            turn_s = math.degrees(2 * math.pi / p.legs) / p.turn_rate_deg_s
            keys += [(t + p.corner_hover_s, b - 2 * math.pi / p.legs, 0.0, 0.0), (t + p.corner_hover_s + turn_s, b, 0.0, 0.0)]
            t += p.corner_hover_s + turn_s + 1.0
        target = p.high_alt_m if k % 2 == 0 else p.cruise_alt_m
        climb = (target - alt) / max(cruise_s, 1.0)
        keys += [(t, b, 0.0, 0.0), (t + acc_s, b, p.speed_mps, climb), (t + acc_s + cruise_s, b, p.speed_mps, climb),
                 (t + 2 * acc_s + cruise_s, b, 0.0, 0.0)]
        ev.setdefault("legs", []).append([t, t + 2 * acc_s + cruise_s])
        t += 2 * acc_s + cruise_s
        alt = target
    land_s = alt / 1.5
    keys += [(t + 2.0, keys[-1][1], 0.0, -1.5), (t + 2.0 + land_s, keys[-1][1], 0.0, -1.5),
             (t + 3.0 + land_s, keys[-1][1], 0.0, 0.0)]
    ev["landing"] = [t, t + 3.0 + land_s]
    return keys, ev


def _interp_keys(keys: list[tuple], t: np.ndarray) -> np.ndarray:
    """Smoothstep interpolation between keyframes -> (len(t), 3): yaw, speed, climb."""
    kt = np.array([k[0] for k in keys])
    kv = np.array([k[1:] for k in keys])
    j = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
    span = np.maximum(kt[j + 1] - kt[j], 1e-9)
    x = np.clip((t - kt[j]) / span, 0, 1)
    s = x * x * (3 - 2 * x)
    return kv[j] + (kv[j + 1] - kv[j]) * s[:, None]


def _lowpass(x: np.ndarray, dt: float, tau_s: float) -> np.ndarray:
    a = 1.0 - math.exp(-dt / tau_s)
    out = np.empty_like(x)
    acc = x[0]
    for i, v in enumerate(x):
        acc = acc + a * (v - acc)
        out[i] = acc
    return out


def _flight_attitude(p: FlightPlan, t: np.ndarray, ys: np.ndarray, dt: float, rng) -> tuple:
    """Yaw, tilt, velocity, current and throttle of the flying part from the keyframe track."""
    yaw, speed, climb = ys[:, 0], ys[:, 1], ys[:, 2]
    vel = np.column_stack([speed * np.cos(yaw), speed * np.sin(yaw), -climb])
    acc = np.gradient(vel, dt, axis=0)
    air = vel[:, :2] - np.asarray(p.wind_ne_mps)[None, :]
    need = acc[:, :2] + p.drag_per_s * air                   # horizontal force per mass from the thrust
    fwd = need[:, 0] * np.cos(yaw) + need[:, 1] * np.sin(yaw)
    right = -need[:, 0] * np.sin(yaw) + need[:, 1] * np.cos(yaw)
    turb = _lowpass(rng.normal(0, math.radians(1.5), (len(t), 2)), dt, 0.5)
    pitch = -np.arctan2(fwd, G_MPS2) + turb[:, 0]
    roll = np.arctan2(right * np.cos(pitch), G_MPS2) + turb[:, 1]
    thrust_g = (1.0 - acc[:, 2] / G_MPS2) / (np.cos(roll) * np.cos(pitch))
    current = p.hover_current_A * thrust_g ** 1.5 + p.climb_current_A_per_mps * climb + rng.normal(0, 0.3, len(t))
    throttle = np.clip(0.38 * thrust_g + 0.02 * climb, 0.0, 1.0)
    return roll, pitch, wrap_angle_rad(yaw), vel, np.maximum(current, 0.5), throttle


def fly(p: FlightPlan, rng: np.random.Generator) -> FlightTruth:
    """The whole log's truth on the log-rate grid."""
    dt = 1.0 / p.log_rate_hz
    yaw0 = math.radians(p.first_bearing_deg)
    R0 = dcm_body_to_ned(0.0, 0.0, yaw0)
    parts_R, events = [], {}
    n_ground = int(round(p.ground_s / dt))
    parts_R.append(np.repeat(R0[None], n_ground, axis=0))
    t_cursor = n_ground * dt
    if p.dance:
        n_d = int(round(p.dance_s / dt))
        parts_R.append(_dance(n_d, dt, math.radians(p.dance_rate_deg_s), rng, R0))
        events["dance"] = [t_cursor, t_cursor + n_d * dt]
        t_cursor += n_d * dt
    n_settle = int(round(p.settle_s / dt))
    parts_R.append(np.repeat(R0[None], n_settle, axis=0))
    t_cursor += n_settle * dt
    ground_R = np.concatenate(parts_R)
    roll_g, pitch_g, yaw_g = euler_from_dcm(ground_R)
    keys, ev = _mission_keys(p, t_cursor)
    events.update(ev)
    t_f = t_cursor + np.arange(int(round((keys[-1][0] - t_cursor) / dt)) + int(5 / dt)) * dt
    roll_f, pitch_f, yaw_f, vel_f, cur_f, thr_f = _flight_attitude(p, t_f, _interp_keys(keys, t_f), dt, rng)
    n_g = len(ground_R)
    t = np.arange(n_g + len(t_f)) * dt
    vel = np.vstack([np.zeros((n_g, 3)), vel_f])
    pos = np.cumsum(vel, axis=0) * dt
    pos[:, 2] = np.minimum(pos[:, 2], 0.0)
    current = np.concatenate([p.ground_current_A + rng.normal(0, 0.05, n_g), cur_f])
    on_ground = np.concatenate([np.ones(n_g, bool), pos[n_g:, 2] > -0.05])
    current[n_g:][on_ground[n_g:]] = p.ground_current_A
    throttle = np.concatenate([np.zeros(n_g), thr_f])
    events["flight"] = [float(t_cursor), float(t[-1])]
    return FlightTruth(t, np.concatenate([roll_g, roll_f]), np.concatenate([pitch_g, pitch_f]),
                       np.concatenate([yaw_g, yaw_f]), pos, vel, current, throttle, ~on_ground, events)


def autopilot_attitude(truth: FlightTruth, compass0_corrected_mG: np.ndarray, declination_rad: float,
                       yaw_source: str, rng: np.random.Generator, tau_s: float = 2.0) -> np.ndarray:
    """(N,3) roll, pitch, yaw the autopilot reports.  yaw_source "compass": yaw = true yaw + the
    low-passed error of compass 0's tilt-compensated heading (an EKF heading in steady state);
    "independent": true yaw + 0.3° noise."""
    n = len(truth.t_s)
    dt = float(truth.t_s[1] - truth.t_s[0])
    roll = truth.roll_rad + rng.normal(0, math.radians(0.2), n)
    pitch = truth.pitch_rad + rng.normal(0, math.radians(0.2), n)
    if yaw_source == "independent":
        return np.column_stack([roll, pitch, wrap_angle_rad(truth.yaw_rad + rng.normal(0, math.radians(0.3), n))])
    T = dcm_body_to_ned(roll, pitch, np.zeros(n))
    lv = np.einsum("nij,nj->ni", T, compass0_corrected_mG)
    psi_c = np.arctan2(-lv[:, 1], lv[:, 0]) + declination_rad
    err = _lowpass(np.unwrap(wrap_angle_rad(psi_c - truth.yaw_rad)), dt, tau_s)
    return np.column_stack([roll, pitch, wrap_angle_rad(truth.yaw_rad + err)])
