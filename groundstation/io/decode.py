"""MAVLink messages -> typed samples (units per the MAVLink XML, converted once, here).

Shared by the .tlog reader and the live link: ``MavlinkDecoder.decode(msg, arrival_s)``.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Callable

from .boot_clock import BootClock, boot_ms_of_usec
from .mavlink_units import (G_MPS2, euler_from_quaternion, global_position_int_to_si, gps_raw_int_to_si,
                            normalised_quaternion, scaled_imu_to_si, sys_status_current_A, vfr_hud_throttle)
from ..samples import (AttitudeSample, BatterySample, GpsSample, ImuSample, MagCalSample, MagSample, MissionSample,
                       OffsetsSample, ParamSample, Sample, StatusSample, ThrottleSample)

__all__ = ["MavlinkDecoder", "G_MPS2", "MG_PER_GAUSS", "MG_PER_UT", "MAV_CMD_NAV_WAYPOINT",
           "MAV_CMD_SET_MESSAGE_INTERVAL", "MAG_CAL_COMMANDS", "SOURCE_NAMES", "compass_of_source", "source_name",
           "PLAUSIBLE_FIELD_mG", "FieldUnit", "judge_field_unit", "field_plausible", "expected_field_mG",
           "HIGHRES_MAG_UNITS", "MG_UNIT", "rank_mag_source", "scaled_imu_to_si", "euler_from_quaternion",
           "normalised_quaternion", "gps_raw_int_to_si", "global_position_int_to_si", "vfr_hud_throttle",
           "sys_status_current_A", "judge_first_field"]

MG_PER_GAUSS = 1000.0
MG_PER_UT = 10.0  # 1 uT = 10 mG

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_GCS = 6
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_SET_MESSAGE_INTERVAL = 511
# MAV_CMD_DO_START_MAG_CAL / DO_ACCEPT_MAG_CAL / DO_CANCEL_MAG_CAL (ardupilotmega.xml)
MAG_CAL_COMMANDS = {42424: "start", 42425: "accept", 42426: "cancel"}

# MagSample/ImuSample ``instance`` is the source: RAW_IMU 0, SCALED_IMU 10, SCALED_IMU2 11,
# SCALED_IMU3 12, HIGHRES_IMU 20 + id.  ArduPilot streams compass n in RAW_IMU (or SCALED_IMU),
# SCALED_IMU2, SCALED_IMU3 for n = 0, 1, 2.
SOURCE_NAMES = {0: "RAW_IMU", 10: "SCALED_IMU", 11: "SCALED_IMU2", 12: "SCALED_IMU3"}


def compass_of_source(instance: int) -> int:
    """0-based compass (or IMU) number of a MavlinkDecoder source instance."""
    instance = int(instance)
    if instance >= 20:
        return instance - 20
    return instance - 10 if instance >= 10 else instance


def preferred_source(current: int | None, instance: int) -> int:
    """The source kept of those carrying one compass (or IMU) live: the lowest instance heard
    (RAW_IMU 0 before SCALED_IMU 10 before HIGHRES_IMU 20+id), whichever came first; the rule
    of the live analysis (jobs.live.LiveAnalyzer.accepts), the wizard and the dance cloud."""
    return int(instance) if current is None or int(instance) < current else current


def source_name(instance: int) -> str:
    instance = int(instance)
    return SOURCE_NAMES.get(instance, f"HIGHRES_IMU[{instance - 20}]" if instance >= 20 else f"source {instance}")



# The Earth's field is 220-670 mG at the surface; a compass whose offsets are not yet removed, or
# near iron, reads more.  A source outside this range (or 0.5-2x the WMM where the place is known)
# is not in the unit we think.
PLAUSIBLE_FIELD_mG = (150.0, 1000.0)
PLAUSIBLE_WMM_RATIO = (0.5, 2.0)
MG_UNIT = (("mG", 1.0),)
# HIGHRES_IMU xmag..zmag: gauss says the MAVLink XML; ArduPilot (4.7, GCS_Common.cpp
# send_highres_imu) sends get_field() * 1000, i.e. mG x 1000.  The magnitudes differ 10^6-fold.
HIGHRES_MAG_UNITS = (("gauss (the MAVLink definition)", MG_PER_GAUSS),
                     ("mG x 1000 (ArduPilot sends get_field() * 1000)", 1e-3))


@dataclass(frozen=True)
class FieldUnit:
    """The unit chosen for a magnetometer source: ``scale_to_mG`` times the value as sent is mG;
    ``magnitude_mG`` the field's length judged; ``plausible`` whether it is within the range."""
    source: str
    unit: str
    scale_to_mG: float
    magnitude_mG: float
    plausible: bool
    why: str

    def as_dict(self) -> dict:
        return {"source": self.source, "unit": self.unit, "scale_to_mG": self.scale_to_mG,
                "magnitude_mG": round(self.magnitude_mG, 1) if math.isfinite(self.magnitude_mG) else None,
                "plausible": self.plausible, "why": self.why}


