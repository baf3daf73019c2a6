"""Per-instance tables and parameter history, shared by the log readers (assembled in builder.py).

A log may hold up to three compasses and IMUs (ArduPilot RAW_IMU / SCALED_IMU2 / SCALED_IMU3,
DataFlash MAG/MAG2/MAG3 or MAG with an instance column, PX4 sensor_mag instances).  Every one is
kept; the primary (the one ``FlightLog.mag`` / ``imu`` hold, for the single-sensor callers) is
the one with the most samples, ties to the lowest number.  A compass sent in several messages
(ArduPilot: RAW_IMU and HIGHRES_IMU) is read from the one with a plausible field, ArduPilot's
RAW_IMU/SCALED_IMUn before HIGHRES_IMU, then the most samples (``decode.rank_mag_source``).
"""
from __future__ import annotations

from collections import Counter
from typing import Callable

import numpy as np

from ..decode import compass_of_source, rank_mag_source, source_name
from ...samples import CompassTable

Clean = Callable[[np.ndarray, str, Counter], np.ndarray]   # builder.clean_table

__all__ = ["split_compasses", "split_imus", "compact_history", "ardupilot_device_id"]


def ardupilot_device_id(params: dict[str, float], compass: int) -> int | None:
    """COMPASS_DEV_ID / COMPASS_DEV_ID2 / COMPASS_DEV_ID3 of compass 0/1/2 (None when absent or 0)."""
    v = params.get("COMPASS_DEV_ID" + ("" if compass == 0 else str(compass + 1)))
    try:
        return int(v) if v is not None and int(v) != 0 else None
    except (TypeError, ValueError, OverflowError):
        return None


def _sources(rows: np.ndarray) -> dict[int, int]:
    """The source with the most rows for each compass/IMU number (IMUs; compasses: ``_mag_sources``)."""
    best: dict[int, tuple[int, int]] = {}
    for src in np.unique(rows[:, -1]).astype(int).tolist():
        n = int(np.count_nonzero(rows[:, -1] == src))
        k = compass_of_source(src)
        if k not in best or n > best[k][1]:
            best[k] = (src, n)
    return {k: s for k, (s, _) in best.items()}


def _mag_sources(rows: np.ndarray, source_names: dict[int, str], autopilot: str | None,
                 expected_mG: float | None) -> dict[int, tuple[int, str | None]]:
    """For each compass, its source ranked by ``decode.rank_mag_source`` (a plausible median
    |B| first, for ArduPilot RAW_IMU/SCALED_IMUn before HIGHRES_IMU, then the most samples) and a
    note saying why when there was a choice or the field is implausible."""
    cands: dict[int, list[tuple[tuple, int, float, int]]] = {}
    for src in np.unique(rows[:, -1]).astype(int).tolist():
        sel = rows[rows[:, -1] == src, 1:4]
        with np.errstate(invalid="ignore", over="ignore"):
            mag = float(np.nanmedian(np.linalg.norm(sel, axis=1))) if len(sel) else float("nan")
        k = compass_of_source(src)
        cands.setdefault(k, []).append((rank_mag_source(src, mag, len(sel), autopilot, expected_mG), src, mag, len(sel)))
    out: dict[int, tuple[int, str | None]] = {}
    for k, options in cands.items():
        options.sort(key=lambda c: c[0], reverse=True)
        key, src, mag, n = options[0]
        name = lambda s: source_names.get(s) or source_name(s)  # noqa: E731
        against = f"WMM {expected_mG:.0f} mG" if expected_mG else "150-1000 mG"
        note = None
        if len(options) > 1:
            why = "plausible field" if key[0] else "no source has a plausible field"
            if autopilot == "ardupilot" and any(c[1] >= 20 for c in options) and src < 20:
                why += ", ArduPilot: RAW_IMU/SCALED_IMUn preferred to HIGHRES_IMU"
            note = (f"{name(src)} chosen ({why}; median |B| {mag:.0f} mG vs {against}, {n} samples) over "
                    + ", ".join(f"{name(c[1])} (|B| {c[2]:.4g} mG, {c[3]} samples)" for c in options[1:]))
        elif not key[0]:
            note = f"{name(src)}: implausible median |B| {mag:.4g} mG (vs {against}): is its unit right?"
        out[k] = (src, note)
    return out


def _primary(tables: dict[int, np.ndarray]) -> int:
    return max(sorted(tables), key=lambda k: len(tables[k]))


def split_compasses(rows: np.ndarray, source_names: dict[int, str], params: dict[str, float],
                    applied: bool | None, warnings: Counter, clean_table: Clean, autopilot: str | None = None,
                    expected_mG: float | None = None) -> tuple[list[CompassTable], int]:
    """CompassTables from mag rows [t, mx, my, mz, mox, moy, moz, source] (motor offsets NaN when
    not logged) and the primary compass number (0 when there is none); each compass's source is
    chosen by ``_mag_sources`` (``expected_mG``: the WMM intensity at the log's place, or None).
    ``rows`` is consumed: with one source its motor columns are zeroed in place (no copy)."""
    if not len(rows):
        return [], 0
    sources = _mag_sources(rows, source_names, autopilot, expected_mG)
    out: list[CompassTable] = []
    for k, (src, note) in sorted(sources.items()):
        mine = rows[:, -1] == src
        sel = rows[:, :-1] if mine.all() else rows[mine, :-1]       # one source: no copy of the rows
        if not sel.flags.writeable:
            sel = sel.copy()
        has_mot = bool(np.isfinite(sel[:, 4:7]).any())
        np.nan_to_num(sel[:, 4:7], copy=False)                     # the motor columns zeroed in place
        table = clean_table(sel, "mag" if k == 0 else f"mag[{k}]", warnings)
        name = source_names.get(src) or source_name(src)
        out.append(CompassTable(k, np.ascontiguousarray(table[:, :4]), name, ardupilot_device_id(params, k), applied,
                                np.ascontiguousarray(table[:, 4:7]) if has_mot else None, note))
    out = [c for c in out if len(c.field)]
    if not out:
        return [], 0
    primary = max(out, key=lambda c: (len(c.field), -c.compass)).compass
    return out, primary


def split_imus(rows: np.ndarray, warnings: Counter, clean_table: Clean) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """{IMU number: [t, gyro, accel]} from rows with the source last, and the primary's table."""
    if not len(rows):
        return {}, np.empty((0, 7))
    sources = _sources(rows)
    tables = {k: clean_table(np.ascontiguousarray(rows[rows[:, -1] == src, :-1]), "imu" if k == 0 else f"imu[{k}]",
                             warnings) for k, src in sorted(sources.items())}
    return tables, tables[_primary(tables)]


def compact_history(entries: list[tuple[float, str, float, float]]) -> list[tuple[float, str, float]]:
    """(t_s, name, value) in time order, keeping an entry only when the value changed: by a whole
    quantum or more for integer sources (SENSOR_OFFSETS and DataFlash MAG Ofs* are the float
    offsets cast to int16, truncated: quantum 1), any change for exact sources (quantum 0).  A
    parameter list re-sent with the same values adds nothing."""
    held: dict[str, float] = {}
    out: list[tuple[float, str, float]] = []
    for t, name, value, quantum in sorted(entries, key=lambda e: e[0]):
        if not np.isfinite(value):
            continue
        last = held.get(name)
        if last is not None and (abs(value - last) < quantum if quantum > 0 else value == last):
            continue
        held[name] = value
        out.append((float(t), name, float(value)))
    return out
