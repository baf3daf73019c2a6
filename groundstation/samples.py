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
from dataclasses import dataclass, field, replace
from typing import Union

import numpy as np


@dataclass(slots=True)
class MagSample:
    """``instance``: the source (groundstation.io.decode.compass_of_source maps it to the compass);
    ``motor_offset_mG``: the motor compensation the autopilot applied, when it logs it."""
    t_s: float
    mag_body_mG: tuple[float, float, float]
    instance: int = 0
    motor_offset_mG: tuple[float, float, float] | None = None


@dataclass(slots=True)
class ImuSample:
    t_s: float
    gyro_rad_s: tuple[float, float, float]
    accel_mps2: tuple[float, float, float]
    instance: int = 0


@dataclass(slots=True)
class AttitudeSample:
    """The autopilot's own attitude estimate (not truth).  ``source`` "": the log's attitude (ATT,
    ATTITUDE, vehicle_attitude); else another estimator the log also recorded (AHR2, XKF1, NKF1)."""
    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    source: str = ""


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
class ThrottleSample:
    """Motor throttle 0..1 (VFR_HUD throttle %, DataFlash CTUN ThO/ThrOut, RCOU): the signal of
    ArduPilot's per-throttle motor compensation (COMPASS_MOTCT = 1)."""
    t_s: float
    throttle: float


@dataclass(slots=True)
class OffsetsSample:
    """Compass offsets the autopilot reports it is using (SENSOR_OFFSETS mag_ofs_*, compass 0),
    in ArduPilot's COMPASS_OFS convention (mG, added to the raw field).  Integers at the source
    (``quantum_mG``), so a change smaller than that is not a change."""
    t_s: float
    compass: int
    offsets_mG: tuple[float, float, float]
    quantum_mG: float = 1.0


@dataclass(slots=True)
class MagCalSample:
    """Onboard compass calibration events (ArduPilot's CompassCalibrator, MAVLink).

    kind: "start" (MAV_CMD_DO_START_MAG_CAL, compass = −1 for the mask in ``mask``), "accept",
    "cancel", "progress" (MAG_CAL_PROGRESS, ``completion_pct``), "report" (MAG_CAL_REPORT:
    ``status`` MAG_CAL_STATUS, 4 = success; ``fitness_mG``; ``offsets_mG`` COMPASS_OFS convention;
    ``diag``, ``offdiag``, ``scale_factor``; ``orientation`` (old, new, confidence)).
    """
    t_s: float
    kind: str
    compass: int
    mask: int = 0
    completion_pct: float = math.nan
    status: int = -1
    autosaved: int = 0
    fitness_mG: float = math.nan
    offsets_mG: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    diag: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    offdiag: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    scale_factor: float = math.nan
    orientation: tuple[float, float, float] = (math.nan, math.nan, math.nan)


MAG_CAL_SUCCESS = 4   # MAVLink MAG_CAL_STATUS


@dataclass(slots=True)
class StatusSample:
    """Anything else worth showing: HEARTBEAT autopilot, STATUSTEXT, MAG_CAL_* ..."""
    t_s: float
    kind: str
    text: str