def expected_field_mG(lat_deg: float, lon_deg: float, alt_m: float, unix_s: float | None) -> float | None:
    """The WMM total intensity [mG] at a place (None when the place is not a place)."""
    from estimators.geomag import decimal_year_from_unix, earth_field

    if not _finite(lat_deg, lon_deg, alt_m) or not (-90 <= lat_deg <= 90 and -180 <= lon_deg <= 180):
        return None
    year = decimal_year_from_unix(unix_s if unix_s is not None and math.isfinite(unix_s) else 1.75e9)
    return float(earth_field(lat_deg, lon_deg, alt_m, year).field_strength_mG)


def field_plausible(magnitude_mG: float, expected_mG: float | None = None) -> bool:
    """|B| within 0.5-2x the WMM intensity (``expected_mG``), or 150-1000 mG where no place is known."""
    if not math.isfinite(magnitude_mG):
        return False
    if expected_mG is not None and math.isfinite(expected_mG) and expected_mG > 0:
        return PLAUSIBLE_WMM_RATIO[0] <= magnitude_mG / expected_mG <= PLAUSIBLE_WMM_RATIO[1]
    return PLAUSIBLE_FIELD_mG[0] <= magnitude_mG <= PLAUSIBLE_FIELD_mG[1]


def judge_field_unit(source: str, magnitude_as_sent: float, units=MG_UNIT,
                     expected_mG: float | None = None) -> FieldUnit:
    """The unit of a magnetometer source, judged by its field's length: of ``units`` ((name,
    scale to mG), the documented one first) the one whose |B| x scale is nearest the expected
    field in ratio, min |ln(|B| s / E)|, E the WMM intensity where known, else the geometric
    middle of PLAUSIBLE_FIELD_mG (387 mG).  With one unit it is only checked.  The one rule for
    the live decoder and the log readers (which decode through it)."""
    target = expected_mG if expected_mG is not None and expected_mG > 0 else math.sqrt(
        PLAUSIBLE_FIELD_mG[0] * PLAUSIBLE_FIELD_mG[1])
    against = f"the WMM's {expected_mG:.0f} mG" if expected_mG is not None and expected_mG > 0 else \
        f"the plausible {PLAUSIBLE_FIELD_mG[0]:.0f}-{PLAUSIBLE_FIELD_mG[1]:.0f} mG (no position yet)"
    m = abs(float(magnitude_as_sent))
    if not math.isfinite(m) or m == 0.0:
        name, scale = units[0]
        return FieldUnit(source, name, scale, math.nan, False, f"|B| {m:g} as sent: unit not judged, {name} assumed")
    name, scale = min(units, key=lambda u: abs(math.log(m * u[1] / target)))
    mag = m * scale
    ok = field_plausible(mag, expected_mG)
    others = [f"{n} would give {m * sc:.3g} mG" for n, sc in units if n != name]
    why = (f"|B| {mag:.0f} mG read as {name}, against {against}" + ("; " + ", ".join(others) if others else "")
           + ("" if ok else "; implausible in every unit known: the source is used with a warning"))
    return FieldUnit(source, name, scale, mag, ok, why)


