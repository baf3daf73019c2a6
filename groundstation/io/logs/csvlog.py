"""CSV logs (.csv): any IMU, magnetometer-only dumps, with optional attitude, position and current.

Columns (header names, any order, case-insensitive; body frame FRD):

    t_s                         seconds (required with IMU columns; else the row number is used)
    gx, gy, gz                  gyro [rad/s]
    ax, ay, az                  accelerometer specific force [m/s²] (level and still: az ≈ −9.81)
    mx, my, mz                  magnetometer [mG]
    roll_deg, pitch_deg, yaw_deg   an attitude reference (e.g. the autopilot's)
    lat_deg, lon_deg, alt_m     position (WGS84, AMSL); optional vn_mps, ve_mps, vd_mps, fix_type
    current_A                   battery/motor current

A file needs the magnetometer or the IMU group.  Groups may be sampled at different rates: a
row whose cells of a group are all empty has no sample of that group; a partly filled or
non-numeric group is skipped and counted in the log's warnings.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import IngestError
from .builder import clean_table
from ...samples import FlightLog

__all__ = ["read_csv", "CSV_GROUPS"]

CSV_GROUPS: dict[str, tuple[str, ...]] = {
    "gyro": ("gx", "gy", "gz"),
    "accel": ("ax", "ay", "az"),
    "mag": ("mx", "my", "mz"),
    "attitude": ("roll_deg", "pitch_deg", "yaw_deg"),
    "position": ("lat_deg", "lon_deg", "alt_m"),
    "velocity": ("vn_mps", "ve_mps", "vd_mps"),
    "fix": ("fix_type",),
    "current": ("current_A",),
}


def _group_values(rows: list[list[str]], cols: list[int], warnings, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(row mask, values (n, len(cols))) of the rows where every cell of the group is a number."""
    n = len(rows)
    out = np.full((n, len(cols)), np.nan)
    have = np.zeros(n, bool)
    bad = 0
    for i, row in enumerate(rows):
        cells = [row[c].strip() if c < len(row) else "" for c in cols]
        if not any(cells):
            continue
        try:
            out[i] = [float(c) for c in cells]
            have[i] = True
        except ValueError:
            bad += 1
    if bad:
        warnings[f"CSV {name}: rows with empty or non-numeric cells skipped"] += bad
    return have, out


def read_csv(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """Read a CSV log (columns in the module docstring) into a FlightLog in internal units."""
    log = FlightLog(source=str(path), mag_calibration_applied=False)
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        reader = csv.reader(f)
        header = next(reader, [])
        rows = list(reader)
    index = {c.strip().lower(): k for k, c in enumerate(header)}
    present = {g: [index[c.lower()] for c in cols] for g, cols in CSV_GROUPS.items()
               if all(c.lower() in index for c in cols)}
    imu = "gyro" in present and "accel" in present
    if "mag" not in present and not imu:
        raise IngestError(f"{path.name}: CSV needs columns mx,my,mz (milligauss) or gx,gy,gz (rad/s) with "
                          f"ax,ay,az (m/s²); found {', '.join(index) or 'none'}")
    if imu and "t_s" not in index:
        raise IngestError(f"{path.name}: CSV with IMU columns needs a t_s column (seconds)")
    warnings = log.warnings
    if "t_s" in index:
        have_t, t = _group_values(rows, [index["t_s"]], warnings, "t_s")
        t = t[:, 0]
    else:
        have_t, t = np.ones(len(rows), bool), np.arange(len(rows), dtype=float)
    values = {g: _group_values(rows, cols, warnings, g) for g, cols in present.items()}
    log.message_counts["csv rows"] = len(rows)

    def table(*groups: str, scale: tuple[float, ...] | None = None) -> np.ndarray:
        have = have_t & np.logical_and.reduce([values[g][0] for g in groups])
        cols = np.column_stack([t[have]] + [values[g][1][have] for g in groups])
        return cols * np.asarray((1.0,) + scale) if scale else cols

    if "mag" in values:
        log.mag = clean_table(table("mag"), "mag", warnings)
    if imu:
        log.imu = clean_table(table("gyro", "accel"), "imu", warnings)
    if "attitude" in values:
        log.attitude = clean_table(table("attitude", scale=(math.radians(1.0),) * 3), "attitude", warnings)
    if "position" in values:
        log.gps = clean_table(_gps_table(t, have_t, values), "gps", warnings)
    if "current" in values:
        log.battery = clean_table(table("current"), "battery", warnings)
    _rebase_time(log)
    return log


def _gps_table(t: np.ndarray, have_t: np.ndarray, values: dict) -> np.ndarray:
    """GPS rows (t, lat, lon, alt, vn, ve, vd, fix): velocity NaN and fix 3 when not given."""
    have = have_t & values["position"][0]
    n = int(have.sum())
    vel = values["velocity"][1][have] if "velocity" in values else np.full((n, 3), np.nan)
    fix = values["fix"][1][have, 0] if "fix" in values else np.full(n, 3.0)
    fix = np.where(np.isfinite(fix), fix, 3.0)
    return np.column_stack([t[have], values["position"][1][have], vel, fix])


def _rebase_time(log: FlightLog) -> None:
    """Times from the first sample of any table (t_s = 0 at the start of the log)."""
    tables = ("mag", "imu", "attitude", "gps", "battery")
    starts = [getattr(log, k)[0, 0] for k in tables if len(getattr(log, k))]
    if not starts:
        return
    t0 = min(starts)
    for k in tables:
        arr = getattr(log, k)
        if len(arr):
            arr[:, 0] -= t0