Sample = Union[MagSample, ImuSample, AttitudeSample, GpsSample, BatterySample, ThrottleSample, ParamSample,
               OffsetsSample, MagCalSample, MissionSample, StatusSample]


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
class CompassTable:
    """One magnetometer's samples in a log.

    compass: 0-based compass number (ArduPilot compass n+1, whose parameters are COMPASS_OFS_*,
    COMPASS_OFS2_* ...; PX4 sensor_mag instance).  field: [t_s, mx, my, mz] mG, as the log has it
    (``calibration_applied`` says whether the autopilot's corrections are in it).  source: the
    message it came from ("RAW_IMU", "SCALED_IMU2", "MAG2", "MAG[1]", "sensor_mag[1]",
    "vehicle_magnetometer").  motor_offset_mG: (N, 3) motor compensation the autopilot logged with
    each sample (DataFlash MAG MOfsX.. / MOX..), None when not logged.  source_note: which source
    was chosen among the log's for this compass, in which unit, and why (None: the only one).
    """
    compass: int
    field: np.ndarray
    source: str
    device_id: int | None = None
    calibration_applied: bool | None = None
    motor_offset_mG: np.ndarray | None = None
    source_note: str | None = None      # why this source (of several for the compass) and its unit

    @property
    def rate_hz(self) -> float:
        """Mean sample rate over the compass's own span (0 with fewer than two samples)."""
        if len(self.field) < 2:
            return 0.0
        span = float(self.field[-1, 0] - self.field[0, 0])
        return (len(self.field) - 1) / span if span > 0 else 0.0


@dataclass
class FlightLog:
    """A whole log as column arrays, the form the batch estimators take.

    Each table's first column is t_s, sorted ascending (out-of-order samples are dropped at
    ingest and counted in ``warnings``).
      mag:       [t_s, mx_mG, my_mG, mz_mG]                (primary instance only)
      imu:       [t_s, gx, gy, gz rad/s, ax, ay, az m/s^2]  (primary instance only)
      attitude:  [t_s, roll_rad, pitch_rad, yaw_rad]  (the log's own; ``attitudes``: the other
                 estimators the log recorded, e.g. DataFlash AHR2 (DCM), XKF1 (EKF3), NKF1 (EKF2))
      gps:       [t_s, lat_deg, lon_deg, alt_m, vn, ve, vd m/s, fix_type]
      battery:   [t_s, current_A]
      throttle:  [t_s, throttle 0..1]
    Every compass is in ``compasses`` (``mag`` is the primary one's field, ``primary_compass`` its
    number), every IMU instance in ``imus`` (instance -> [t_s, gyro, accel]).
    ``param_history``: (t_s, name, value) each time a parameter was set or reported with a new
    value (PARAM_VALUE, PARM, ULog parameter changes; SENSOR_OFFSETS and DataFlash MAG Ofs* as
    COMPASS_OFS{n}_*), in time order; ``params`` holds the last values.  ``mag_cal``: the onboard
    calibration events (MagCalSample) in time order.
    """
    source: str
    mag: np.ndarray = field(default_factory=lambda: _empty(4))
    imu: np.ndarray = field(default_factory=lambda: _empty(7))
    attitude: np.ndarray = field(default_factory=lambda: _empty(4))
    attitudes: dict[str, np.ndarray] = field(default_factory=dict)   # other estimators logged, like attitude
    gps: np.ndarray = field(default_factory=lambda: _empty(8))
    battery: np.ndarray = field(default_factory=lambda: _empty(2))
    throttle: np.ndarray = field(default_factory=lambda: _empty(2))
    params: dict[str, float] = field(default_factory=dict)
    param_history: list[tuple[float, str, float]] = field(default_factory=list)
    compasses: list[CompassTable] = field(default_factory=list)
    primary_compass: int = 0
    imus: dict[int, np.ndarray] = field(default_factory=dict)
    mag_cal: list[MagCalSample] = field(default_factory=list)
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
        ends += [c.field[-1, 0] for c in self.compasses if len(c.field)]
        return float(max(ends)) if ends else 0.0

    def compass_tables(self) -> list[CompassTable]:
        """Every compass (``calibration_applied`` filled in from the log's when a reader left it
        None); a log built without per-compass tables (the calibration wizard, a CSV) gives its
        ``mag`` table as compass ``primary_compass``."""
        if self.compasses:
            return [c if c.calibration_applied is not None else replace(c, calibration_applied=self.mag_calibration_applied)
                    for c in self.compasses]
        if len(self.mag):
            return [CompassTable(self.primary_compass, self.mag, "mag", None, self.mag_calibration_applied)]
        return []
