"""Assembling samples into a FlightLog (tables sorted, damage counted) and back into a stream."""
from __future__ import annotations

from array import array
from collections import Counter
from collections.abc import Sequence
from typing import Iterator

import numpy as np

from ...samples import (AttitudeSample, BatterySample, FlightLog, GpsSample, ImuSample, MagCalSample, MagSample,
                        MissionSample, OffsetsSample, ParamSample, Sample, StatusSample, ThrottleSample)
from ..decode import expected_field_mG
from .instances import compact_history, split_compasses, split_imus
from ..params import param_value_problem

__all__ = ["LogBuilder", "clean_table", "drop_time_outliers", "iter_samples", "SampleTimeline", "column_table",
           "in_record_order"]


NAN3 = (float("nan"),) * 3


# columns while collecting: mag t, field, logged motor offset (NaN when not logged), source; imu t,
# gyro, accel, source
WIDTHS = {"mag": 8, "imu": 8, "attitude": 4, "gps": 8, "battery": 2, "throttle": 2}


class LogBuilder:
    """Collects samples into a FlightLog: every compass and IMU instance (the most sampled one also
    as ``mag`` / ``imu``), the parameter history and the onboard-calibration events.  Rows are
    kept as flat float64 arrays (8 bytes a value, no Python object per sample).

    ``source_names`` names the compass sources in ``CompassTable.source`` (readers whose instance
    numbers are compass numbers, DataFlash, set it; MAVLink sources are named by the decoder)."""

    def __init__(self, source: str) -> None:
        self.log = FlightLog(source=source)
        self.rows: dict[str, array] = {name: array("d") for name in WIDTHS}
        self.mission: dict[int, tuple[float, float, float]] = {}
        self.history: list[tuple[float, str, float, float]] = []     # t, name, value, quantum
        self.source_names: dict[int, str] = {}
        self.other_attitudes: dict[str, array | np.ndarray] = {}   # AttitudeSample.source -> flat rows

    def add_history(self, t_s: float, name: str, value: float, quantum: float = 0.0) -> None:
        """A parameter value seen at t_s (PARM, PARAM_VALUE, logged offsets) for the history only."""
        self.history.append((t_s, name, value, quantum))

    def set_table(self, name: str, rows: np.ndarray) -> None:
        """Rows of one table at once ([t, ...] as ``WIDTHS`` says, in arrival order), after any
        added one by one."""
        rows = np.ascontiguousarray(rows, dtype=float).reshape(-1, WIDTHS[name])
        held = self.rows[name]
        self.rows[name] = np.concatenate([np.frombuffer(held, dtype=float), rows.ravel()]) if len(held) else rows.ravel()

    def add(self, s: Sample) -> None:
        if isinstance(s, MagSample):
            mot = s.motor_offset_mG if s.motor_offset_mG is not None else NAN3
            self.rows["mag"].extend((s.t_s, *s.mag_body_mG, *mot, s.instance))
        elif isinstance(s, ImuSample):
            self.rows["imu"].extend((s.t_s, *s.gyro_rad_s, *s.accel_mps2, s.instance))
        elif isinstance(s, AttitudeSample):
            rows = self.rows["attitude"] if not s.source else self.other_attitudes.setdefault(s.source, array("d"))
            rows.extend((s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad))
        elif isinstance(s, GpsSample):
            self.rows["gps"].extend((s.t_s, s.lat_deg, s.lon_deg, s.alt_m, *s.vel_ned_mps, s.fix_type))
        elif isinstance(s, BatterySample):
            self.rows["battery"].extend((s.t_s, s.current_A))
        elif isinstance(s, ThrottleSample):
            self.rows["throttle"].extend((s.t_s, s.throttle))
        elif isinstance(s, ParamSample):
            problem = param_value_problem(s.name, s.value)
            if problem is not None:
                self.log.warnings[f"parameter value refused: {problem}"] += 1
                return
            self.log.params[s.name] = s.value
            self.history.append((s.t_s, s.name, s.value, 0.0))
        elif isinstance(s, OffsetsSample):
            n = "" if s.compass == 0 else str(s.compass + 1)
            self.history += [(s.t_s, f"COMPASS_OFS{n}_{a}", v, s.quantum_mG) for a, v in zip("XYZ", s.offsets_mG)]
        elif isinstance(s, MagCalSample):
            self.log.mag_cal.append(s)
        elif isinstance(s, MissionSample):
            self.mission[s.seq] = (s.lat_deg, s.lon_deg, s.alt_m)
        elif isinstance(s, StatusSample):
            self.log.status.append(s)
            if s.kind == "autopilot":
                self.log.autopilot = s.text

    def _expected_field_mG(self) -> float | None:
        """The WMM intensity at the log's median GPS position (None without one), to judge the
        magnetometer sources by (``decode.field_plausible``)."""
        gps = np.frombuffer(self.rows["gps"], dtype=float).reshape(-1, WIDTHS["gps"])
        good = gps[np.isfinite(gps[:, 1]) & np.isfinite(gps[:, 2]) & ((gps[:, 1] != 0) | (gps[:, 2] != 0))]
        if not len(good):
            return None
        lat, lon, alt = (float(np.median(good[:, i])) for i in (1, 2, 3))
        return expected_field_mG(lat, lon, alt, self.log.start_unix_s)

    def finish(self) -> FlightLog:
        log = self.log
        mag = np.frombuffer(self.rows.pop("mag"), dtype=float).reshape(-1, WIDTHS["mag"])
        log.compasses, log.primary_compass = split_compasses(mag, self.source_names, log.params,
                                                             log.mag_calibration_applied, log.warnings, clean_table,
                                                             log.autopilot, self._expected_field_mG())
        del mag
        primary = [c for c in log.compasses if c.compass == log.primary_compass]
        log.mag = primary[0].field if primary else np.empty((0, 4))
        imu = np.frombuffer(self.rows.pop("imu"), dtype=float).reshape(-1, WIDTHS["imu"])
        log.imus, log.imu = split_imus(imu, log.warnings, clean_table)
        del imu
        for name in ("attitude", "gps", "battery", "throttle"):   # one table at a time: its rows are freed after
            arr = np.frombuffer(self.rows.pop(name), dtype=float).reshape(-1, WIDTHS[name])
            setattr(log, name, clean_table(arr, name, log.warnings))
            del arr
        for name, rows in self.other_attitudes.items():
            log.attitudes[name] = clean_table(np.frombuffer(rows, dtype=float).reshape(-1, 4), name, log.warnings)
        log.param_history = compact_history(self.history)
        log.mag_cal.sort(key=lambda e: e.t_s)
        # ArduPilot numbers mission item 0 as home; a mission is the waypoints after it.
        seqs = sorted(self.mission)
        if log.autopilot == "ardupilot" and seqs and seqs[0] == 0 and len(seqs) > 1:
            seqs = seqs[1:]
        log.mission = [self.mission[s] for s in seqs]
        return log


