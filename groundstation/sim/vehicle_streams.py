"""MAVLink streams of a vehicle with up to three compasses, built from a known attitude history.

What an ArduPilot multirotor sends about its sensors: RAW_IMU (IMU 0 + compass 0), SCALED_IMU2
(compass 1) and SCALED_IMU3 (compass 2), ATTITUDE, GPS_RAW_INT and SYSTEM_TIME.  Each compass has
its own hard iron, soft iron, noise and *mounting rotation* (an ArduPilot ``Rotation`` enum:
the sensor reads s = R_mountᵀ · m_body, so a compass mounted at ROTATION_YAW_90 whose
COMPASS_ORIENT still says 0 reports a field turned by 90°).

The mag fields of the IMU messages carry the **raw sensor-frame** reading (``msg.raw_mag_mG``
holds the unrounded value); ``groundstation.sim.fake_vehicle.FakeVehicle`` applies the
vehicle's own calibration parameters (COMPASS_ORIENT/OFS/DIA/ODI or PX4 CAL_MAGn_*) to them at
send time, as the autopilot does, so a parameter write changes what the station receives.

Attitude histories: ``dance_attitude`` (the simulator's X/Y/Z turns and tumble), ``hold_attitude``
(held still at a heading, hand wobble), ``walk_attitude`` (carried level along a straight line),
``attitude_from_rates`` (any sequence of body rates).  ``pack_stream`` turns one into messages.
Units: rad, rad/s, mG, m; body FRD, NED.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.rotations import dcm_body_to_ned, euler_from_dcm, rotation_from_vector_rad
from groundstation.io.mavlink import mavlink2
from groundstation.io.params import rotation_enum_matrix
from groundstation.sim.scenarios import ORIGIN as SCENARIO_ORIGIN, START_UNIX_S, simulate

__all__ = ["FakeCompass", "Hardware", "AttitudeHistory", "three_compasses", "make_hardware",
           "attitude_from_rates", "attitude_from_moves", "guided_dance_attitude", "dance_attitude", "TILTS", "MORE_TILTS", "hold_attitude", "walk_attitude", "pack_stream",
           "COMPASS_MESSAGES", "ROTATION_YAW_90", "ROTATION_ROLL_180"]

ROTATION_YAW_90 = 2
ROTATION_ROLL_180 = 8
G_MPS2 = 9.80665
ORIGIN = (SCENARIO_ORIGIN[0], SCENARIO_ORIGIN[1], SCENARIO_ORIGIN[2] + 1.0)   # held 1 m above ground
COMPASS_MESSAGES = {"RAW_IMU": 0, "SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}


@dataclass(frozen=True)
class FakeCompass:
    """One magnetometer: s = A · R_mountᵀ · m_body + offsets + noise (sensor frame, mG)."""
    mount_rotation: int = 0
    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    offsets_mG: np.ndarray = field(default_factory=lambda: np.zeros(3))
    noise_mG: float = 1.5

    def reading_mG(self, field_body_mG: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        r = rotation_enum_matrix(self.mount_rotation)
        s = field_body_mG @ r              # rows: R_mountᵀ m  (m @ R == (Rᵀ m)ᵀ)
        return s @ np.asarray(self.matrix).T + np.asarray(self.offsets_mG) + rng.normal(0, self.noise_mG, s.shape)


@dataclass(frozen=True)
class Hardware:
    """The vehicle's compasses and where it is (the Earth field there, from the WMM)."""
    compasses: tuple[FakeCompass, ...]
    field_ned_mG: np.ndarray
    declination_deg: float
    origin: tuple[float, float, float] = ORIGIN


