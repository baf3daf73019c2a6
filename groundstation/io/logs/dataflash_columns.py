"""DataFlash records decoded column-wise (dataflash.py's default path; see its docstring).

The records DFReader indexed that ``recv_match(type=WANTED)`` would return, each type's one numpy
structured array from its FMT (``_fmt_dtype``), values as DFReader gives them (``_Type.col``),
samples by ``DataFlashDecoder``'s rules on whole columns (``_BulkDecoder``).  ``_Fallback``: a
structure this path does not reproduce; the caller reads record by record instead.
"""
from __future__ import annotations

import math
import re
import struct
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from .builder import LogBuilder, column_table, in_record_order
from .dataflash_messages import (_SPLIT, THROTTLE_PRIORITY, WANTED, att_rad, curr_amps, gps_velocity_ned,
                                 rcou_throttle)
from ..decode import MAG_CAL_COMMANDS, MAV_CMD_NAV_WAYPOINT
from ...samples import FlightLog, MagCalSample, MissionSample, ParamSample, StatusSample

__all__ = ["Decoded", "Taken", "build_log", "decode_records", "take_records"]


class _Fallback(Exception):
    """A structure the bulk path does not reproduce exactly: read record by record instead."""


_STRUCT_TO_NUMPY = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "q": "<i8", "Q": "<u8",
                    "f": "<f4", "d": "<f8", "e": "<f2"}
_INT_CHARS = set("bBhHiIqQM")
_TEXT_CHARS = set("nNZ")
_ALWAYS = ("MODE", "MSG", "PARM", "STAT", "ORGN", "VER")     # DFReader's skip_to_type adds these (not strict)
_REQUIRED = {"MAG": ("MagX", "MagY", "MagZ"), "IMU": ("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ"),
             "ATT": ("Roll", "Pitch", "Yaw"), "GPS": ("Status", "GCrs", "Lat", "Lng", "Alt", "Spd"),
             "PARM": ("Name", "Value"), "CMD": ("CId", "CNum", "Lat", "Lng", "Alt"), "BAT": ("Curr",),
             "CURR": ("Curr",), "CTUN": (), "RCOU": (), "MSG": ("Message",), "MAVC": ("Cmd", "Res", "P1"),
             "OTHERATT": ("Roll", "Pitch", "Yaw")}
_FAMILY = {"MAG2": "MAG", "MAG3": "MAG", "IMU2": "IMU", "IMU3": "IMU", "BATT": "BAT",
           "AHR2": "OTHERATT", "XKF1": "OTHERATT", "NKF1": "OTHERATT", "EKF1": "OTHERATT"}


def _fmt_dtype(fmt) -> np.dtype:
    """The structured dtype of one FMT's record body: DFReader's ``msg_struct`` token by token."""
    names, formats = [], []
    for i, (count, char) in enumerate(re.findall(r"(\d*)([a-zA-Z])", fmt.msg_struct.lstrip("<"))):
        names.append(f"f{i}")
        formats.append(f"S{count}" if char == "s" else _STRUCT_TO_NUMPY[char])
    return np.dtype({"names": names, "formats": formats})


class _Type:
    """One message type's records (before the first one cut off) as columns with DFReader's values."""

    def __init__(self, name: str, fmt, body: np.ndarray, order: np.ndarray) -> None:
        self.name, self.fmt, self.order = name, fmt, order
        self.body = body

    def has(self, column: str) -> bool:
        return column in self.fmt.colhash

    def char(self, column: str) -> str:
        try:
            return self.fmt.format[self.fmt.colhash[column]]
        except (KeyError, IndexError):
            return ""

    def col(self, column: str) -> np.ndarray:
        """Values as DFMessage.__getattr__ gives them: ints, floats (c/C/e/E / 100, L / 1e7), text."""
        i = self.fmt.colhash[column]
        c = self.fmt.format[i]
        raw = self.body[f"f{i}"]
        with np.errstate(invalid="ignore", over="ignore"):
            return self._value(raw, i, c)

    def _value(self, raw: np.ndarray, i: int, c: str) -> np.ndarray:
        if c in _TEXT_CHARS:
            return np.array([_text(b) for b in raw.tolist()], dtype=object)
        mult = self.fmt.msg_mults[i]
        if mult is not None:
            return raw.astype(np.float64) / (1 / mult) if 0.0 < mult < 1.0 else raw.astype(np.float64) * mult
        if c in _INT_CHARS:
            return raw if raw.dtype == np.uint64 else raw.astype(np.int64)     # uint64 stays whole
        return raw.astype(np.float64)

    def int_col(self, column: str) -> np.ndarray:
        """``int(value)`` of a column; a float column with a NaN/inf (int() would raise) falls back."""
        v = self.col(column)
        if v.dtype == object:
            raise _Fallback(f"{self.name}.{column} is text")
        if v.dtype.kind == "f":
            if not np.isfinite(v).all():
                raise _Fallback(f"{self.name}.{column} not finite")
            return np.trunc(v).astype(np.int64)
        return v

    def instance(self) -> np.ndarray:
        for name in ("I", "Inst", "Instance"):
            if self.has(name):
                return self.int_col(name)
        return np.full(len(self.order), _SPLIT.get(self.name, 0), dtype=np.int64)


