"""PX4 ULogs (.ulg) through pyulog."""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Callable

import numpy as np

from ..decode import MG_PER_GAUSS
from ..errors import IngestError
from .builder import clean_table
from .quiet import counting, quiet
from ...samples import FlightLog

__all__ = ["read_ulog"]


def _ulog_table(ulog, name: str, instance: int = 0):
    for d in ulog.data_list:
        if d.name == name and d.multi_id == instance:
            return d.data
    return None


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
    """PX4 ULog: sensor_mag (gauss, raw) or vehicle_magnetometer (gauss, calibrated),
    sensor_combined, vehicle_attitude (quaternion), vehicle_gps_position, parameters."""
    from pyulog import ULog

    topics = ["sensor_mag", "vehicle_magnetometer", "sensor_combined", "vehicle_attitude",
              "vehicle_gps_position", "sensor_gps"]
    import pyulog.core

    quiet(pyulog.core, _pyulog_complaint)      # it prints a line per unknown or damaged message
    complaints: Counter = Counter()
    try:
        with counting(complaints):
            guarded = _ProgressGuardedFile(path)
            try:
                ulog = ULog(guarded, topics, parse_header_only=False)
            finally:
                guarded.close()
    except Exception as err:  # pyulog raises bare exceptions on corrupt headers
        raise IngestError(f"{path.name}: not a readable ULog ({type(err).__name__}: "
                          f"{str(err).splitlines()[0][:120] if str(err) else ''})") from err
    log = FlightLog(source=str(path), autopilot="px4")
    log.warnings.update(complaints)
    log.params = {k: float(v) for k, v in ulog.initial_parameters.items()}
    for d in ulog.data_list:
        log.message_counts[d.name if d.multi_id == 0 else f"{d.name}[{d.multi_id}]"] += len(d.data["timestamp"])
    t0_us = float(ulog.start_timestamp)

    def tcol(data) -> np.ndarray:
        return (data["timestamp"].astype(float) - t0_us) * 1e-6

    raw = _ulog_table(ulog, "sensor_mag")
    fused = _ulog_table(ulog, "vehicle_magnetometer")
    if raw is not None and len(raw["timestamp"]) >= 50:
        log.mag = np.column_stack([tcol(raw), raw["x"], raw["y"], raw["z"]]) * [1, MG_PER_GAUSS, MG_PER_GAUSS, MG_PER_GAUSS]
        log.mag_calibration_applied = False
    elif fused is not None:
        log.mag = np.column_stack([tcol(fused)] + [fused[f"magnetometer_ga[{i}]"].astype(float) * MG_PER_GAUSS
                                                   for i in range(3)])      # float64 first: no overflow
        log.mag_calibration_applied = True
    imu = _ulog_table(ulog, "sensor_combined")
    if imu is not None:
        log.imu = np.column_stack([tcol(imu)] + [imu[f"gyro_rad[{i}]"] for i in range(3)]
                                  + [imu[f"accelerometer_m_s2[{i}]"] for i in range(3)])
    bat = _ulog_table(ulog, "battery_status")
    if bat is not None and "current_a" in bat:
        table = np.column_stack([tcol(bat), bat["current_a"]]).astype(float)
        log.battery = table[table[:, 1] >= 0]       # -1: not measured
    att = _ulog_table(ulog, "vehicle_attitude")
    if att is not None:
        w, x, y, z = (att[f"q[{i}]"].astype(float) for i in range(4))
        roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
        yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        log.attitude = np.column_stack([tcol(att), roll, pitch, yaw])
    gps = _ulog_table(ulog, "vehicle_gps_position")
    if gps is None:
        gps = _ulog_table(ulog, "sensor_gps")
    if gps is not None:
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
    for name in ("mag", "imu", "attitude", "gps", "battery"):
        setattr(log, name, clean_table(getattr(log, name), name, log.warnings))
    return log
