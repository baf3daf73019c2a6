"""PX4 ULogs (.ulg) through pyulog."""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Callable

import numpy as np

from ..decode import MG_PER_GAUSS
from ..errors import IngestError
from ..params import param_value_problem, trusted_params
from .builder import clean_table
from .instances import compact_history
from .quiet import counting, quiet
from ...samples import CompassTable, FlightLog

__all__ = ["read_ulog"]

TOPICS = ["sensor_mag", "vehicle_magnetometer", "sensor_combined", "vehicle_attitude", "vehicle_gps_position",
          "sensor_gps", "battery_status", "vehicle_thrust_setpoint", "actuator_controls_0"]
MIN_RAW_SAMPLES = 50      # a sensor_mag instance sparser than this (logged at 1 Hz) yields to vehicle_magnetometer


def _ulog_table(ulog, name: str, instance: int = 0):
    for d in ulog.data_list:
        if d.name == name and d.multi_id == instance:
            return d.data
    return None


def _instances(ulog, name: str) -> list:
    return sorted((d for d in ulog.data_list if d.name == name), key=lambda d: d.multi_id)


def _device_id(data) -> int | None:
    ids = data.get("device_id")
    if ids is None or not len(ids):
        return None
    values, counts = np.unique(np.asarray(ids, dtype=np.int64), return_counts=True)
    v = int(values[np.argmax(counts)])          # the id the instance reported most
    return v or None