def _text(b: bytes) -> str:
    try:
        v = b.decode("utf-8")
    except UnicodeDecodeError:
        v = b.decode("ISO-8859-1")
    k = v.find("\0")
    return v if k == -1 else v[:k]


def _records(reader) -> tuple[dict[str, _Type], int, int]:
    """Every record ``recv_match(type=WANTED)`` visits, in its order (DFReader's skip_to_type: the
    indexed offsets of the wanted types and the ones it always adds, by offset), decoded per type;
    the visit stops at the first record cut off by the end.  Returns (wanted types, records
    visited, DFReader's offset at the end)."""
    names = [t for t in set(WANTED) | set(_ALWAYS) if t in reader.name_to_id]
    ids = [reader.name_to_id[t] for t in names]
    if len(set(ids)) != len(ids):
        raise _Fallback("a message type named twice")
    parts = [(np.asarray(reader.offsets[i], dtype=np.int64), i) for i in ids]
    offsets = np.concatenate([p[0] for p in parts] + [np.empty(0, np.int64)])
    types = np.concatenate([np.full(len(p[0]), p[1]) for p in parts] + [np.empty(0, np.int64)])
    order = np.argsort(offsets, kind="stable")
    offsets, types = offsets[order], types[order]
    lengths = np.zeros(256, dtype=np.int64)
    for i in ids:
        fmt = reader.formats[i]
        if struct.calcsize(fmt.msg_struct) != fmt.len - 3 or len(fmt.columns) != len(fmt.format):
            raise _Fallback(f"FMT of {fmt.name} inconsistent")
        lengths[i] = fmt.len
    cut = np.flatnonzero((reader.data_len - offsets < 3) | (offsets + lengths[types] > reader.data_len))
    stop = int(cut[0]) if len(cut) else len(offsets)
    end = reader.data_len if stop == len(offsets) else (
        int(offsets[stop]) if reader.data_len - offsets[stop] < 3 else int(offsets[stop]) + 3)
    data = np.frombuffer(reader.data_map, dtype=np.uint8)
    out: dict[str, _Type] = {}
    for name, i in zip(names, ids):
        if name not in WANTED:
            continue
        rows = np.flatnonzero(types[:stop] == i)
        fmt = reader.formats[i]
        dtype = _fmt_dtype(fmt)
        if len(rows) and dtype.itemsize:
            body = np.lib.stride_tricks.sliding_window_view(data, fmt.len - 3)[offsets[rows] + 3].view(dtype).ravel()
        else:
            body = np.zeros(len(rows), dtype=dtype)
        out[name] = _Type(name, fmt, body, rows)
    del data
    return out, stop, end