ABSURD_VALUE = 1e15          # no time [s] or reading in any internal unit comes near (their squares overflow)
OUTLIER_GAP_S = 300.0     # samples separated from the rest of a table by a gap this long ...
OUTLIER_MAX_ROWS = 2      # ... in a group of at most this many rows (or 0.1 % of the table) have
OUTLIER_MAX_FRACTION = 1e-3  # corrupt times (a flipped bit: 9e12 s), not a second session


def column_table(rows: np.ndarray, *columns) -> tuple[np.ndarray, np.ndarray]:
    """(record numbers, [n, len(columns)] float table) of one message type decoded in bulk,
    converted column by column (no float copy of each column)."""
    out = np.empty((len(rows), len(columns)))
    for j, c in enumerate(columns):
        out[:, j] = c
    return rows, out


def in_record_order(parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The rows of a table made of several message types' ``column_table`` parts, in record
    order (stable: rows of one record keep their order)."""
    if len(parts) == 1:
        return parts[0][1]                      # one message type: already in record order
    rows = np.concatenate([p[0] for p in parts])
    return np.concatenate([p[1] for p in parts])[np.argsort(rows, kind="stable")]


def drop_time_outliers(arr: np.ndarray, name: str, warnings: Counter) -> np.ndarray:
    """Drop the rows of small groups of samples far away in time from the rest of the table (a
    corrupt timestamp: a flipped bit turns 10 s into 9e12 s) and count them; real pauses, with
    many samples on both sides, are kept.  The largest group is always kept."""
    if len(arr) < 3:
        return arr
    order = np.argsort(arr[:, 0], kind="stable")
    t = arr[order, 0]
    breaks = np.flatnonzero(np.diff(t) > OUTLIER_GAP_S)
    if not len(breaks):
        return arr
    sizes = np.diff(np.r_[0, breaks + 1, len(t)])
    small = sizes <= max(OUTLIER_MAX_ROWS, OUTLIER_MAX_FRACTION * len(t))
    small[np.argmax(sizes)] = False
    if not small.any():
        return arr
    bad = np.empty(len(t), dtype=bool)
    bad[order] = np.repeat(small, sizes)
    warnings[f"{name}: samples with outlier times dropped (corrupt timestamps)"] += int(bad.sum())
    return arr[~bad]


def clean_table(arr: np.ndarray, name: str, warnings: Counter) -> np.ndarray:
    """Drop rows with non-finite time or values (GPS velocity may be NaN) or outlier times
    (``drop_time_outliers``), sort by time."""
    check = arr[:, :4] if name == "gps" else arr
    sane = np.all((check > -ABSURD_VALUE) & (check < ABSURD_VALUE), axis=1)   # no float temporary; NaN fails too
    if not sane.all():                  # the usual log is all sane: one pass, no finite check
        good = np.all(np.isfinite(check), axis=1)
        if not good.all():
            warnings[f"{name}: rows with NaN/inf dropped"] += int((~good).sum())
        if not (sane == good).all():
            warnings[f"{name}: rows with absurd values (beyond {ABSURD_VALUE:g}) dropped"] += int((good & ~sane).sum())
        arr = arr[sane]
    arr = drop_time_outliers(arr, name, warnings)
    if len(arr) > 1:
        backwards = int(np.count_nonzero(np.diff(arr[:, 0]) < 0))
        if backwards:
            warnings[f"{name}: samples out of time order (re-sorted)"] += backwards
            arr = arr[np.argsort(arr[:, 0], kind="stable")]
    return arr


def _mag(r: list) -> Sample:
    return MagSample(r[0], (r[1], r[2], r[3]))


def _imu(r: list) -> Sample:
    return ImuSample(r[0], (r[1], r[2], r[3]), (r[4], r[5], r[6]))


def _attitude(r: list) -> Sample:
    return AttitudeSample(r[0], r[1], r[2], r[3])


def _gps(r: list) -> Sample:
    return GpsSample(r[0], r[1], r[2], r[3], (r[4], r[5], r[6]), int(r[7]))


class SampleTimeline(Sequence):
    """A FlightLog's tables merged back into one time-ordered sample stream (for replay), as a
    sequence whose samples are made when asked for: the log's parameters, mission and autopilot
    first (at t = 0), then every IMU, magnetometer, attitude and GPS row and status event in time
    order (equal times: in that order, then in table order).  It holds 17 bytes a sample (time,
    table, row), not a Python object per sample, so a long log opens and seeks at once.
    ``t_s``: the times (numpy, the order of the sequence)."""

    _MAKERS = (_imu, _mag, _attitude, _gps)

    def __init__(self, log: FlightLog) -> None:
        head: list[Sample] = [ParamSample(0.0, k, v) for k, v in log.params.items()]
        head += [MissionSample(0.0, i, *wp) for i, wp in enumerate(log.mission)]
        if log.autopilot:
            head.append(StatusSample(0.0, "autopilot", log.autopilot))
        self._head = head
        self._status = sorted(log.status, key=lambda s: s.t_s)
        self._tables = [np.asarray(a, dtype=float) for a in (log.imu, log.mag, log.attitude, log.gps)]
        parts = [a[:, 0] for a in self._tables] + [np.array([s.t_s for s in self._status], dtype=float)]
        times = np.concatenate(parts)
        order = np.argsort(times, kind="stable")
        self._src = np.repeat(np.arange(len(parts), dtype=np.int8), [len(p) for p in parts])[order]
        self._row = np.concatenate([np.arange(len(p)) for p in parts])[order]
        self.t_s = np.concatenate([np.zeros(len(head)), times[order]])

    def __len__(self) -> int:
        return len(self.t_s)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return self._build(*index.indices(len(self))[:2]) if index.step in (None, 1) \
                else [self[i] for i in range(*index.indices(len(self)))]
        i = range(len(self))[index]           # IndexError as a list's
        return self._build(i, i + 1)[0]

    def __iter__(self) -> Iterator[Sample]:
        for lo in range(0, len(self), 4096):
            yield from self._build(lo, min(len(self), lo + 4096))

    def _build(self, lo: int, hi: int) -> list[Sample]:
        nh = len(self._head)
        out: list = self._head[lo:min(hi, nh)]
        lo, hi = max(lo, nh) - nh, max(hi, nh) - nh
        if hi <= lo:
            return out
        src, row = self._src[lo:hi], self._row[lo:hi]
        rest: list = [None] * (hi - lo)
        for k in np.unique(src).tolist():
            at = np.flatnonzero(src == k)
            if k == len(self._MAKERS):
                for j, r in zip(at.tolist(), row[at].tolist()):
                    rest[j] = self._status[r]
                continue
            make = self._MAKERS[k]
            for j, r in zip(at.tolist(), self._tables[k][row[at]].tolist()):
                rest[j] = make(r)
        return out + rest


def iter_samples(log: FlightLog) -> Iterator[Sample]:
    """Merge a FlightLog's tables back into one time-ordered sample stream (``SampleTimeline``)."""
    return iter(SampleTimeline(log))