def three_compasses(mounts: tuple[int, int, int] = (0, 0, 0)) -> tuple[FakeCompass, ...]:
    """Three compasses with different errors: an external one (small soft iron, low noise) and
    two internal ones (larger hard and soft iron, noisier)."""
    a0 = np.array([[1.03, 0.02, 0.0], [0.02, 0.97, -0.01], [0.0, -0.01, 1.01]])
    a1 = np.array([[0.92, 0.04, 0.02], [0.04, 1.06, 0.03], [0.02, 0.03, 0.98]])
    a2 = np.array([[1.08, -0.03, 0.01], [-0.03, 1.0, 0.05], [0.01, 0.05, 0.94]])
    return (FakeCompass(mounts[0], a0, np.array([120.0, -80.0, 45.0]), 1.5),
            FakeCompass(mounts[1], a1, np.array([-210.0, 150.0, -300.0]), 3.0),
            FakeCompass(mounts[2], a2, np.array([60.0, 250.0, 100.0]), 2.5))


def make_hardware(compasses: tuple[FakeCompass, ...] | None = None, origin=ORIGIN) -> Hardware:
    ef = earth_field(origin[0], origin[1], origin[2], decimal_year_from_unix(START_UNIX_S))
    return Hardware(compasses or three_compasses(), np.array(ef.field_ned_mG), ef.declination_deg, origin)


@dataclass
class AttitudeHistory:
    """Truth on a fixed-rate grid: time, attitude (ZYX Euler, rad) and position (NED m from origin)."""
    t_s: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    pos_ned_m: np.ndarray | None = None

    @property
    def rate_hz(self) -> float:
        return 1.0 / float(self.t_s[1] - self.t_s[0])

    def every(self, n: int) -> "AttitudeHistory":
        """Every n-th row (a lower telemetry rate)."""
        pos = None if self.pos_ned_m is None else self.pos_ned_m[::n]
        return AttitudeHistory(self.t_s[::n], self.roll_rad[::n], self.pitch_rad[::n], self.yaw_rad[::n], pos)

    def then(self, other: "AttitudeHistory") -> "AttitudeHistory":
        """This history followed by ``other`` (same rate; positions zero where not given)."""
        dt = 1.0 / self.rate_hz
        pos = [h.pos_ned_m if h.pos_ned_m is not None else np.zeros((len(h.t_s), 3)) for h in (self, other)]
        pos[1] = pos[1] + pos[0][-1]          # it goes on from where this one ended
        return AttitudeHistory(np.concatenate([self.t_s, self.t_s[-1] + dt + other.t_s - other.t_s[0]]),
                               np.concatenate([self.roll_rad, other.roll_rad]),
                               np.concatenate([self.pitch_rad, other.pitch_rad]),
                               np.concatenate([self.yaw_rad, other.yaw_rad]), np.vstack(pos))