class _BulkDecoder:
    """``DataFlashDecoder``'s rules on whole columns: times (``time_of``), every handler, the
    offsets history, the throttle source; samples and history entries in record order."""

    def __init__(self, types: dict[str, _Type], visited: int) -> None:
        self.types, self.n = types, visited
        for name, tp in types.items():
            for column in _REQUIRED[_FAMILY.get(name, name)]:
                if not tp.has(column) and len(tp.order):
                    raise _Fallback(f"{name} without {column}")
        self.t = self._times()
        self.tables: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"mag": [], "imu": [], "attitude": [],
                                                                       "gps": [], "battery": []}
        self.events: list[tuple[int, int, object]] = []     # (record, sub-order, ParamSample | entry | sample)
        self.throttle: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {k: [] for k in THROTTLE_PRIORITY}
        self.other_attitudes: dict[str, np.ndarray] = {}     # AHR2/XKF1/NKF1/EKF1 -> [t, roll, pitch, yaw]
        self.source_names: dict[int, str] = {}
        self.gps_week_ms: tuple[float, float, float] | None = None

    def _times(self) -> np.ndarray:
        """``DataFlashDecoder.time_of`` for every visited record: boot time minus the first timed
        record's (PARM and CMD do not start the clock), records without a time take the last one."""
        boot = np.full(self.n, np.nan)
        starts_clock = np.zeros(self.n, dtype=bool)
        for name, tp in self.types.items():
            if not len(tp.order):
                continue
            if tp.has("TimeUS"):
                b = tp.col("TimeUS").astype(np.float64) * 1e-6
            elif name == "GPS" and tp.has("Week"):
                b = tp.col("T").astype(np.float64) * 1e-3 if tp.has("T") else None
            elif tp.has("TimeMS"):
                b = tp.col("TimeMS").astype(np.float64) * 1e-3
            else:
                b = None
            if b is not None:
                boot[tp.order] = b
                starts_clock[tp.order] = name not in ("PARM", "CMD")
        timed = np.isfinite(boot)
        first = np.flatnonzero(timed & starts_clock)
        t = np.full(self.n, np.nan)
        if len(first):
            i0 = int(first[0])
            own = timed & ((np.arange(self.n) >= i0) | starts_clock)
            t[own] = boot[own] - boot[i0]
        else:
            own = np.zeros(self.n, dtype=bool)
        idx = np.where(own, np.arange(self.n), -1)
        np.maximum.accumulate(idx, out=idx)
        return np.where(idx >= 0, t[np.maximum(idx, 0)], 0.0)

    def table(self, name: str, rows: np.ndarray, *columns) -> None:
        if len(rows):
            self.tables[name].append(column_table(rows, *columns))

    def run(self) -> None:
        for name, tp in self.types.items():
            if len(tp.order):
                getattr(self, "_" + _FAMILY.get(name, name).lower())(tp)

    def _mag(self, tp: _Type) -> None:
        k, t = tp.instance(), self.t[tp.order]
        for kk in np.unique(k).tolist():
            first = int(tp.order[np.argmax(k == kk)])
            label = tp.name if tp.name != "MAG" or not tp.has("I") else f"MAG[{kk}]"
            self.events.append((first, -1, ("source", kk, label)))
        if all(tp.has(f"Ofs{a}") for a in "XYZ"):
            q = 1.0 if tp.char("OfsX") in "hH" else 0.0
            ofs = np.column_stack([tp.col(f"Ofs{a}") for a in "XYZ"])
            self.events.append((int(tp.order[0]), -2, ("offsets", k, ofs, q, tp.order, t)))
        mx, my, mz = (tp.col(f"Mag{a}").astype(float) for a in "XYZ")
        mot = [f"MOfs{a}" if tp.has(f"MOfs{a}") else f"MO{a}" if tp.has(f"MO{a}") else None for a in "XYZ"]
        motor = [tp.col(c).astype(float) if c else None for c in mot]
        if any(c is None for c in motor):
            motor = [np.full(len(t), np.nan)] * 3
        self.table("mag", tp.order, t, mx, my, mz, *motor, k)

    def _imu(self, tp: _Type) -> None:
        self.table("imu", tp.order, self.t[tp.order], *(tp.col(c) for c in ("GyrX", "GyrY", "GyrZ", "AccX", "AccY",
                                                                            "AccZ")), tp.instance())

    def _att(self, tp: _Type) -> None:
        self.table("attitude", tp.order, self.t[tp.order], *(att_rad(tp.col(c)) for c in ("Roll", "Pitch", "Yaw")))

    def _otheratt(self, tp: _Type) -> None:
        """``DataFlashDecoder._other_att`` on columns: degrees -> rad, the first core only (``C`` = 0)."""
        keep = tp.int_col("C") == 0 if tp.has("C") else np.ones(len(tp.order), dtype=bool)
        rows = tp.order[keep]
        if len(rows):
            self.other_attitudes[tp.name] = np.column_stack(
                [self.t[rows]] + [np.radians(tp.col(c).astype(float)[keep]) for c in ("Roll", "Pitch", "Yaw")])

    def _gps(self, tp: _Type) -> None:
        use = (tp.instance() == 0) & ~(tp.col("Status") < 2)
        rows, t = tp.order[use], self.t[tp.order][use]
        week = tp.col("GWk") if tp.has("GWk") else tp.col("Week") if tp.has("Week") else np.zeros(len(tp.order))
        ms = tp.col("GMS") if tp.has("GMS") else tp.col("TimeMS") if tp.has("Week") and tp.has("TimeMS") else None
        if ms is not None:
            ok = np.flatnonzero(use & (week != 0) & (week > 0))
            if len(ok):
                k = int(ok[0])
                self.gps_week_ms = (float(week[k]), float(ms[k]), float(self.t[tp.order[k]]))
        elif tp.has("Week") and len(tp.order):
            raise _Fallback("GPS with Week but no TimeMS")
        vz = tp.col("VZ").astype(float)[use] if tp.has("VZ") else np.full(len(rows), np.nan)
        vn, ve, vd = gps_velocity_ned(tp.col("Spd")[use], tp.col("GCrs")[use], vz)
        self.table("gps", rows, t, tp.col("Lat")[use], tp.col("Lng")[use], tp.col("Alt")[use], vn, ve, vd,
                   tp.int_col("Status")[use])

    def _parm(self, tp: _Type) -> None:
        for r, name, value in zip(tp.order.tolist(), tp.col("Name").tolist(), tp.col("Value").astype(float).tolist()):
            self.events.append((r, 0, ParamSample(float(self.t[r]), str(name), value)))

    def _cmd(self, tp: _Type) -> None:
        use = tp.int_col("CId") == MAV_CMD_NAV_WAYPOINT
        for r, seq, lat, lon, alt in zip(tp.order[use].tolist(), tp.int_col("CNum")[use].tolist(),
                                         *(tp.col(c)[use].tolist() for c in ("Lat", "Lng", "Alt"))):
            self.events.append((r, 0, MissionSample(float(self.t[r]), seq, lat, lon, alt)))

    def _bat(self, tp: _Type) -> None:
        use = tp.instance() == 0
        self.table("battery", tp.order[use], self.t[tp.order][use], tp.col("Curr").astype(float)[use])

    def _curr(self, tp: _Type) -> None:
        t = self.t[tp.order]
        self.table("battery", tp.order, t, curr_amps(tp.col("Curr"), tp.char("Curr") in "hH"))
        if tp.has("ThrOut"):
            self.throttle["CURR"].append((tp.order, np.column_stack([t, tp.col("ThrOut").astype(float) / 1000.0])))

    def _ctun(self, tp: _Type) -> None:
        t = self.t[tp.order]
        if tp.has("ThO"):
            self.throttle["CTUN"].append((tp.order, np.column_stack([t, tp.col("ThO").astype(float)])))
        elif tp.has("ThrOut"):
            self.throttle["CTUN"].append((tp.order, np.column_stack([t, tp.col("ThrOut").astype(float) / 1000.0])))

    def _rcou(self, tp: _Type) -> None:
        if all(tp.has(f"C{i}") for i in range(1, 5)):
            thr = rcou_throttle(*(tp.col(f"C{i}") for i in range(1, 5)))
            self.throttle["RCOU"].append((tp.order, np.column_stack([self.t[tp.order], thr])))

    def _msg(self, tp: _Type) -> None:
        for r, text in zip(tp.order.tolist(), tp.col("Message").tolist()):
            self.events.append((r, 0, StatusSample(float(self.t[r]), "statustext", str(text))))

    def _mavc(self, tp: _Type) -> None:
        cmd, res, p1 = tp.int_col("Cmd"), tp.int_col("Res"), tp.col("P1")
        for r, c, ok, p in zip(tp.order.tolist(), cmd.tolist(), res.tolist(), p1.tolist()):
            kind = MAG_CAL_COMMANDS.get(c)
            if kind is None or ok != 0:
                continue
            mask = int(p) if kind == "start" and math.isfinite(p) else 0
            self.events.append((r, 0, MagCalSample(float(self.t[r]), kind, -1, mask)))

    def history_and_events(self) -> list[tuple[str, object]]:
        """Events in record order: ("add", sample) and ("history", entry); the offsets history
        keeps each compass's changes (``DataFlashDecoder._mag``), across MAG, MAG2, MAG3."""
        out: list[tuple[int, int, tuple]] = []
        changes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]] = []
        for r, sub, item in self.events:
            if isinstance(item, tuple) and item[0] == "source":
                out.append((r, sub, ("source", item[1], item[2])))
            elif isinstance(item, tuple) and item[0] == "offsets":
                changes.append(item[1:])
            else:
                out.append((r, sub, ("add", item)))
        if changes:
            k = np.concatenate([c[0] for c in changes])
            ofs = np.concatenate([c[1].astype(float) if c[1].dtype.kind == "f" else c[1] for c in changes]) \
                if len({c[1].dtype.kind for c in changes}) == 1 else None
            if ofs is None:
                raise _Fallback("MAG offsets of mixed types")
            q = np.concatenate([np.full(len(c[0]), c[2]) for c in changes])
            rows = np.concatenate([c[3] for c in changes])
            t = np.concatenate([c[4] for c in changes])
            if len(changes) > 1 or (k[1:] != k[:-1]).any():
                order = np.lexsort((rows, k))                # by compass, then record
                k, ofs, q, rows, t = k[order], ofs[order], q[order], rows[order], t[order]
            new = np.ones(len(k), dtype=bool)
            new[1:] = (k[1:] != k[:-1]) | (ofs[1:] != ofs[:-1]).any(axis=1)
            for kk, v, qq, r, tt in zip(k[new].tolist(), ofs[new].tolist(), q[new].tolist(), rows[new].tolist(),
                                        t[new].tolist()):
                n = "" if kk == 0 else str(kk + 1)
                for a, x in zip("XYZ", v):
                    out.append((r, 1, ("history", (tt, f"COMPASS_OFS{n}_{a}", float(x), qq))))
        out.sort(key=lambda e: (e[0], e[1]))
        return [e[2] for e in out]


