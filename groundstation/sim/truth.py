"""Small truth generators for estimator tests and benchmarks (no MAVLink, no files).

* ``simulate_manoeuvring_flight`` — IMU/GPS/magnetometer of a smooth manoeuvring flight with
  known attitude, gyro bias and GPS outage (used against ``estimators.ins_gps``).
* ``simulate_ellipsoid_samples`` — raw magnetometer samples m_raw = A·m_body + b + noise with
  known A and b (used against ``estimators.calibration``).
* ``random_rotation`` — a uniform random rotation, or one of bounded angle.

Units: m, m/s, m/s², rad, rad/s, mG; body FRD, navigation NED.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.ins_gps import GRAVITY_MPS2
from estimators.rotations import dcm_body_to_ned, rotation_from_vector_rad

__all__ = ["FlightTruth", "simulate_manoeuvring_flight", "simulate_ellipsoid_samples", "random_rotation"]


@dataclass
class FlightTruth:
    imu: np.ndarray        # (N,7) measured
    gps_ned: np.ndarray    # (G,7) measured, rows inside the outage removed
    mag: np.ndarray        # (M,4) measured (calibrated: no hard/soft iron)
    t_s: np.ndarray        # truth on the IMU time base
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    field_ned_mG: np.ndarray
    outage: tuple[float, float] | None


def _euler_and_rates(t):
    """Smooth manoeuvring attitude (rad) and its time derivative."""
    roll = 0.25 * np.sin(0.13 * t + 0.5) + 0.10 * np.sin(0.37 * t)
    droll = 0.25 * 0.13 * np.cos(0.13 * t + 0.5) + 0.10 * 0.37 * np.cos(0.37 * t)
    pitch = 0.15 * np.sin(0.09 * t) + 0.08 * np.sin(0.29 * t + 1.0)
    dpitch = 0.15 * 0.09 * np.cos(0.09 * t) + 0.08 * 0.29 * np.cos(0.29 * t + 1.0)
    yaw = 1.0 + 1.5 * np.sin(0.04 * t) + 0.8 * np.sin(0.11 * t)
    dyaw = 1.5 * 0.04 * np.cos(0.04 * t) + 0.8 * 0.11 * np.cos(0.11 * t)
    return roll, pitch, yaw, droll, dpitch, dyaw


def _trajectory(t, scale: float = 1.0):
    """Position, velocity, acceleration (NED) of a smooth manoeuvring path (amplitudes × scale)."""
    comps = [((300.0, 0.02, 0.0), (40.0, 0.10, 0.0)), ((200.0, 0.03, 1.0), (30.0, 0.13, 0.0)),
             ((5.0, 0.07, 0.0),)]
    p, v, a = (np.zeros((len(t), 3)) for _ in range(3))
    for i, terms in enumerate(comps):
        for amp, w, ph in terms:
            amp = amp * scale
            p[:, i] += amp * np.sin(w * t + ph)
            v[:, i] += amp * w * np.cos(w * t + ph)
            a[:, i] -= amp * w * w * np.sin(w * t + ph)
    p[:, 2] -= 50.0
    return p, v, a


def simulate_manoeuvring_flight(duration_s: float = 200.0, imu_rate_hz: float = 100.0,
                                gps_rate_hz: float = 5.0, mag_rate_hz: float = 50.0,
                                field_ned_mG=(200.0, 15.0, 440.0), outage: tuple[float, float] | None = None,
                                gyro_bias_rad_s=(0.0, 0.0, 0.0), outage_gyro_bias_rad_s=(0.0, 0.0, 0.0),
                                gyro_noise_rad_s: float = 0.003, accel_noise_mps2: float = 0.03,
                                mag_noise_mG: float = 1.5, gps_pos_sigma_m: float = 1.0,
                                gps_vel_sigma_mps: float = 0.1, path_scale: float = 1.0, seed: int = 0) -> FlightTruth:
    """Measured IMU/GPS/mag of a manoeuvring flight with known truth.

    IMU samples are the rates/specific force at the middle of each sample interval.
    ``outage_gyro_bias_rad_s`` is added to the gyro bias during the outage (an unmodelled bias
    change the Kalman filter has not seen).  GPS rows inside the outage are removed.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / imu_rate_hz
    t = np.arange(0.0, duration_s, dt)
    tm = np.maximum(t - 0.5 * dt, 0.0)
    r, p, y, dr, dp, dy = _euler_and_rates(tm)
    wx = dr - dy * np.sin(p)
    wy = dp * np.cos(r) + dy * np.cos(p) * np.sin(r)
    wz = -dp * np.sin(r) + dy * np.cos(p) * np.cos(r)
    C = dcm_body_to_ned(r, p, y)
    _, _, acc = _trajectory(tm, path_scale)
    f_n = acc - np.array([0.0, 0.0, GRAVITY_MPS2])
    f_b = np.einsum("nji,nj->ni", C, f_n)
    bias = np.broadcast_to(np.asarray(gyro_bias_rad_s, float), (len(t), 3)).copy()
    if outage is not None:
        inside = (t >= outage[0]) & (t < outage[1])
        bias[inside] += np.asarray(outage_gyro_bias_rad_s, float)
    imu = np.c_[t, np.c_[wx, wy, wz] + bias + rng.normal(0, gyro_noise_rad_s, (len(t), 3)),
                f_b + rng.normal(0, accel_noise_mps2, (len(t), 3))]
    rt, pt, yt, *_ = _euler_and_rates(t)
    Ct = dcm_body_to_ned(rt, pt, yt)
    pos, vel, _ = _trajectory(t, path_scale)
    h_n = np.asarray(field_ned_mG, float)
    step = int(round(imu_rate_hz / mag_rate_hz))
    mi = np.arange(0, len(t), step)
    mag = np.c_[t[mi], np.einsum("nji,j->ni", Ct[mi], h_n) + rng.normal(0, mag_noise_mG, (len(mi), 3))]
    gstep = int(round(imu_rate_hz / gps_rate_hz))
    gi = np.arange(0, len(t), gstep)
    gps = np.c_[t[gi], pos[gi] + rng.normal(0, gps_pos_sigma_m, (len(gi), 3)),
                vel[gi] + rng.normal(0, gps_vel_sigma_mps, (len(gi), 3))]
    if outage is not None:
        gps = gps[(gps[:, 0] < outage[0]) | (gps[:, 0] >= outage[1])]
    return FlightTruth(imu, gps, mag, t, rt, pt, np.mod(yt, 2 * np.pi), pos, vel, h_n, outage)


def random_rotation(rng: np.random.Generator, max_angle_rad: float | None = None) -> np.ndarray:
    """Uniform random rotation, or a random axis with angle U[0, max_angle_rad]."""
    if max_angle_rad is None:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return rotation_from_vector_rad(axis * rng.uniform(0, max_angle_rad))


def simulate_ellipsoid_samples(n: int, field_strength_mG: float, offsets_mG: np.ndarray, A: np.ndarray,
                               noise_sigma_mG: float, rng: np.random.Generator,
                               directions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Raw samples m_raw = A·m_body + b + noise with m_body = F·u, u uniform on the sphere
    (or the given unit ``directions`` (n, 3)).  Returns (m_raw (n, 3), m_body (n, 3))."""
    if directions is None:
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
    else:
        u = np.asarray(directions, float)
    body = field_strength_mG * u
    raw = body @ np.asarray(A, float).T + np.asarray(offsets_mG, float) + rng.normal(scale=noise_sigma_mG, size=body.shape)
    return raw, body