def attitude_from_rates(rates_rad_s: np.ndarray, rate_hz: float = 50.0,
                        start_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> AttitudeHistory:
    """Integrate body rates (N, 3) from a start attitude (exact rotation per step)."""
    dt = 1.0 / rate_hz
    r = dcm_body_to_ned(*start_rpy_rad)
    dcm = np.empty((len(rates_rad_s), 3, 3))
    for i, w in enumerate(np.asarray(rates_rad_s, float)):
        dcm[i] = r
        r = r @ rotation_from_vector_rad(w * dt)
    roll, pitch, yaw = euler_from_dcm(dcm)
    return AttitudeHistory(np.arange(len(dcm)) * dt, roll, pitch, yaw)


def attitude_from_moves(moves: list[tuple], rate_hz: float = 50.0, start_yaw_deg: float = 30.0) -> AttitudeHistory:
    """A hand-held sequence of moves from level at ``start_yaw_deg``:
    ("still", seconds) | ("body", axis 0/1/2, angle_deg, rate_deg_s) — about a body axis |
    ("vertical", angle_deg, rate_deg_s) — about the NED vertical (a turn while tilted)."""
    dt = 1.0 / rate_hz
    r = dcm_body_to_ned(0.0, 0.0, math.radians(start_yaw_deg))
    out = []
    for move in moves:
        if move[0] == "still":
            out += [r] * int(round(move[1] * rate_hz))
            continue
        angle, rate = move[-2], move[-1]
        n = max(1, int(round(abs(angle) / rate * rate_hz)))
        step = math.radians(angle) / n
        for _ in range(n):
            out.append(r)
            if move[0] == "body":
                v = np.zeros(3)
                v[move[1]] = step
                r = r @ rotation_from_vector_rad(v)
            else:
                r = rotation_from_vector_rad((0.0, 0.0, step)) @ r
    out.append(r)
    roll, pitch, yaw = euler_from_dcm(np.asarray(out))
    return AttitudeHistory(np.arange(len(out)) * dt, roll, pitch, yaw)


TILTS = ((1, -45.0), (0, 45.0), (0, 180.0), (1, 45.0), (0, -60.0), (1, -80.0))
MORE_TILTS = ((0, 90.0), (0, -90.0), (1, 80.0), (0, 135.0), (0, -135.0), (1, -20.0), (0, 20.0))


def guided_dance_attitude(rate_deg_s: float = 35.0, rate_hz: float = 25.0, turn_deg: float = 370.0,
                          tilts: tuple = TILTS) -> AttitudeHistory:
    """What an operator following the wizard does: full turns about X, Y, Z, then turns about the
    vertical with the nose down, a side down, upside down and the nose up (``tilts``: (body axis,
    angle) of each tilted pose; ``TILTS + MORE_TILTS`` keeps going as for an onboard calibrator)."""
    w = rate_deg_s
    moves: list[tuple] = [("still", 3.0), ("body", 0, turn_deg, w), ("still", 1.0), ("body", 1, turn_deg, w),
                          ("still", 1.0), ("body", 2, turn_deg, w), ("still", 1.0)]
    for axis, tilt in tilts:
        moves += [("body", axis, tilt, w), ("vertical", 360.0, w), ("body", axis, -tilt, w)]
    moves.append(("still", 2.0))
    return attitude_from_moves(moves, rate_hz)


def dance_attitude(seed: int = 0, **overrides) -> AttitudeHistory:
    """The calibration dance of ``simulate("calibration", seed)``: X, Y, Z turns then a tumble."""
    r = simulate("calibration", seed, **overrides).result
    return AttitudeHistory(r.t_s, r.roll_rad, r.pitch_rad, r.yaw_rad)


def hold_attitude(heading_deg: float, duration_s: float, rate_hz: float = 50.0, wobble_deg: float = 0.8,
                  seed: int = 0) -> AttitudeHistory:
    """Held still (by hand or on the ground) at a true heading, with a slow small wobble."""
    t = np.arange(int(duration_s * rate_hz)) / rate_hz
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * np.pi, 3)
    w = np.radians(wobble_deg)
    return AttitudeHistory(t, w * np.sin(0.7 * t + ph[0]), w * np.sin(0.5 * t + ph[1]),
                           math.radians(heading_deg) + 0.5 * w * np.sin(0.3 * t + ph[2]))


def walk_attitude(course_deg: float, duration_s: float, speed_mps: float = 1.4, rate_hz: float = 50.0,
                  seed: int = 0) -> AttitudeHistory:
    """Carried level, nose along a straight walk on ``course_deg`` at ``speed_mps``."""
    h = hold_attitude(course_deg, duration_s, rate_hz, wobble_deg=1.5, seed=seed)
    c = math.radians(course_deg)
    s = speed_mps * h.t_s
    h.pos_ned_m = np.stack([s * math.cos(c), s * math.sin(c), np.zeros_like(s)], axis=1)
    return h


def _body_rates(dcm: np.ndarray, dt: float) -> np.ndarray:
    """Body rates over each step from consecutive DCMs (small-angle vee of Rᵢᵀ Rᵢ₊₁)."""
    rel = np.einsum("nji,njk->nik", dcm[:-1], dcm[1:])
    w = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1) / (2 * dt)
    return np.vstack([w, w[-1:]])


def _i16(x) -> int:
    return int(max(-32767, min(32767, round(float(x)))))