class Taken(NamedTuple):
    """The records ``take_records`` copied out of a DataFlash reader (none of its index or map)."""
    types: dict[str, "_Type"]
    visited: int
    unread_bytes: int                       # bytes after the last whole record


class Decoded(NamedTuple):
    """What ``decode_records`` made of them."""
    bulk: "_BulkDecoder"
    events: list
    counts: list[tuple[int, str, int]]      # (first record, message type, records) of each type read
    unread_bytes: int


def take_records(reader) -> Taken | None:
    """The records recv_match(type=WANTED) returns, each type's as columns copied out of the
    reader, which can be closed after (None: use the per-record path, see the module docstring)."""
    try:
        types, visited, end = _records(reader)
    except _Fallback:
        return None
    return Taken(types, visited, reader.data_len - end)


def decode_records(taken: Taken) -> Decoded | None:
    """``DataFlashDecoder``'s rules on the records taken (None: use the per-record path)."""
    types = taken.types
    try:
        bulk = _BulkDecoder(types, taken.visited)
        bulk.run()
        events = bulk.history_and_events()
    except _Fallback:
        return None
    counts = sorted((int(tp.order[0]), name, len(tp.order)) for name, tp in types.items() if len(tp.order))
    bulk.types, bulk.t = {}, np.empty(0)      # the records' columns and times: decoded, not needed
    return Decoded(bulk, events, counts, taken.unread_bytes)