def rank_mag_source(instance: int, magnitude_mG: float, n_samples: int, autopilot: str | None,
                    expected_mG: float | None = None) -> tuple:
    """Sort key (larger is better) of a compass's candidate sources: a plausible field first,
    then, for ArduPilot, RAW_IMU/SCALED_IMUn before HIGHRES_IMU (whose unit it does not send as
    documented), then the most samples."""
    return (field_plausible(magnitude_mG, expected_mG), not (autopilot == "ardupilot" and instance >= 20),
            n_samples)


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def judge_first_field(instance: int, sent: tuple[float, float, float], units, t: float,
                      place: tuple[float, float, float] | None, start_unix_s: float | None) -> FieldUnit | None:
    """The unit of a magnetometer source judged at its first sample (``judge_field_unit``) against
    the WMM at ``place`` (the last GPS position, None before one) on the date of t; None when the
    sample is all zero (the next one is judged)."""
    m = math.sqrt(sum(v * v for v in sent))
    if m == 0.0:
        return None
    expected = None
    if place is not None:
        expected = expected_field_mG(*place, start_unix_s + t if start_unix_s is not None else None)
    return judge_field_unit(source_name(instance), m, units, expected)


class MavlinkDecoder:
    """Turns pymavlink message objects into samples, with units exactly as the MAVLink XML says.

    SCALED_IMU/2/3 and ArduPilot's RAW_IMU: acc mG (milli-g), gyro mrad/s, mag mgauss.
    HIGHRES_IMU: acc m/s^2, gyro rad/s, mag gauss, or mG x 1000 as ArduPilot sends it: each
    magnetometer source's unit is judged at its first sample by its field's length
    (``judge_field_unit``, ``mag_units`` says which and why).  ATTITUDE: rad.  GPS_RAW_INT: degE7, mm,
    cm/s, cdeg.  Messages from a GCS (our own heartbeats echoed, other ground stations) are
    ignored.  ``vehicle_sysid``: the system to decode (None: the first autopilot heartbeat's);
    messages of other systems give no samples.
    """

    def __init__(self, vehicle_sysid: int | None = None) -> None:
        self.clock = BootClock()
        self.autopilot: str | None = None
        self.vehicle_sysid: int | None = vehicle_sysid
        self.start_unix_s: float | None = None
        self.warnings: Counter = Counter()
        self._last_gps_raw_t = -math.inf
        self._last_fix_type = 3
        self._place: tuple[float, float, float] | None = None     # the last GPS position (WMM)
        self.mag_units: dict[str, dict] = {}      # source name -> FieldUnit.as_dict(), judged at its first sample
        self._mag_scale: dict[int, float] = {}
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
            "MAG_CAL_PROGRESS": self._mag_cal_progress,
            "MAG_CAL_REPORT": self._mag_cal_report,
            "COMMAND_LONG": self._command_long,
            "SENSOR_OFFSETS": self._sensor_offsets,
            "VFR_HUD": self._vfr_hud,
            "SYSTEM_TIME": self._system_time,
            "SYS_STATUS": self._sys_status,
        }

    def _t(self, msg, arrival_s: float) -> float:
        """The message's time on the boot clock: its time_boot_ms, or (RAW_IMU, HIGHRES_IMU) its
        time_usec where that is a boot time; ``_sent`` where it has neither."""
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is None:
            usec = getattr(msg, "time_usec", None)
            boot_ms = None if usec is None else float(boot_ms_of_usec(usec))
            if boot_ms is None or math.isnan(boot_ms):
                return self._sent(arrival_s)
        return self.clock(boot_ms, arrival_s)

    def _sent(self, arrival_s: float) -> float:
        """When a message without a boot time (GPS_RAW_INT: GPS time; SYS_STATUS, VFR_HUD: none;
        RAW_IMU with a UNIX time_usec) left the vehicle: its arrival less the link's delay on the
        last boot-timed message before it (a radio backlog delays the current as much as the
        attitude sent beside it)."""
        return arrival_s - self.clock.lag_s

    def decode(self, msg, arrival_s: float) -> list[Sample]:
        """Samples carried by one message; ``arrival_s`` is its time on the log's time base."""
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return []
        if msg.get_type() not in ("HEARTBEAT", "COMMAND_LONG") and self._from_gcs(msg):
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
            t = self._t(msg, arrival_s)
            out: list[Sample] = []
            mag = (float(msg.xmag), float(msg.ymag), float(msg.zmag))
            if mag != (0.0, 0.0, 0.0):  # all-zero = no compass on this instance
                out += self._judge(instance, mag, MG_UNIT, t)
                out.append(MagSample(t, mag, instance))
            gyro, acc = scaled_imu_to_si((msg.xgyro, msg.ygyro, msg.zgyro), (msg.xacc, msg.yacc, msg.zacc))
            out.append(ImuSample(t, tuple(gyro.tolist()), tuple(acc.tolist()), instance))
            return out
        return decode

    def _highres_imu(self, msg, arrival_s: float) -> list[Sample]:
        t = self._t(msg, arrival_s)
        updated = msg.fields_updated
        out: list[Sample] = []
        if updated & 0x1C0 or not updated:
            sent = (float(msg.xmag), float(msg.ymag), float(msg.zmag))
            if _finite(*sent):
                out += self._judge(20 + msg.id, sent, HIGHRES_MAG_UNITS, t)
                scale = self._mag_scale.get(20 + msg.id, MG_PER_GAUSS)
                out.append(MagSample(t, (sent[0] * scale, sent[1] * scale, sent[2] * scale), 20 + msg.id))
            else:
                self.warnings["NaN magnetometer field"] += 1
        gyro = (msg.xgyro, msg.ygyro, msg.zgyro)
        acc = (msg.xacc, msg.yacc, msg.zacc)
        if _finite(*gyro, *acc):
            out.append(ImuSample(t, gyro, acc, 20 + msg.id))
        else:
            self.warnings["NaN IMU field"] += 1
        return out

    def _judge(self, instance: int, sent: tuple[float, float, float], units, t: float) -> list[Sample]:
        """The unit of a magnetometer source, judged at its first non-zero sample
        (``judge_first_field``), kept in ``mag_units`` (the live link says it as a "mag_unit" status)."""
        if instance in self._mag_scale:
            return []
        unit = judge_first_field(instance, sent, units, t, self._place, self.start_unix_s)
        if unit is None:
            return []
        self._mag_scale[instance] = unit.scale_to_mG
        self.mag_units[unit.source] = unit.as_dict()
        if not unit.plausible:
            self.warnings[f"{unit.source}: implausible magnetometer field ({unit.why})"] += 1
        return []

    def _attitude(self, msg, arrival_s: float) -> list[Sample]:
        if not _finite(msg.roll, msg.pitch, msg.yaw):
            self.warnings["NaN attitude field"] += 1
            return []
        return [AttitudeSample(self._t(msg, arrival_s), msg.roll, msg.pitch, msg.yaw)]

    def _attitude_quaternion(self, msg, arrival_s: float) -> list[Sample]:
        q, valid = normalised_quaternion(msg.q1, msg.q2, msg.q3, msg.q4)
        if not valid:
            self.warnings["invalid attitude quaternion"] += 1
            return []
        return [AttitudeSample(self._t(msg, arrival_s), *(float(a) for a in euler_from_quaternion(*q)))]

    def _gps_raw_int(self, msg, arrival_s: float) -> list[Sample]:
        t = self._last_gps_raw_t = self._sent(arrival_s)
        self._last_fix_type = int(msg.fix_type)
        if msg.fix_type < 2 or (msg.lat == 0 and msg.lon == 0):
            return []
        lat, lon, alt, vn, ve, vd = (float(v) for v in gps_raw_int_to_si(msg.lat, msg.lon, msg.alt, msg.vel, msg.cog))
        self._place = (lat, lon, alt)
        return [GpsSample(t, lat, lon, alt, (vn, ve, vd), int(msg.fix_type))]

    def _global_position_int(self, msg, arrival_s: float) -> list[Sample]:
        """The autopilot's fused position: used only when no GPS_RAW_INT came for 3 s."""
        t = self._t(msg, arrival_s)
        if t - self._last_gps_raw_t < 3.0 or (msg.lat == 0 and msg.lon == 0):
            return []
        lat, lon, alt, vn, ve, vd = (float(v) for v in global_position_int_to_si(msg.lat, msg.lon, msg.alt, msg.vx,
                                                                                  msg.vy, msg.vz))
        return [GpsSample(t, lat, lon, alt, (vn, ve, vd), self._last_fix_type)]

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

    def _mag_cal_progress(self, msg, t: float) -> list[Sample]:
        pct = float(msg.completion_pct)
        return [StatusSample(t, "mag_cal_progress", f"compass {msg.compass_id}: {msg.completion_pct}%"),
                MagCalSample(t, "progress", int(msg.compass_id), int(msg.cal_mask), pct, int(msg.cal_status))]

    def _mag_cal_report(self, msg, t: float) -> list[Sample]:
        """MAG_CAL_REPORT: offsets in ArduPilot's COMPASS_OFS convention (mG), the fit's RMS
        residual (fitness, mG); orientation and scale factor are MAVLink 2 extensions."""
        g = lambda name: float(getattr(msg, name, math.nan))  # noqa: E731
        report = MagCalSample(
            t, "report", int(msg.compass_id), int(msg.cal_mask), 100.0, int(msg.cal_status), int(msg.autosaved),
            float(msg.fitness), (g("ofs_x"), g("ofs_y"), g("ofs_z")), (g("diag_x"), g("diag_y"), g("diag_z")),
            (g("offdiag_x"), g("offdiag_y"), g("offdiag_z")), g("scale_factor"),
            (g("old_orientation"), g("new_orientation"), g("orientation_confidence")))
        return [StatusSample(t, "mag_cal_report", f"compass {msg.compass_id}: status {msg.cal_status}, "
                                                  f"fitness {msg.fitness:.1f}"), report]

    def _command_long(self, msg, t: float) -> list[Sample]:
        """The GCS's onboard-calibration commands (sent to the vehicle, so not filtered as GCS
        traffic); param1 of DO_START_MAG_CAL is the compass mask (0 = all)."""
        kind = MAG_CAL_COMMANDS.get(int(msg.command))
        if kind is None or (self.vehicle_sysid is not None and msg.target_system not in (0, self.vehicle_sysid)):
            return []
        mask = int(msg.param1) if math.isfinite(msg.param1) else 0
        return [MagCalSample(t, kind, -1, mask)]

    def _sensor_offsets(self, msg, t: float) -> list[Sample]:
        """SENSOR_OFFSETS mag_ofs_*: compass 0's COMPASS_OFS in force (int16 mG)."""
        return [OffsetsSample(t, 0, (float(msg.mag_ofs_x), float(msg.mag_ofs_y), float(msg.mag_ofs_z)), 1.0)]

    def _vfr_hud(self, msg, arrival_s: float) -> list[Sample]:
        """VFR_HUD throttle: percent of full throttle (ArduPilot: the motors' throttle output)."""
        thr, valid = vfr_hud_throttle(msg.throttle)
        return [ThrottleSample(self._sent(arrival_s), float(thr))] if valid else []

    def _sys_status(self, msg, arrival_s: float) -> list[Sample]:
        """current_battery is in cA (10 mA); -1 means the autopilot does not measure it."""
        amps, valid = sys_status_current_A(msg.current_battery)
        return [BatterySample(self._sent(arrival_s), float(amps))] if valid else []

    def _system_time(self, msg, t: float) -> list[Sample]:
        if self.start_unix_s is None and msg.time_unix_usec > 1e15:
            self.start_unix_s = msg.time_unix_usec * 1e-6 - t
        return []