def pack_stream(history: AttitudeHistory, hardware: Hardware, *, start_unix: float = START_UNIX_S,
                boot_offset_s: float = 12.0, seed: int = 0, gps_rate_hz: float = 10.0) -> list:
    """Time-ordered [(unix_s, message)] of the history as the vehicle would send it."""
    rng = np.random.default_rng([seed, 3])
    h = history
    n, dt = len(h.t_s), 1.0 / h.rate_hz
    dcm = dcm_body_to_ned(h.roll_rad, h.pitch_rad, h.yaw_rad)
    gyro = _body_rates(dcm, dt) + rng.normal(0, 0.003, (n, 3))
    accel = np.einsum("nji,j->ni", dcm, [0.0, 0.0, -G_MPS2]) + rng.normal(0, 0.05, (n, 3))
    field_body = np.einsum("nji,j->ni", dcm, hardware.field_ned_mG)
    mags = [c.reading_mG(field_body, rng) for c in hardware.compasses]
    pos = h.pos_ned_m if h.pos_ned_m is not None else np.zeros((n, 3))
    vel = np.gradient(pos, dt, axis=0)
    out: list = []
    kinds = (mavlink2.MAVLink_raw_imu_message, mavlink2.MAVLink_scaled_imu2_message, mavlink2.MAVLink_scaled_imu3_message)
    for i in range(n):
        u = start_unix + h.t_s[i]
        boot_ms = int(round((h.t_s[i] + boot_offset_s) * 1000))
        acc = [_i16(a / G_MPS2 * 1000) for a in accel[i]]
        gy = [_i16(g * 1000) for g in gyro[i]]
        for k, mag in enumerate(mags[:3]):
            m = [_i16(v) for v in mag[i]]
            first = (boot_ms * 1000,) if k == 0 else (boot_ms,)
            tail = (0, 3500) if k == 0 else (3500,)
            msg = kinds[k](*first, *acc, *gy, *m, *tail)
            msg.raw_mag_mG = tuple(float(v) for v in mag[i])
            out.append((u + 1e-5 * k, msg))
        out.append((u + 1e-4, mavlink2.MAVLink_attitude_message(
            boot_ms, float(h.roll_rad[i]), float(h.pitch_rad[i]), float(h.yaw_rad[i]), *map(float, gyro[i]))))
    out += _gps_messages(h, hardware, pos, vel, start_unix, boot_offset_s, gps_rate_hz, rng)
    out.sort(key=lambda x: x[0])
    return out


def _gps_messages(h: AttitudeHistory, hardware: Hardware, pos, vel, start_unix, boot_offset_s, gps_rate_hz, rng):
    lat0, lon0, alt0 = hardware.origin
    step = max(1, int(round(h.rate_hz / gps_rate_hz)))
    out = []
    for i in range(0, len(h.t_s), step):
        u = start_unix + h.t_s[i] + 5e-4
        n_m, e_m = pos[i, 0] + rng.normal(0, 0.02), pos[i, 1] + rng.normal(0, 0.02)
        lat = lat0 + math.degrees(n_m / 6378137.0)
        lon = lon0 + math.degrees(e_m / (6378137.0 * math.cos(math.radians(lat0))))
        speed = math.hypot(vel[i, 0], vel[i, 1])
        cog = (math.degrees(math.atan2(vel[i, 1], vel[i, 0])) % 360.0) if speed > 0.2 else 0.0
        boot_us = int((h.t_s[i] + boot_offset_s) * 1e6)
        out.append((u, mavlink2.MAVLink_gps_raw_int_message(
            boot_us, 6, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((alt0 - pos[i, 2]) * 1000)),
            2, 4, int(round(speed * 100)), int(round(cog * 100)) % 36000, 22)))
        if i % int(h.rate_hz) == 0:
            out.append((u + 1e-4, mavlink2.MAVLink_system_time_message(int(round(u * 1e6)), int(boot_us / 1000))))
    return out
