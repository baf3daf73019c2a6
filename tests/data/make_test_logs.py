"""Regenerate the small logs in tests/data (deterministic).  Run:  python tests/data/make_test_logs.py

Every file encodes known values so the reader tests can check units end to end:
  - magnetometer: a field of 400 mG rotating about Z at 36 deg/s, z = -300 mG
  - gyro z = 0.6283 rad/s, accel z = -9.80665 m/s^2 (level, 1 g up)
  - attitude roll 0.1 rad, pitch -0.05 rad, yaw following the rotation
  - GPS at 30.26 N, 120.12 E, 50 m, RTK fixed (fix_type 6), 2 m/s north
"""
from __future__ import annotations

import json
import math
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent.parent))

import groundstation  # noqa: E402,F401  (selects MAVLink 2 before pymavlink loads)
from groundstation.io.mavlink import TlogWriter, mavlink2 as m  # noqa: E402

START_UNIX = 1_780_000_000.0  # 2026-05-28
DURATION_S = 10.0
RATE_HZ = 50
LAT, LON, ALT = 30.26, 120.12, 50.0
MISSION = [(30.26, 120.12, 0.0), (30.2600, 120.1200, 20.0), (30.2610, 120.1210, 20.0)]  # home, A, B


def truth_mag_mG(t: float) -> tuple[float, float, float]:
    a = math.radians(36.0) * t
    return 400.0 * math.cos(a), -400.0 * math.sin(a), -300.0


def tlog_messages() -> list[tuple[float, object]]:
    """(seconds since start, message) for the reference tlog."""
    msgs: list[tuple[float, object]] = []
    n = int(DURATION_S * RATE_HZ)
    msgs.append((0.0, m.MAVLink_system_time_message(int(START_UNIX * 1e6), 0)))
    for i, wp in enumerate(MISSION):
        if i == 0:
            msgs.append((0.0, m.MAVLink_mission_count_message(255, 190, len(MISSION), 0)))
        msgs.append((0.0, m.MAVLink_mission_item_int_message(
            255, 190, i, 0 if i == 0 else 3, 16, 0, 1, 0, 0, 0, 0,
            int(wp[0] * 1e7), int(wp[1] * 1e7), wp[2], 0)))
    msgs.append((0.0, m.MAVLink_param_value_message(b"COMPASS_OFS_X", 12.5, 9, 3, 0)))
    msgs.append((0.0, m.MAVLink_statustext_message(6, b"MagStation test log")))
    for k in range(n):
        t = k / RATE_HZ
        boot_ms = int(1000 + t * 1000)
        if k % RATE_HZ == 0:
            msgs.append((t, m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3)))
        mx, my, mz = truth_mag_mG(t)
        msgs.append((t, m.MAVLink_scaled_imu_message(
            boot_ms, 0, 0, -1000, 0, 0, 628, int(round(mx)), int(round(my)), int(round(mz)))))
        yaw = math.radians(36.0) * t
        msgs.append((t, m.MAVLink_attitude_message(boot_ms, 0.1, -0.05, math.atan2(math.sin(yaw), math.cos(yaw)),
                                                  0.0, 0.0, 0.6283)))
        if k % 5 == 0:  # 10 Hz
            msgs.append((t, m.MAVLink_highres_imu_message(      # time_usec on the boot clock, as a vehicle's
                boot_ms * 1000, 0, 0, -9.80665, 0, 0, 0.6283, mx / 1000, my / 1000, mz / 1000,
                1013.0, 0, 0, 20.0, 0x1FF, 1)))
            msgs.append((t, m.MAVLink_gps_raw_int_message(
                int(t * 1e6), 6, int(LAT * 1e7), int(LON * 1e7), int(ALT * 1000), 80, 120, 200, 0, 18)))
        if k % 25 == 0:
            msgs.append((t, m.MAVLink_mag_cal_progress_message(0, 1, 1, 1, int(100 * k / n),
                                                                [0] * 10, 0.0, 0.0, 1.0)))
    return msgs


def write_tlog(path: Path, msgs: list[tuple[float, object]]) -> None:
    path.unlink(missing_ok=True)
    with TlogWriter(path) as w:
        for t, msg in msgs:
            w.write_message(msg, START_UNIX + t)


