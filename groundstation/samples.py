"""Typed sample stream shared by every source (logs, live links, simulator).

Internal units (converted once, at ingest, never again):
  magnetic field  mG (milligauss; 1 G = 1000 mG = 100 uT)
  angular rate    rad/s, body frame FRD
  acceleration    m/s^2, body frame FRD (specific force, as an accelerometer reads it)
  angles          rad (roll, pitch, yaw; yaw from north, clockwise, NED)
  position        lat/lon in degrees (WGS84), alt in metres (AMSL)
  velocity        m/s, NED
  time            t_s: seconds since the first timestamp of the source
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Union

import numpy as np


@dataclass(slots=True)
class MagSample:
    t_s: float
    mag_body_mG: tuple[float, float, float]
    instance: int = 0


@dataclass(slots=True)
class ImuSample:
    t_s: float
    gyro_rad_s: tuple[float, float, float]
    accel_mps2: tuple[float, float, float]
    instance: int = 0


@dataclass(slots=True)
class AttitudeSample:
    """The autopilot's own attitude estimate (not truth)."""
    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(slots=True)
class GpsSample:
    t_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    vel_ned_mps: tuple[float, float, float]  # NaN where the source does not give it
    fix_type: int  # MAVLink GPS_FIX_TYPE: 3 = 3D, 5 = RTK float, 6 = RTK fixed


@dataclass(slots=True)
class ParamSample:
    t_s: float
    name: str
    value: float


@dataclass(slots=True)
class MissionSample:
    """One mission waypoint (seq order) as lat/lon/alt."""
    t_s: float
    seq: int
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(slots=True)
class BatterySample:
    """Battery current [A] (SYS_STATUS current_battery): the motor current, whose magnetic field
    the magnetometer sees."""
    t_s: float
    current_A: float


@dataclass(slots=True)
class StatusSample:
    """Anything else worth showing: HEARTBEAT autopilot, STATUSTEXT, MAG_CAL_* ..."""
    t_s: float
    kind: str
    text: str


Sample = Union[MagSample, ImuSample, AttitudeSample, GpsSample, BatterySample, ParamSample, MissionSample,
               StatusSample]


def finite_or_none(x) -> float | None:
    """``float(x)`` when it is a finite number, else None (JSON has no NaN)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _empty(cols: int) -> np.ndarray:
    return np.empty((0, cols), dtype=float)


@dataclass
class FlightLog:
    """A whole log as column arrays, the form the batch estimators take.

    Each table's first column is t_s, sorted ascending (out-of-order samples are dropped at
    ingest and counted in ``warnings``).
      mag:       [t_s, mx_mG, my_mG, mz_mG]                (primary instance only)
      imu:       [t_s, gx, gy, gz rad/s, ax, ay, az m/s^2]  (primary instance only)
      attitude:  [t_s, roll_rad, pitch_rad, yaw_rad]
      gps:       [t_s, lat_deg, lon_deg, alt_m, vn, ve, vd m/s, fix_type]
      battery:   [t_s, current_A]
    """
    source: str
    mag: np.ndarray = field(default_factory=lambda: _empty(4))
    imu: np.ndarray = field(default_factory=lambda: _empty(7))
    attitude: np.ndarray = field(default_factory=lambda: _empty(4))
    gps: np.ndarray = field(default_factory=lambda: _empty(8))
    battery: np.ndarray = field(default_factory=lambda: _empty(2))
    params: dict[str, float] = field(default_factory=dict)
    mission: list[tuple[float, float, float]] = field(default_factory=list)  # (lat, lon, alt)
    start_unix_s: float | None = None   # wall-clock time of t_s = 0 when known (WMM date)
    autopilot: str | None = None        # "ardupilot" | "px4" | None
    # True when the mag table already has the autopilot's own calibration applied (ArduPilot
    # RAW_IMU/SCALED_IMU/MAG, PX4 vehicle_magnetometer); False for raw sensor output (PX4
    # sensor_mag, CSV dumps); None when unknown.  See groundstation.io.params.
    mag_calibration_applied: bool | None = None
    message_counts: Counter = field(default_factory=Counter)
    warnings: Counter = field(default_factory=Counter)
    status: list[StatusSample] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        ends = [a[-1, 0] for a in (self.mag, self.imu, self.attitude, self.gps) if len(a)]
        return float(max(ends)) if ends else 0.0