def build_log(path: Path, progress: Callable[[float], None] | None, decoded: Decoded) -> FlightLog:
    """The FlightLog of what ``decode_records`` decoded."""
    bulk, events = decoded.bulk, decoded.events
    builder = LogBuilder(str(path))
    log = builder.log
    log.autopilot = "ardupilot"
    for _, name, count in decoded.counts:
        log.message_counts[name] += count
    for name in list(bulk.tables):          # each table's parts freed once it is set
        parts = bulk.tables.pop(name)
        if parts:
            builder.set_table(name, in_record_order(parts))
        del parts
    for kind, *item in events:
        if kind == "add":
            builder.add(item[0])
        elif kind == "history":
            builder.add_history(*item[0])
        else:
            bulk.source_names.setdefault(item[0], item[1])
    if progress is not None:
        progress(0.9)
    if decoded.unread_bytes > 0:
        log.warnings[f"log truncated: last {decoded.unread_bytes} bytes unreadable"] += 1
    throttle_source = next((k for k in THROTTLE_PRIORITY if bulk.throttle[k]), None)
    if throttle_source:
        table = in_record_order(bulk.throttle[throttle_source])
        builder.set_table("throttle", table)
    for name, table in bulk.other_attitudes.items():
        builder.other_attitudes[name] = np.ascontiguousarray(table).ravel()   # read back with np.frombuffer
    builder.source_names.update(bulk.source_names)
    log.mag_calibration_applied = True
    log = builder.finish()
    if throttle_source:
        log.message_counts[f"throttle from {throttle_source}"] = len(table)
    if bulk.gps_week_ms is not None:
        week, ms, t = bulk.gps_week_ms
        log.start_unix_s = 315964800 + week * 604800 + ms * 1e-3 - 18 - t
    return log
