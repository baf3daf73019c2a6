"""ArduPilot DataFlash records -> typed samples, for every firmware generation we meet.

Timing: ``TimeUS`` (µs since boot, ArduPilot 3.3+) or ``TimeMS`` (ms since boot, 2014–2015
logs).  In the old GPS record ``TimeMS`` is the GPS time of week and the boot time is ``T``;
records without a time of their own (old PARM, CMD) take the last time seen.

Units (ArduPilot's LogStructure, read with pymavlink's DFReader, which applies the format's
multipliers): MAG/MAG2/MAG3 (or MAG with an instance column ``I``) mGauss with OfsX.. (COMPASS_OFS
in force, int16) and the motor compensation MOfsX.. / MOX..; IMU rad/s and m/s²; ATT (and AHR2, XKF1, NKF1, EKF1) degrees;
GPS degrees, m, m/s; CURR Curr in cA as int16 ('h', 3.1/3.2) or A ('c'/'f'), ThrOut 0..1000;
BAT/BATT Curr in A; CTUN ThO 0..1 (ThrOut 0..1000 in old logs); RCOU PWM µs; PARM Name, Value.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..decode import MAG_CAL_COMMANDS, MAV_CMD_NAV_WAYPOINT
from ...samples import (AttitudeSample, BatterySample, GpsSample, ImuSample, MagCalSample, MagSample, MissionSample,
                        ParamSample, Sample, StatusSample, ThrottleSample)

__all__ = ["DataFlashDecoder", "WANTED", "THROTTLE_PRIORITY", "att_rad", "gps_velocity_ned", "curr_amps",
           "rcou_throttle"]

WANTED = {"MAG", "MAG2", "MAG3", "IMU", "IMU2", "IMU3", "ATT", "GPS", "PARM", "CMD", "BAT", "BATT", "CURR",
          "CTUN", "RCOU", "MSG", "MAVC"} | {"AHR2", "XKF1", "NKF1", "EKF1"}   # other attitude estimators
THROTTLE_PRIORITY = ("CTUN", "CURR", "RCOU")     # best throttle source first
_SPLIT = {"MAG": 0, "MAG2": 1, "MAG3": 2, "IMU": 0, "IMU2": 1, "IMU3": 2}


# Unit conversions, numpy ufuncs: the per-record decoder calls them with scalars, the bulk reader
# (dataflash.py) with columns, so both give the same numbers.

def att_rad(deg):
    """ATT Roll/Pitch/Yaw degrees -> rad."""
    return np.radians(deg)


def gps_velocity_ned(spd_mps, gcrs_deg, vz_mps) -> tuple:
    """GPS ground speed along the course (deg from north) and VZ -> (vn, ve, vd) m/s."""
    crs = np.radians(gcrs_deg)
    return spd_mps * np.cos(crs), spd_mps * np.sin(crs), vz_mps


def curr_amps(curr, centiamps: bool):
    """CURR Curr: cA when stored as int16 ('h'/'H', ArduPilot 3.1/3.2), already A otherwise."""
    return np.asarray(curr, dtype=float) / (100.0 if centiamps else 1.0)


def rcou_throttle(c1, c2, c3, c4):
    """Mean of the first four motor outputs, 1000-2000 us -> 0..1 (clipped)."""
    return np.clip(((c1 + c2 + c3 + c4) / 4.0 - 1000.0) / 1000.0, 0.0, 1.0)


def _instance(m, mtype: str) -> int:
    for name in ("I", "Inst", "Instance"):
        v = getattr(m, name, None)
        if v is not None:
            return int(v)
    return _SPLIT.get(mtype, 0)


def _column_char(m, column: str) -> str:
    try:
        return m.fmt.format[m.fmt.columns.index(column)]
    except (AttributeError, ValueError, IndexError):
        return ""


class DataFlashDecoder:
    """One DataFlash message -> samples (plus parameter-history entries and throttle rows, which
    the reader collects itself).  ``t_s`` of the samples: seconds since the first timed record."""

    def __init__(self) -> None:
        self.t0_s: float | None = None
        self.last_t = 0.0
        self.gps_week_ms: tuple[float, float, float] | None = None     # (week, ms of week, t_s)
        self.history: list[tuple[float, str, float, float]] = []       # t, name, value, quantum
        self.throttle: dict[str, list[tuple[float, float]]] = {k: [] for k in THROTTLE_PRIORITY}
        self.source_names: dict[int, str] = {}
        self._last_ofs: dict[int, tuple] = {}
        self._handlers: dict[str, Callable] = {
            "MAG": self._mag, "MAG2": self._mag, "MAG3": self._mag, "IMU": self._imu, "IMU2": self._imu,
            "IMU3": self._imu, "ATT": self._att, "GPS": self._gps, "PARM": self._parm, "CMD": self._cmd,
            "BAT": self._bat, "BATT": self._bat, "CURR": self._curr, "CTUN": self._ctun, "RCOU": self._rcou,
            "MSG": self._msg, "MAVC": self._mavc,
            "AHR2": self._other_att, "XKF1": self._other_att, "NKF1": self._other_att, "EKF1": self._other_att,
        }

    # ------------------------------------------------------------------ time
    def _boot_s(self, m, mtype: str) -> float | None:
        us = getattr(m, "TimeUS", None)
        if us is not None:
            return float(us) * 1e-6
        if mtype == "GPS" and getattr(m, "Week", None) is not None:      # old GPS: TimeMS is GPS time
            boot_ms = getattr(m, "T", None)
            return None if boot_ms is None else float(boot_ms) * 1e-3
        ms = getattr(m, "TimeMS", None)
        return None if ms is None else float(ms) * 1e-3

    def time_of(self, m, mtype: str) -> float:
        boot = self._boot_s(m, mtype)
        if boot is None or mtype in ("PARM", "CMD") and self.t0_s is None:
            return self.last_t
        if self.t0_s is None:
            self.t0_s = boot
        self.last_t = boot - self.t0_s
        return self.last_t

    def decode(self, m, mtype: str) -> list[Sample]:
        handler = self._handlers.get(mtype)
        return [] if handler is None else handler(m, mtype, self.time_of(m, mtype))

    # ------------------------------------------------------------------ messages
    def _mag(self, m, mtype: str, t: float) -> list[Sample]:
        k = _instance(m, mtype)
        self.source_names.setdefault(k, mtype if mtype != "MAG" or getattr(m, "I", None) is None else f"MAG[{k}]")
        n = "" if k == 0 else str(k + 1)
        ofs = tuple(getattr(m, f"Ofs{a}", None) for a in "XYZ")
        if None not in ofs and ofs != self._last_ofs.get(k):       # every record repeats them: keep changes
            self._last_ofs[k] = ofs
            q = 1.0 if _column_char(m, "OfsX") in "hH" else 0.0
            self.history += [(t, f"COMPASS_OFS{n}_{a}", float(v), q) for a, v in zip("XYZ", ofs)]
        mot = [getattr(m, f"MOfs{a}", getattr(m, f"MO{a}", None)) for a in "XYZ"]
        motor = None if None in mot else tuple(float(v) for v in mot)
        return [MagSample(t, (float(m.MagX), float(m.MagY), float(m.MagZ)), k, motor)]

    def _imu(self, m, mtype: str, t: float) -> list[Sample]:
        return [ImuSample(t, (m.GyrX, m.GyrY, m.GyrZ), (m.AccX, m.AccY, m.AccZ), _instance(m, mtype))]

    def _att(self, m, mtype: str, t: float) -> list[Sample]:
        return [AttitudeSample(t, *(float(att_rad(v)) for v in (m.Roll, m.Pitch, m.Yaw)))]

    def _other_att(self, m, mtype: str, t: float) -> list[Sample]:
        """AHR2 (DCM, or the backup estimator), XKF1 (EKF3), NKF1 (EKF2), EKF1 (EKF1, 2014–2015):
        Roll, Pitch, Yaw in degrees; the first core only (``C`` = 0)."""
        if int(getattr(m, "C", 0) or 0) != 0:
            return []
        return [AttitudeSample(t, math.radians(m.Roll), math.radians(m.Pitch), math.radians(m.Yaw), mtype)]

    def _gps(self, m, mtype: str, t: float) -> list[Sample]:
        if _instance(m, mtype) != 0 or m.Status < 2:
            return []
        course_deg = m.GCrs
        week, ms = getattr(m, "GWk", getattr(m, "Week", 0)), getattr(m, "GMS", None)
        if ms is None and getattr(m, "Week", None) is not None:
            ms = m.TimeMS
        if self.gps_week_ms is None and week and ms is not None and week > 0:
            self.gps_week_ms = (float(week), float(ms), t)
        vel = tuple(float(v) for v in gps_velocity_ned(m.Spd, course_deg, float(getattr(m, "VZ", math.nan))))
        return [GpsSample(t, m.Lat, m.Lng, m.Alt, vel, int(m.Status))]

    def _parm(self, m, mtype: str, t: float) -> list[Sample]:
        return [ParamSample(t, str(m.Name), float(m.Value))]

    def _cmd(self, m, mtype: str, t: float) -> list[Sample]:
        if m.CId != MAV_CMD_NAV_WAYPOINT:
            return []
        return [MissionSample(t, int(m.CNum), m.Lat, m.Lng, m.Alt)]

    def _bat(self, m, mtype: str, t: float) -> list[Sample]:
        return [BatterySample(t, float(m.Curr))] if _instance(m, mtype) == 0 else []     # A

    def _curr(self, m, mtype: str, t: float) -> list[Sample]:
        """Old CURR: current in cA when stored as int16 ('h'), already A when 'c' or float."""
        amps = float(curr_amps(m.Curr, _column_char(m, "Curr") in "hH"))
        thr = getattr(m, "ThrOut", None)
        if thr is not None:
            self.throttle["CURR"].append((t, float(thr) / 1000.0))
        return [BatterySample(t, amps)]

    def _ctun(self, m, mtype: str, t: float) -> list[Sample]:
        tho = getattr(m, "ThO", None)
        if tho is not None:
            self.throttle["CTUN"].append((t, float(tho)))
        elif getattr(m, "ThrOut", None) is not None:
            self.throttle["CTUN"].append((t, float(m.ThrOut) / 1000.0))
        return []

    def _rcou(self, m, mtype: str, t: float) -> list[Sample]:
        """Mean of the first four motor outputs, 1000–2000 µs -> 0..1 (a rough throttle: used only
        when neither CTUN nor CURR gives one)."""
        pwm = [getattr(m, f"C{i}", None) for i in range(1, 5)]
        if None not in pwm:
            self.throttle["RCOU"].append((t, float(rcou_throttle(*pwm))))
        return []

    def _mavc(self, m, mtype: str, t: float) -> list[Sample]:
        """MAVC: a MAVLink command the vehicle received (Cmd, P1..P4, Res = MAV_RESULT).  ArduPilot
        4.7 logs its onboard calibration only this way (no MAG_CAL_REPORT-like record; the accepted
        values are PARM records): DO_START/ACCEPT/CANCEL_MAG_CAL it accepted (Res 0) are events."""
        kind = MAG_CAL_COMMANDS.get(int(m.Cmd))
        if kind is None or int(m.Res) != 0:
            return []
        mask = int(m.P1) if kind == "start" and math.isfinite(m.P1) else 0
        return [MagCalSample(t, kind, -1, mask)]

    def _msg(self, m, mtype: str, t: float) -> list[Sample]:
        return [StatusSample(t, "statustext", str(m.Message))]

    def throttle_samples(self) -> tuple[str | None, list[Sample]]:
        """(source, ThrottleSamples) of the best throttle source present."""
        for name in THROTTLE_PRIORITY:
            rows = self.throttle[name]
            if rows:
                return name, [ThrottleSample(t, v) for t, v in rows]
        return None, []