def write_damaged_tlogs(good: Path) -> None:
    data = bytearray(good.read_bytes())
    # corrupt.tlog: 200 bytes of garbage a third of the way in, a flipped byte (bad CRC) at
    # two thirds, and the last record cut in half.
    third = len(data) // 3
    corrupt = bytes(data[:third]) + bytes((i * 37 + 11) % 256 for i in range(200)) + bytes(data[third:])
    corrupt = bytearray(corrupt)
    corrupt[2 * len(corrupt) // 3] ^= 0xFF
    (HERE / "corrupt.tlog").write_bytes(bytes(corrupt[:-7]))
    # backwards.tlog: the recorder clock jumps back 5 s half-way through.
    msgs = tlog_messages()
    path = HERE / "backwards.tlog"
    path.unlink(missing_ok=True)
    with TlogWriter(path) as w:
        for t, msg in msgs:
            w.write_message(msg, START_UNIX + (t - 5.0 if t >= DURATION_S / 2 else t))
    # nan.tlog: HIGHRES_IMU magnetometer fields NaN for the first second.
    nan_msgs = []
    for t, msg in msgs:
        if msg.get_type() == "HIGHRES_IMU" and t < 1.0:
            msg.xmag = msg.ymag = msg.zmag = float("nan")
        nan_msgs.append((t, msg))
    write_tlog(HERE / "nan.tlog", [(t, x) for t, x in nan_msgs if x.get_type() != "SCALED_IMU"])


# ------------------------------------------------------------------------------ DataFlash .bin

DF_HEAD = b"\xa3\x95"
DF_TYPES = {  # name: (type id, format, columns) -- ArduPilot 4.x layouts
    "FMT": (128, "BBnNZ", "Type,Length,Name,Format,Columns"),
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "MAG": (65, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "IMU": (66, "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "ATT": (67, "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    "GPS": (68, "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "CMD": (69, "QHHHffffLLfB", "TimeUS,CTot,CNum,CId,Prm1,Prm2,Prm3,Prm4,Lat,Lng,Alt,Frame"),
}
STRUCT_CHARS = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d",
                "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I",
                "L": "i", "M": "B", "q": "q", "Q": "Q"}


def _df_struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(STRUCT_CHARS[c] for c in fmt))


def df_record(name: str, *values: object) -> bytes:
    type_id, fmt, _ = DF_TYPES[name]
    vals = [v.encode() if isinstance(v, str) else v for v in values]
    return DF_HEAD + bytes([type_id]) + _df_struct(fmt).pack(*vals)


def write_dataflash(path: Path) -> None:
    out = bytearray()
    for name, (type_id, fmt, cols) in DF_TYPES.items():
        out += df_record("FMT", type_id, 3 + _df_struct(fmt).size, name, fmt, cols)
    out += df_record("PARM", 0, "COMPASS_OFS_X", 12.5)
    out += df_record("PARM", 0, "COMPASS_DIA_X", 1.02)
    for i, (lat, lon, alt) in enumerate(MISSION):
        out += df_record("CMD", 0, len(MISSION), i, 16, 0, 0, 0, 0, int(lat * 1e7), int(lon * 1e7), alt, 3)
    gps_epoch_s = START_UNIX - 315964800 + 18
    for k in range(int(DURATION_S * RATE_HZ)):
        t = k / RATE_HZ
        t_us = int(5_000_000 + t * 1e6)
        mx, my, mz = truth_mag_mG(t)
        yaw_deg = (36.0 * t) % 360.0
        out += df_record("IMU", t_us, 0, 0.0, 0.0, 0.6283, 0.0, 0.0, -9.80665, 0, 0, 25.0, 1, 1, 400, 400)
        out += df_record("MAG", t_us, 0, int(round(mx)), int(round(my)), int(round(mz)), 12, 0, 0, 0, 0, 0, 1, t_us)
        out += df_record("ATT", t_us, 0, int(round(math.degrees(0.1) * 100)), 0,
                         int(round(math.degrees(-0.05) * 100)), 0, int(round(yaw_deg * 100)), 0, 0, 3)
        if k % 5 == 0:
            tow = gps_epoch_s + t
            week, ms = int(tow // 604800), int((tow % 604800) * 1000)
            out += df_record("GPS", t_us, 0, 6, ms, week, 18, 80, int(LAT * 1e7), int(LON * 1e7),
                             int(ALT * 100), 2.0, 0.0, 0.0, 0.0, 0)
    path.write_bytes(bytes(out))
    (HERE / "truncated.bin").write_bytes(bytes(out[: len(out) // 2 + 13]))


def write_text_files() -> None:
    lines = ["QGC WPL 110"]
    for i, (lat, lon, alt) in enumerate(MISSION):
        lines.append("\t".join(str(v) for v in (i, int(i == 0), 0 if i == 0 else 3, 16, 0, 0, 0, 0,
                                                f"{lat:.7f}", f"{lon:.7f}", f"{alt:.2f}", 1)))
    (HERE / "mission.waypoints").write_text("\n".join(lines) + "\n")
    items = [{"type": "SimpleItem", "command": 22, "params": [0, 0, 0, None, 0, 0, 20]}]
    items += [{"type": "SimpleItem", "command": 16, "frame": 3, "params": [0, 0, 0, None, lat, lon, alt]}
              for lat, lon, alt in MISSION[1:]]
    plan = {"fileType": "Plan", "version": 1, "mission": {"items": items, "plannedHomePosition": list(MISSION[0])}}
    (HERE / "mission.plan").write_text(json.dumps(plan, indent=1) + "\n")
    rows = ["t_s,mx,my,mz,roll_deg,pitch_deg,yaw_deg"]
    for k in range(200):
        t = k * 0.05
        mx, my, mz = truth_mag_mG(t)
        rows.append(f"{t:.2f},{mx:.2f},{my:.2f},{mz:.2f},5.73,-2.86,{(36 * t) % 360:.2f}")
    rows.insert(50, "1.23,oops,,")
    rows.insert(80, "4.00,nan,1,2")
    (HERE / "mag.csv").write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    good = HERE / "reference.tlog"
    write_tlog(good, tlog_messages())
    write_damaged_tlogs(good)
    write_dataflash(HERE / "reference.bin")
    write_text_files()
    (HERE / "garbage.tlog").write_bytes(bytes((i * 131 + 7) % 256 for i in range(4096)))
    print("wrote", ", ".join(sorted(p.name for p in HERE.iterdir() if p.suffix != ".py")))
