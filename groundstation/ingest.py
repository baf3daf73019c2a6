"""One ingest layer: every source becomes the same typed sample stream (see samples.py).

Sources: MAVLink telemetry logs (.tlog), ArduPilot DataFlash logs (.bin), PX4 ULogs (.ulg),
raw CSV dumps (.csv), and live MAVLink links (UDP/TCP/serial, see LiveLink).  Units are
converted here, once; everything downstream sees the internal units of samples.py.

Bad input never raises out of ``read_log`` except as an ``IngestError`` with a one-line
message (nothing usable at all); damage inside a log (bad CRC, garbage bytes, NaN fields,
time going backwards, truncation) is skipped and counted in ``FlightLog.warnings``.
"""
from __future__ import annotations

import csv
import heapq
import math
import os
import struct
import time
from collections import Counter
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from .mavlink import mavlink2
from .samples import (AttitudeSample, BatterySample, FlightLog, GpsSample, ImuSample, MagSample, MissionSample,
                      ParamSample, Sample, StatusSample)

G_MPS2 = 9.80665
MG_PER_GAUSS = 1000.0
MG_PER_UT = 10.0  # 1 uT = 10 mG

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_GCS = 6
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_SET_MESSAGE_INTERVAL = 511


class IngestError(Exception):
    """A source that cannot be read at all.  ``str(err)`` is a one-line message for the user."""


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _euler_from_quaternion(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in rad of a body-to-NED quaternion."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


class _BootClock:
    """Maps a message's time_boot_ms onto the log's time base.

    Radio links deliver packets in bursts, so arrival times jitter by tens of ms; the
    vehicle's boot clock does not.  t = boot_s + offset, where offset is the smallest
    (arrival - boot) seen so far (a packet never arrives before it is sent).  A reboot
    (boot time going back) or a drift beyond 2 s re-anchors the offset.
    """

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self.last_boot_s = -math.inf

    def __call__(self, boot_ms: float, arrival_s: float) -> float:
        boot_s = boot_ms * 1e-3
        candidate = arrival_s - boot_s
        if (self.offset_s is None or boot_s < self.last_boot_s - 1.0
                or abs(candidate - self.offset_s) > 2.0):
            self.offset_s = candidate
        elif candidate < self.offset_s:
            self.offset_s = candidate
        self.last_boot_s = boot_s
        return boot_s + self.offset_s


class MavlinkDecoder:
    """Turns pymavlink message objects into samples, with units exactly as the MAVLink XML says.

    SCALED_IMU/2/3 and ArduPilot's RAW_IMU: acc mG (milli-g), gyro mrad/s, mag mgauss.
    HIGHRES_IMU: acc m/s^2, gyro rad/s, mag gauss.  ATTITUDE: rad.  GPS_RAW_INT: degE7, mm,
    cm/s, cdeg.  Messages from a GCS (our own heartbeats echoed, other ground stations) are
    ignored.
    """

    def __init__(self) -> None:
        self.clock = _BootClock()
        self.autopilot: str | None = None
        self.vehicle_sysid: int | None = None
        self.start_unix_s: float | None = None
        self.warnings: Counter = Counter()
        self._last_gps_raw_t = -math.inf
        self._last_fix_type = 3
        self._handlers: dict[str, Callable] = {
            "HEARTBEAT": self._heartbeat,
            "RAW_IMU": self._scaled_imu(0),
            "SCALED_IMU": self._scaled_imu(10),
            "SCALED_IMU2": self._scaled_imu(11),
            "SCALED_IMU3": self._scaled_imu(12),
            "HIGHRES_IMU": self._highres_imu,
            "ATTITUDE": self._attitude,
            "ATTITUDE_QUATERNION": self._attitude_quaternion,
            "GPS_RAW_INT": self._gps_raw_int,
            "GLOBAL_POSITION_INT": self._global_position_int,
            "MISSION_ITEM_INT": self._mission_item,
            "MISSION_ITEM": self._mission_item,
            "PARAM_VALUE": self._param_value,
            "STATUSTEXT": self._status("statustext", lambda m: m.text),
            "MAG_CAL_PROGRESS": self._status(
                "mag_cal_progress", lambda m: f"compass {m.compass_id}: {m.completion_pct}%"),
            "MAG_CAL_REPORT": self._status(
                "mag_cal_report", lambda m: f"compass {m.compass_id}: status {m.cal_status}, "
                                            f"fitness {m.fitness:.1f}"),
            "SYSTEM_TIME": self._system_time,
            "SYS_STATUS": self._sys_status,
        }

    def _t(self, msg, arrival_s: float) -> float:
        boot_ms = getattr(msg, "time_boot_ms", None)
        return arrival_s if boot_ms is None else self.clock(boot_ms, arrival_s)

    def decode(self, msg, arrival_s: float) -> list[Sample]:
        """Samples carried by one message; ``arrival_s`` is its time on the log's time base."""
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return []
        if msg.get_type() != "HEARTBEAT" and self._from_gcs(msg):
            return []
        try:
            return handler(msg, arrival_s)
        except (AttributeError, TypeError, ValueError, OverflowError) as err:
            self.warnings[f"undecodable {msg.get_type()}: {type(err).__name__}"] += 1
            return []

    def _from_gcs(self, msg) -> bool:
        return self.vehicle_sysid is not None and msg.get_srcSystem() != self.vehicle_sysid

    def _heartbeat(self, msg, t: float) -> list[Sample]:
        if msg.type == MAV_TYPE_GCS or msg.autopilot == 8:  # 8 = MAV_AUTOPILOT_INVALID
            return []
        if self.vehicle_sysid is None:
            self.vehicle_sysid = msg.get_srcSystem()
        elif msg.get_srcSystem() != self.vehicle_sysid:
            return []
        name = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}.get(msg.autopilot)
        if name and name != self.autopilot:
            self.autopilot = name
            return [StatusSample(t, "autopilot", name)]
        return []

    def _scaled_imu(self, instance: int) -> Callable:
        def decode(msg, arrival_s: float) -> list[Sample]:
            t = arrival_s if msg.get_type() == "RAW_IMU" else self._t(msg, arrival_s)
            out: list[Sample] = []
            mag = (float(msg.xmag), float(msg.ymag), float(msg.zmag))
            if mag != (0.0, 0.0, 0.0):  # all-zero = no compass on this instance
                out.append(MagSample(t, mag, instance))
            gyro = (msg.xgyro * 1e-3, msg.ygyro * 1e-3, msg.zgyro * 1e-3)
            acc = (msg.xacc * 1e-3 * G_MPS2, msg.yacc * 1e-3 * G_MPS2, msg.zacc * 1e-3 * G_MPS2)
            out.append(ImuSample(t, gyro, acc, instance))
            return out
        return decode

    def _highres_imu(self, msg, t: float) -> list[Sample]:
        updated = msg.fields_updated
        out: list[Sample] = []
        if updated & 0x1C0 or not updated:
            mag = (msg.xmag * MG_PER_GAUSS, msg.ymag * MG_PER_GAUSS, msg.zmag * MG_PER_GAUSS)
            if _finite(*mag):
                out.append(MagSample(t, mag, 20 + msg.id))
            else:
                self.warnings["NaN magnetometer field"] += 1
        gyro = (msg.xgyro, msg.ygyro, msg.zgyro)
        acc = (msg.xacc, msg.yacc, msg.zacc)
        if _finite(*gyro, *acc):
            out.append(ImuSample(t, gyro, acc, 20 + msg.id))
        else:
            self.warnings["NaN IMU field"] += 1
        return out

    def _attitude(self, msg, arrival_s: float) -> list[Sample]:
        if not _finite(msg.roll, msg.pitch, msg.yaw):
            self.warnings["NaN attitude field"] += 1
            return []
        return [AttitudeSample(self._t(msg, arrival_s), msg.roll, msg.pitch, msg.yaw)]

    def _attitude_quaternion(self, msg, arrival_s: float) -> list[Sample]:
        q = (msg.q1, msg.q2, msg.q3, msg.q4)
        norm = math.sqrt(sum(v * v for v in q)) if _finite(*q) else 0.0
        if not 0.5 < norm < 1.5:
            self.warnings["invalid attitude quaternion"] += 1
            return []
        return [AttitudeSample(self._t(msg, arrival_s), *_euler_from_quaternion(*(v / norm for v in q)))]

    def _gps_raw_int(self, msg, t: float) -> list[Sample]:
        self._last_gps_raw_t = t
        self._last_fix_type = int(msg.fix_type)
        if msg.fix_type < 2 or (msg.lat == 0 and msg.lon == 0):
            return []
        speed = msg.vel * 0.01 if msg.vel != 65535 else math.nan
        course = math.radians(msg.cog * 0.01) if msg.cog != 65535 else math.nan
        vel = (speed * math.cos(course), speed * math.sin(course), math.nan)
        return [GpsSample(t, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3, vel, int(msg.fix_type))]

    def _global_position_int(self, msg, arrival_s: float) -> list[Sample]:
        """The autopilot's fused position: used only when no GPS_RAW_INT came for 3 s."""
        t = self._t(msg, arrival_s)
        if t - self._last_gps_raw_t < 3.0 or (msg.lat == 0 and msg.lon == 0):
            return []
        vel = (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
        return [GpsSample(t, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3, vel, self._last_fix_type)]

    def _mission_item(self, msg, t: float) -> list[Sample]:
        if msg.command != MAV_CMD_NAV_WAYPOINT:
            return []
        scale = 1e-7 if msg.get_type() == "MISSION_ITEM_INT" else 1.0
        lat, lon = msg.x * scale, msg.y * scale
        if not _finite(lat, lon) or (lat == 0 and lon == 0):
            return []
        return [MissionSample(t, int(msg.seq), lat, lon, float(msg.z))]

    def _param_value(self, msg, t: float) -> list[Sample]:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
        return [ParamSample(t, name, float(msg.param_value))]

    @staticmethod
    def _status(kind: str, text: Callable) -> Callable:
        return lambda msg, t: [StatusSample(t, kind, str(text(msg)))]

    def _sys_status(self, msg, t: float) -> list[Sample]:
        """current_battery is in cA (10 mA); -1 means the autopilot does not measure it."""
        if msg.current_battery < 0:
            return []
        return [BatterySample(t, msg.current_battery * 0.01)]

    def _system_time(self, msg, t: float) -> list[Sample]:
        if self.start_unix_s is None and msg.time_unix_usec > 1e15:
            self.start_unix_s = msg.time_unix_usec * 1e-6 - t
        return []


# --------------------------------------------------------------------------------- assembling

def _primary_instance(rows: np.ndarray) -> np.ndarray:
    """Rows of the most frequent sensor instance (last column), instance column removed."""
    if not len(rows):
        return rows[:, :-1]
    ids, counts = np.unique(rows[:, -1], return_counts=True)
    return rows[rows[:, -1] == ids[np.argmax(counts)], :-1]


class _LogBuilder:
    """Collects samples into a FlightLog; keeps the primary instance of mag and IMU."""

    def __init__(self, source: str) -> None:
        self.log = FlightLog(source=source)
        self.rows: dict[str, list] = {"mag": [], "imu": [], "attitude": [], "gps": [], "battery": []}
        self.mission: dict[int, tuple[float, float, float]] = {}

    def add(self, s: Sample) -> None:
        if isinstance(s, MagSample):
            self.rows["mag"].append((s.t_s, *s.mag_body_mG, s.instance))
        elif isinstance(s, ImuSample):
            self.rows["imu"].append((s.t_s, *s.gyro_rad_s, *s.accel_mps2, s.instance))
        elif isinstance(s, AttitudeSample):
            self.rows["attitude"].append((s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad))
        elif isinstance(s, GpsSample):
            self.rows["gps"].append((s.t_s, s.lat_deg, s.lon_deg, s.alt_m, *s.vel_ned_mps, s.fix_type))
        elif isinstance(s, BatterySample):
            self.rows["battery"].append((s.t_s, s.current_A))
        elif isinstance(s, ParamSample):
            self.log.params[s.name] = s.value
        elif isinstance(s, MissionSample):
            self.mission[s.seq] = (s.lat_deg, s.lon_deg, s.alt_m)
        elif isinstance(s, StatusSample):
            self.log.status.append(s)
            if s.kind == "autopilot":
                self.log.autopilot = s.text

    def finish(self) -> FlightLog:
        log = self.log
        tables = {"mag": _primary_instance(np.asarray(self.rows["mag"], dtype=float).reshape(-1, 5)),
                  "imu": _primary_instance(np.asarray(self.rows["imu"], dtype=float).reshape(-1, 8)),
                  "attitude": self.rows["attitude"], "gps": self.rows["gps"], "battery": self.rows["battery"]}
        widths = {"mag": 4, "imu": 7, "attitude": 4, "gps": 8, "battery": 2}
        for name, rows in tables.items():
            arr = np.asarray(rows, dtype=float).reshape(-1, widths[name])
            setattr(log, name, _clean_table(arr, name, log.warnings))
        # ArduPilot numbers mission item 0 as home; a mission is the waypoints after it.
        seqs = sorted(self.mission)
        if log.autopilot == "ardupilot" and seqs and seqs[0] == 0 and len(seqs) > 1:
            seqs = seqs[1:]
        log.mission = [self.mission[s] for s in seqs]
        return log


def _clean_table(arr: np.ndarray, name: str, warnings: Counter) -> np.ndarray:
    """Drop rows with non-finite time or values (GPS velocity may be NaN), sort by time."""
    check = arr[:, :4] if name == "gps" else arr
    good = np.all(np.isfinite(check), axis=1)
    if not good.all():
        warnings[f"{name}: rows with NaN/inf dropped"] += int((~good).sum())
        arr = arr[good]
    if len(arr) > 1:
        backwards = int(np.count_nonzero(np.diff(arr[:, 0]) < 0))
        if backwards:
            warnings[f"{name}: samples out of time order (re-sorted)"] += backwards
            arr = arr[np.argsort(arr[:, 0], kind="stable")]
    return arr


def iter_samples(log: FlightLog) -> Iterator[Sample]:
    """Merge a FlightLog's tables back into one time-ordered sample stream (for replay)."""
    def mags() -> Iterator[Sample]:
        for r in log.mag.tolist():
            yield MagSample(r[0], (r[1], r[2], r[3]))

    def imus() -> Iterator[Sample]:
        for r in log.imu.tolist():
            yield ImuSample(r[0], (r[1], r[2], r[3]), (r[4], r[5], r[6]))

    def atts() -> Iterator[Sample]:
        for r in log.attitude.tolist():
            yield AttitudeSample(r[0], r[1], r[2], r[3])

    def gpss() -> Iterator[Sample]:
        for r in log.gps.tolist():
            yield GpsSample(r[0], r[1], r[2], r[3], (r[4], r[5], r[6]), int(r[7]))

    head: list[Sample] = [ParamSample(0.0, k, v) for k, v in log.params.items()]
    head += [MissionSample(0.0, i, *wp) for i, wp in enumerate(log.mission)]
    if log.autopilot:
        head.append(StatusSample(0.0, "autopilot", log.autopilot))
    yield from head
    yield from heapq.merge(imus(), mags(), atts(), gpss(), log.status, key=lambda s: s.t_s)


# ------------------------------------------------------------------------------------ readers

TLOG_STAMP = struct.Struct(">Q")
_PLAUSIBLE_UNIX_S = (946684800.0, 4102444800.0)  # 2000..2100


def _tlog_records(data: bytes, warnings: Counter) -> Iterator[tuple[float, object]]:
    """(UNIX time, message) of each good record of a .tlog image.

    A record is an 8-byte big-endian microsecond stamp and one MAVLink 1 (0xFE) or 2 (0xFD)
    packet, so the packet length is known from its header and pymavlink's ``decode`` (CRC
    checked) gets whole packets; that skips its byte-at-a-time stream parser, which is built
    for serial links.  After garbage or a bad CRC we resynchronise on the next position whose
    stamp is plausible and whose packet decodes; a cut-off last record is reported.
    """
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    n = len(data)
    i = 0
    last_unix: float | None = None
    while i + 10 <= n:
        magic = data[i + 8]
        if magic == 0xFD:
            size = 12 + data[i + 9] + (13 if data[i + 10] & 1 else 0)
        elif magic == 0xFE:
            size = 8 + data[i + 9]
        else:
            size = 0
        unix = TLOG_STAMP.unpack_from(data, i)[0] * 1e-6
        plausible = (_PLAUSIBLE_UNIX_S[0] < unix < _PLAUSIBLE_UNIX_S[1]
                     and (last_unix is None or abs(unix - last_unix) < 86400.0))
        if size and plausible:
            if i + 8 + size > n:
                warnings["log truncated: last record cut off"] += 1
                return
            try:
                msg = parser.decode(bytearray(data[i + 8:i + 8 + size]))
            except (mavlink2.MAVError, struct.error, IndexError, ValueError, TypeError):
                msg = None
            if msg is not None:
                last_unix = unix
                i += 8 + size
                yield unix, msg
                continue
        warnings["corrupt packets skipped (bad CRC or garbage)"] += 1
        i = _next_record(data, i + 1, last_unix)
    if i < n:
        warnings["log truncated: last record cut off"] += 1


def _next_record(data: bytes, start: int, last_unix: float | None) -> int:
    """Index of the next plausible record start (stamp then a MAVLink magic byte) after garbage."""
    n = len(data)
    j = start
    while True:
        hits = [k for k in (data.find(b"\xfd", j + 8), data.find(b"\xfe", j + 8)) if k >= 0]
        if not hits:
            return n
        k = min(hits) - 8
        unix = TLOG_STAMP.unpack_from(data, k)[0] * 1e-6
        if (_PLAUSIBLE_UNIX_S[0] < unix < _PLAUSIBLE_UNIX_S[1]
                and (last_unix is None or abs(unix - last_unix) < 86400.0)):
            return k
        j = k + 1


def _read_tlog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    data = path.read_bytes()
    builder = _LogBuilder(str(path))
    decoder = MavlinkDecoder()
    counts = builder.log.message_counts
    warnings = builder.log.warnings
    first_unix = None
    last_arrival = -math.inf
    backwards_shift = 0.0
    decode = decoder.decode
    add = builder.add
    for n, (unix, msg) in enumerate(_tlog_records(data, warnings)):
        counts[msg.get_type()] += 1
        if first_unix is None:
            first_unix = unix
        arrival = unix - first_unix + backwards_shift
        if arrival < last_arrival:  # the recorder's clock went back: continue from where it was
            warnings["timestamps going backwards (re-based)"] += 1
            backwards_shift += last_arrival - arrival
            arrival = last_arrival
        last_arrival = arrival
        for s in decode(msg, arrival):
            add(s)
        if progress is not None and n % 20000 == 0:
            progress(n / max(len(data) / 40, 1))
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = first_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True  # ArduPilot sends the corrected field
    return log


def _read_dataflash(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """ArduPilot DataFlash .bin: MAG/MAG2 (mG), IMU (rad/s, m/s^2), ATT (deg), GPS, PARM, CMD."""
    from pymavlink import DFReader

    try:
        reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    except Exception as err:  # pymavlink raises bare exceptions on unreadable headers
        raise IngestError(f"{path.name}: not a readable DataFlash log ({type(err).__name__})") from err
    builder = _LogBuilder(str(path))
    log = builder.log
    log.autopilot = "ardupilot"
    t0_us: float | None = None
    gps_week_ms: tuple[float, float, float] | None = None
    wanted = {"MAG", "MAG2", "MAG3", "IMU", "ATT", "GPS", "PARM", "CMD", "BAT"}
    while True:
        try:
            m = reader.recv_match(type=wanted)
        except Exception as err:  # truncated/corrupt tail inside pymavlink's parser
            log.warnings[f"log truncated or corrupt ({type(err).__name__})"] += 1
            break
        if m is None:
            break
        mtype = m.get_type()
        log.message_counts[mtype] += 1
        if mtype == "PARM":
            builder.add(ParamSample(0.0, m.Name, float(m.Value)))
            continue
        time_us = getattr(m, "TimeUS", None)
        if time_us is None:
            continue
        if t0_us is None and mtype != "CMD":
            t0_us = time_us
        t = (time_us - t0_us) * 1e-6 if t0_us is not None else 0.0
        try:
            if mtype.startswith("MAG"):
                instance = getattr(m, "I", {"MAG": 0, "MAG2": 1, "MAG3": 2}[mtype])
                builder.add(MagSample(t, (float(m.MagX), float(m.MagY), float(m.MagZ)), int(instance)))
            elif mtype == "IMU":
                builder.add(ImuSample(t, (m.GyrX, m.GyrY, m.GyrZ), (m.AccX, m.AccY, m.AccZ),
                                      int(getattr(m, "I", 0))))
            elif mtype == "ATT":
                builder.add(AttitudeSample(t, math.radians(m.Roll), math.radians(m.Pitch),
                                           math.radians(m.Yaw)))
            elif mtype == "GPS":
                if int(getattr(m, "I", 0)) != 0 or m.Status < 2:
                    continue
                crs = math.radians(m.GCrs)
                builder.add(GpsSample(t, m.Lat, m.Lng, m.Alt, (m.Spd * math.cos(crs),
                                      m.Spd * math.sin(crs), m.VZ), int(m.Status)))
                if gps_week_ms is None and getattr(m, "GWk", 0) > 0:
                    gps_week_ms = (m.GWk, m.GMS, t)
            elif mtype == "CMD" and m.CId == MAV_CMD_NAV_WAYPOINT:
                builder.add(MissionSample(t, int(m.CNum), m.Lat, m.Lng, m.Alt))
            elif mtype == "BAT" and int(getattr(m, "Inst", getattr(m, "Instance", 0))) == 0:
                builder.add(BatterySample(t, float(m.Curr)))          # A
        except (AttributeError, TypeError, ValueError) as err:
            log.warnings[f"undecodable {mtype}: {type(err).__name__}"] += 1
        if progress is not None and sum(log.message_counts.values()) % 20000 == 0:
            progress(min(reader.offset / max(reader.data_len, 1), 1.0))
    if reader.data_len - reader.offset > 0:
        log.warnings[f"log truncated: last {reader.data_len - reader.offset} bytes unreadable"] += 1
    log = builder.finish()
    log.mag_calibration_applied = True  # ArduPilot logs the corrected field (offsets in OfsX..)
    if gps_week_ms is not None:
        week, ms, t = gps_week_ms
        log.start_unix_s = 315964800 + week * 604800 + ms * 1e-3 - 18 - t  # GPS epoch, leap s
    return log


def _ulog_table(ulog, name: str, instance: int = 0):
    for d in ulog.data_list:
        if d.name == name and d.multi_id == instance:
            return d.data
    return None


def _read_ulog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """PX4 ULog: sensor_mag (gauss, raw) or vehicle_magnetometer (gauss, calibrated),
    sensor_combined, vehicle_attitude (quaternion), vehicle_gps_position, parameters."""
    from pyulog import ULog

    topics = ["sensor_mag", "vehicle_magnetometer", "sensor_combined", "vehicle_attitude",
              "vehicle_gps_position", "sensor_gps"]
    try:
        ulog = ULog(str(path), topics, parse_header_only=False)
    except Exception as err:  # pyulog raises bare exceptions on corrupt headers
        raise IngestError(f"{path.name}: not a readable ULog ({type(err).__name__}: {err})") from err
    log = FlightLog(source=str(path), autopilot="px4")
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
        log.mag = np.column_stack([tcol(fused)] + [fused[f"magnetometer_ga[{i}]"] * MG_PER_GAUSS
                                                   for i in range(3)])
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
        setattr(log, name, _clean_table(getattr(log, name), name, log.warnings))
    return log


def _read_csv(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """CSV with columns mx,my,mz (mG) and optional t_s, roll_deg, pitch_deg, yaw_deg."""
    log = FlightLog(source=str(path), mag_calibration_applied=False)
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        reader = csv.DictReader(f)
        fields = {c.strip().lower(): c for c in (reader.fieldnames or [])}
        if not {"mx", "my", "mz"} <= fields.keys():
            raise IngestError(f"{path.name}: CSV needs columns mx,my,mz (milligauss); found "
                              f"{', '.join(fields) or 'none'}")
        has_att = {"roll_deg", "pitch_deg", "yaw_deg"} <= fields.keys()
        mag, att = [], []
        for i, row in enumerate(reader):
            try:
                t = float(row[fields["t_s"]]) if "t_s" in fields else float(i)
                mag.append((t, float(row[fields["mx"]]), float(row[fields["my"]]), float(row[fields["mz"]])))
                if has_att:
                    att.append((t, *(math.radians(float(row[fields[k]]))
                                     for k in ("roll_deg", "pitch_deg", "yaw_deg"))))
            except (TypeError, ValueError):
                log.warnings["CSV rows that are not numbers skipped"] += 1
    log.message_counts["csv rows"] = len(mag)
    log.mag = _clean_table(np.asarray(mag, dtype=float).reshape(-1, 4), "mag", log.warnings)
    log.attitude = _clean_table(np.asarray(att, dtype=float).reshape(-1, 4), "attitude", log.warnings)
    if len(log.mag):
        t0 = log.mag[0, 0]
        log.mag[:, 0] -= t0
        if len(log.attitude):
            log.attitude[:, 0] -= t0
    return log


READERS: dict[str, Callable[[Path, Callable[[float], None] | None], FlightLog]] = {
    ".tlog": _read_tlog, ".bin": _read_dataflash, ".ulg": _read_ulog, ".csv": _read_csv,
}


def read_log(path: str | os.PathLike, progress: Callable[[float], None] | None = None) -> FlightLog:
    """Read any supported log into a FlightLog.  Raises IngestError with a one-line message
    when nothing usable can be read (missing file, unknown type, no readable messages).  A log
    without magnetometer samples is returned (``info`` still describes it); the commands that
    need the field say so."""
    path = Path(path)
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise IngestError(f"{path.name}: unknown log type '{path.suffix}' "
                          f"(supported: {', '.join(READERS)})")
    if not path.is_file():
        raise IngestError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise IngestError(f"{path.name}: file is empty")
    try:
        log = reader(path, progress)
    except IngestError:
        raise
    except Exception as err:  # a reader library failing on damage we did not foresee
        raise IngestError(f"{path.name}: could not be read ({type(err).__name__}: {err})") from err
    if progress is not None:
        progress(1.0)
    if not (log.params or any(len(t) for t in (log.mag, log.imu, log.attitude, log.gps))):
        raise IngestError(f"{path.name}: no readable messages (is it really a {path.suffix} file?)")
    return log


# ------------------------------------------------------------------------------------ live link

STREAMED_MESSAGES = ("SCALED_IMU", "RAW_IMU", "ATTITUDE", "GPS_RAW_INT", "GLOBAL_POSITION_INT",
                     "HIGHRES_IMU")


def _drop_partial_packets_between_datagrams(conn) -> None:
    """UDP carries whole MAVLink packets per datagram, so an incomplete packet left in the
    parser when the next datagram arrives can only be garbage: drop it, or the parser would
    complete it with the next (good) packet's bytes and lose that packet to a CRC error.
    (Wraps pymavlink's mavudp.recv; serial/TCP streams are left alone.)"""
    from pymavlink import mavutil

    if not isinstance(conn, mavutil.mavudp):
        return
    parser = conn.mav
    raw_recv = conn.recv

    def recv(n=None):
        data = raw_recv(n)
        if data and 0 < parser.buf_len() < parser.expected_length:
            parser.buf = bytearray()
            parser.buf_index = 0
            parser.expected_length = mavlink2.HEADER_LEN_V1 + 2
            parser.have_prefix_error = False
        return data

    conn.recv = recv


class LiveLink:
    """A live MAVLink link through a pymavlink connection string.

    ``udpin:127.0.0.1:14550``, ``tcp:HOST:PORT``, ``/dev/ttyUSB0,57600``.  Sends a GCS
    heartbeat every second, asks for the streams we need with SET_MESSAGE_INTERVAL and falls
    back to REQUEST_DATA_STREAM when the vehicle does not acknowledge it, and records every
    packet received (raw bytes) through ``recorder`` when given.
    """

    RATE_HZ = 50
    LOST_AFTER_S = 3.0

    def __init__(self, url: str, recorder=None) -> None:
        from pymavlink import mavutil

        self.url = url
        device, baud = (url.split(",", 1) + ["57600"])[:2] if "," in url else (url, "57600")
        try:
            self.mav = mavutil.mavlink_connection(
                device, baud=int(baud), source_system=255, source_component=190,
                robust_parsing=True, autoreconnect=True, dialect="ardupilotmega")
        except Exception as err:
            raise IngestError(f"cannot open link '{url}': {err}") from err
        _drop_partial_packets_between_datagrams(self.mav)
        self.recorder = recorder
        self.decoder = MavlinkDecoder()
        self.t0_unix = time.time()
        self.last_rx_unix: float | None = None
        self.connected = False
        self.bad_packets = 0
        self._last_heartbeat = 0.0
        self._streams_requested_at: float | None = None
        self._interval_acked = False
        self._fallback_sent = False

    def t_s(self, unix_s: float | None = None) -> float:
        return (time.time() if unix_s is None else unix_s) - self.t0_unix

    def poll(self, max_messages: int = 1000) -> list[Sample]:
        """Everything that arrived since the last call (non-blocking), as samples."""
        now = time.time()
        out: list[Sample] = []
        self._housekeeping(now, out)
        for _ in range(max_messages):
            try:
                msg = self.mav.recv_msg()
            except (OSError, ValueError, TypeError, IndexError) as err:
                self.bad_packets += 1
                self.decoder.warnings[f"link read error: {type(err).__name__}"] += 1
                break
            if msg is None:
                break
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                self.bad_packets += 1
                continue
            unix = time.time()
            if self.recorder is not None:
                self.recorder.write_packet(bytes(msg.get_msgbuf()), unix)
            if msg.get_srcSystem() == 255:  # our own or another GCS's traffic
                continue
            self.last_rx_unix = unix
            if not self.connected:
                self.connected = True
                out.append(StatusSample(self.t_s(unix), "link", f"link up on {self.url}"))
            if mtype == "COMMAND_ACK" and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and msg.result == 0:
                self._interval_acked = True
            out.extend(self.decoder.decode(msg, self.t_s(unix)))
        return out

    def _housekeeping(self, now: float, out: list[Sample]) -> None:
        from pymavlink import mavutil

        if now - self._last_heartbeat >= 1.0:
            self._last_heartbeat = now
            try:
                self.mav.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                            mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except OSError:
                pass  # UDP-in before the vehicle has spoken has no peer yet
        if self.connected and self.last_rx_unix is not None and now - self.last_rx_unix > self.LOST_AFTER_S:
            self.connected = False
            self._streams_requested_at = None
            out.append(StatusSample(self.t_s(now), "link",
                                    f"link lost: nothing heard for {self.LOST_AFTER_S:.0f} s, waiting"))
        if self.connected and self.decoder.vehicle_sysid is not None:
            if self._streams_requested_at is None:
                self._request_streams(now)
            elif (not self._interval_acked and not self._fallback_sent
                  and now - self._streams_requested_at > 2.0):
                self._request_data_stream_fallback()

    def _request_streams(self, now: float) -> None:
        self._streams_requested_at = now
        self._interval_acked = False
        self._fallback_sent = False
        sysid = self.decoder.vehicle_sysid
        interval_us = 1e6 / self.RATE_HZ
        for name in STREAMED_MESSAGES:
            msg_id = getattr(mavlink2, "MAVLINK_MSG_ID_" + name)
            try:
                self.mav.mav.command_long_send(sysid, 0, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               msg_id, interval_us, 0, 0, 0, 0, 0)
            except OSError:
                return

    def _request_data_stream_fallback(self) -> None:
        self._fallback_sent = True
        try:
            # MAV_DATA_STREAM_ALL (0) at our rate: the pre-MAVLink-2 way ArduPilot still honours.
            self.mav.mav.request_data_stream_send(self.decoder.vehicle_sysid, 0, 0, self.RATE_HZ, 1)
        except OSError:
            pass

    def close(self) -> None:
        try:
            self.mav.close()
        except Exception:
            pass
        if self.recorder is not None:
            self.recorder.flush()


def summarize_rates(log: FlightLog) -> list[tuple[str, int, float]]:
    """(message type, count, mean rate Hz) sorted by count, for `magstation info`."""
    duration = max(log.duration_s, 1e-9)
    return [(k, v, v / duration) for k, v in log.message_counts.most_common()]


def load_many(paths: Iterable[str | os.PathLike]) -> Iterator[tuple[Path, FlightLog | IngestError]]:
    for p in paths:
        try:
            yield Path(p), read_log(p)
        except IngestError as err:
            yield Path(p), err