def _compasses(ulog, tcol, params: dict[str, float], warnings) -> tuple[list[CompassTable], int]:
    """One table per sensor_mag instance (raw, gauss -> mG); the instance that feeds
    vehicle_magnetometer (same device id, or CAL_MAG_PRIME) takes the calibrated topic instead
    when its raw samples are sparse.  Returns (tables, primary compass)."""
    fused = _ulog_table(ulog, "vehicle_magnetometer")
    fused_id = _device_id(fused) if fused is not None else None
    prime = fused_id or (int(params["CAL_MAG_PRIME"]) if params.get("CAL_MAG_PRIME") else None)
    out: list[CompassTable] = []
    for d in _instances(ulog, "sensor_mag"):
        raw = d.data
        table = np.column_stack([tcol(raw)] + [raw[a].astype(float) * MG_PER_GAUSS for a in "xyz"])  # float64 first
        out.append(CompassTable(d.multi_id, clean_table(table, f"mag[{d.multi_id}]", warnings), f"sensor_mag[{d.multi_id}]",
                                _device_id(raw), False))
    if fused is not None and len(fused["timestamp"]):
        table = clean_table(np.column_stack([tcol(fused)] + [fused[f"magnetometer_ga[{i}]"].astype(float) * MG_PER_GAUSS
                                                            for i in range(3)]), "vehicle_magnetometer", warnings)
        mine = [c for c in out if prime is not None and c.device_id == prime] or ([] if len(out) > 1 else out)
        replace_at = out.index(mine[0]) if mine else None
        if replace_at is None or len(out[replace_at].field) < max(MIN_RAW_SAMPLES, len(table) // 10):
            k = out[replace_at].compass if replace_at is not None else len(out)
            tab = CompassTable(k, table, "vehicle_magnetometer", prime, True)
            if replace_at is None:
                out.append(tab)
            else:
                out[replace_at] = tab
    out = [c for c in out if len(c.field)]
    if not out:
        return [], 0
    primary = [c for c in out if c.source == "vehicle_magnetometer" or (prime is not None and c.device_id == prime)]
    return out, (primary[0] if primary else max(out, key=lambda c: len(c.field))).compass


def _param_history(ulog, t0_us: float) -> list[tuple[float, str, float]]:
    entries = [(0.0, str(k), float(v), 0.0) for k, v in ulog.initial_parameters.items()]
    for ts, name, value in getattr(ulog, "changed_parameters", []) or []:
        entries.append((max((float(ts) - t0_us) * 1e-6, 0.0), str(name), float(value), 0.0))
    return compact_history(entries)


def _throttle(ulog, tcol) -> np.ndarray:
    """Collective thrust 0..1: vehicle_thrust_setpoint −z (newer PX4) or actuator_controls_0[3]."""
    thrust = _ulog_table(ulog, "vehicle_thrust_setpoint")
    if thrust is not None and "xyz[2]" in thrust:
        return np.column_stack([tcol(thrust), np.clip(-thrust["xyz[2]"].astype(float), 0.0, 1.0)])
    ctl = _ulog_table(ulog, "actuator_controls_0")
    if ctl is not None and "control[3]" in ctl:
        return np.column_stack([tcol(ctl), np.clip(ctl["control[3]"].astype(float), 0.0, 1.0)])
    return np.empty((0, 2))


class ReaderStuck(RuntimeError):
    """pyulog stopped making progress through a corrupt file."""


class _ProgressGuardedFile:
    """The file pyulog reads, raising ReaderStuck when reads stop reaching further into it: on
    some truncated, corrupt files pyulog's resynchronisation seeks back further than it read
    and loops forever.  Normal and resynchronising reads always move the furthest position on."""

    MAX_STALLED_READS = 50_000

    def __init__(self, path: Path) -> None:
        self._file = open(path, "rb")
        self._furthest = 0
        self._stalled = 0

    def read(self, size: int = -1) -> bytes:
        data = self._file.read(size)
        position = self._file.tell()
        if position > self._furthest:
            self._furthest, self._stalled = position, 0
        else:
            self._stalled += 1
            if self._stalled > self.MAX_STALLED_READS:
                raise ReaderStuck(f"no progress after {self._stalled} reads at byte {position}")
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def close(self) -> None:
        self._file.close()


def _pyulog_complaint(line: str) -> tuple[str, int]:
    if "no subscription found" in line:
        return "ULog: messages of unknown subscriptions skipped", 1
    if "corruption" in line.lower() or "sync" in line.lower():
        return "ULog: corrupt data skipped (resynchronised)", 1
    return "ULog reader complaints", 1


def read_ulog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """PX4 ULog: every sensor_mag instance (gauss, raw, with its device id) and
    vehicle_magnetometer (gauss, calibrated), sensor_combined, vehicle_attitude (quaternion),
    vehicle_gps_position, battery_status, thrust, parameters with their changes."""
    from pyulog import ULog

    import pyulog.core

    quiet(pyulog.core, _pyulog_complaint)      # it prints a line per unknown or damaged message
    complaints: Counter = Counter()
    try:
        with counting(complaints):
            guarded = _ProgressGuardedFile(path)
            try:
                ulog = ULog(guarded, TOPICS, parse_header_only=False)
            finally:
                guarded.close()
    except Exception as err:  # pyulog raises bare exceptions on corrupt headers
        raise IngestError(f"{path.name}: not a readable ULog ({type(err).__name__}: "
                          f"{str(err).splitlines()[0][:120] if str(err) else ''})") from err
    log = FlightLog(source=str(path), autopilot="px4")
    log.warnings.update(complaints)
    log.params, refused = trusted_params(ulog.initial_parameters)     # NaN, inf, beyond the range: refused
    for problem in refused:
        log.warnings[f"parameter value refused: {problem}"] += 1
    for d in ulog.data_list:
        log.message_counts[d.name if d.multi_id == 0 else f"{d.name}[{d.multi_id}]"] += len(d.data["timestamp"])
    t0_us = float(ulog.start_timestamp)
    log.param_history = _param_history(ulog, t0_us)
    bad = [h for h in log.param_history if param_value_problem(h[1], h[2]) is not None]
    for h in bad:
        log.warnings[f"parameter value refused: {param_value_problem(h[1], h[2])}"] += 1
    log.param_history = [h for h in log.param_history if h not in bad] if bad else log.param_history
    for _, name, value in log.param_history:
        log.params[name] = value

    def tcol(data) -> np.ndarray:
        return (data["timestamp"].astype(float) - t0_us) * 1e-6

    log.compasses, log.primary_compass = _compasses(ulog, tcol, log.params, log.warnings)
    primary = [c for c in log.compasses if c.compass == log.primary_compass]
    if primary:
        log.mag = primary[0].field
        log.mag_calibration_applied = primary[0].calibration_applied
    imu = _ulog_table(ulog, "sensor_combined")
    if imu is not None:
        log.imu = np.column_stack([tcol(imu)] + [imu[f"gyro_rad[{i}]"] for i in range(3)]
                                  + [imu[f"accelerometer_m_s2[{i}]"] for i in range(3)])
    bat = _ulog_table(ulog, "battery_status")
    if bat is not None and "current_a" in bat:
        table = np.column_stack([tcol(bat), bat["current_a"]]).astype(float)
        log.battery = table[table[:, 1] >= 0]       # -1: not measured
    log.throttle = _throttle(ulog, tcol)
    att = _ulog_table(ulog, "vehicle_attitude")
    if att is not None:
        w, x, y, z = (att[f"q[{i}]"].astype(float) for i in range(4))
        roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
        yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        log.attitude = np.column_stack([tcol(att), roll, pitch, yaw])
    _read_gps(ulog, log, tcol)
    for name in ("imu", "attitude", "gps", "battery", "throttle"):
        setattr(log, name, clean_table(getattr(log, name), name, log.warnings))
    if len(log.imu):
        log.imus = {0: log.imu}
    return log


def _read_gps(ulog, log: FlightLog, tcol) -> None:
    gps = _ulog_table(ulog, "vehicle_gps_position")
    if gps is None:
        gps = _ulog_table(ulog, "sensor_gps")
    if gps is None:
        return
    if "latitude_deg" in gps:
        lat, lon, alt = gps["latitude_deg"], gps["longitude_deg"], gps["altitude_msl_m"]
    else:
        lat, lon, alt = gps["lat"] * 1e-7, gps["lon"] * 1e-7, gps["alt"] * 1e-3
    table = np.column_stack([tcol(gps), lat, lon, alt, gps["vel_n_m_s"], gps["vel_e_m_s"],
                             gps["vel_d_m_s"], gps["fix_type"]]).astype(float)
    log.gps = table[(table[:, 7] >= 2) & ~((table[:, 1] == 0) & (table[:, 2] == 0))]
    utc = gps.get("time_utc_usec")
    if utc is not None and np.any(utc > 1e15):
        i = int(np.argmax(utc > 1e15))
        log.start_unix_s = float(utc[i]) * 1e-6 - float(tcol(gps)[i])
