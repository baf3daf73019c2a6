"""ArduPilot DataFlash logs (.bin) through pymavlink's DFReader."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

from ..decode import MAV_CMD_NAV_WAYPOINT
from ..errors import IngestError
from .builder import LogBuilder
from ...samples import AttitudeSample, BatterySample, FlightLog, GpsSample, ImuSample, MagSample, MissionSample, ParamSample

__all__ = ["read_dataflash"]


def read_dataflash(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """ArduPilot DataFlash .bin: MAG/MAG2 (mG), IMU (rad/s, m/s^2), ATT (deg), GPS, PARM, CMD."""
    from pymavlink import DFReader

    try:
        reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    except Exception as err:  # pymavlink raises bare exceptions on unreadable headers
        raise IngestError(f"{path.name}: not a readable DataFlash log ({type(err).__name__})") from err
    builder = LogBuilder(str(path))
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
