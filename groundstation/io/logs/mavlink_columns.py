"""MAVLink records of a .tlog as columns, and ``MavlinkDecoder``'s rules applied to them.

``_Records``: the good records (framed by tlog.frame_records) as columns; ``_ColumnDecoder``: the
samples ``decode.MavlinkDecoder`` would give, message type by message type (used by
tlog.read_tlog).
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np

from .. import decode as dec
from ..boot_clock import BootClock, boot_ms_of_usec
from ..decode import MavlinkDecoder
from ..mavlink import mavlink2
from .builder import WIDTHS, LogBuilder, column_table, in_record_order
from .mavlink_bulk import CORRUPT, byte_at, decode_packet as _decode, decode_payloads
from ...samples import OffsetsSample, StatusSample

__all__ = ["msg_ids"]


def msg_ids(data: np.ndarray, pos: np.ndarray, v2: np.ndarray, last: int | None = None) -> np.ndarray:
    """Message id of the packet at pos + 8: bytes 7..9 of MAVLink 2 (little-endian 24 bit), byte 5
    of MAVLink 1; with ``last``, byte offsets are clamped to it (as the candidate scan reads)."""
    def b(k):
        return (byte_at(data, k) if last is None else data[np.minimum(k, last)]).astype(np.int64)
    ids = b(pos + 13)
    if v2.any():
        w = np.flatnonzero(v2)
        p = pos[w]
        ids[w] = b(p + 15) | b(p + 16) << 8 | b(p + 17) << 16
    return ids


# message ids the decoder turns into samples (decode.MavlinkDecoder's handlers)
_ID = {name: getattr(mavlink2, "MAVLINK_MSG_ID_" + name) for name in (
    "HEARTBEAT", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU", "ATTITUDE",
    "ATTITUDE_QUATERNION", "GPS_RAW_INT", "GLOBAL_POSITION_INT", "SENSOR_OFFSETS", "VFR_HUD", "SYSTEM_TIME",
    "SYS_STATUS", "MISSION_ITEM_INT", "MISSION_ITEM", "PARAM_VALUE", "STATUSTEXT", "MAG_CAL_PROGRESS",
    "MAG_CAL_REPORT", "COMMAND_LONG")}
# decoded per packet through pymavlink and MavlinkDecoder itself: text, parameters, missions and
# calibration events, a few per second at most, each with Python objects for its samples
_PER_PACKET = tuple(_ID[n] for n in ("MISSION_ITEM_INT", "MISSION_ITEM", "PARAM_VALUE", "STATUSTEXT",
                                     "MAG_CAL_PROGRESS", "MAG_CAL_REPORT", "COMMAND_LONG"))
_SCALED = {_ID["RAW_IMU"]: 0, _ID["SCALED_IMU"]: 10, _ID["SCALED_IMU2"]: 11, _ID["SCALED_IMU3"]: 12}


class _Records:
    """A run of good records of one .tlog as columns (record order): start offset, message id,
    payload offset and length, source system, arrival time [s] on the log's time base.  Rows are
    numbered within the run; ``base`` is the number of its first record in the log."""

    def __init__(self, data: np.ndarray, starts: np.ndarray, arrival: np.ndarray, base: int = 0) -> None:
        self.data, self.start, self.arrival, self.base = data, starts, arrival, base
        v2 = data[starts + 8] == 0xFD
        self.v2 = v2
        self.id = msg_ids(data, starts, v2).astype(np.int32)
        self.length = data[starts + 9]
        self.sysid = np.where(v2, data[starts + 13], data[starts + 11])
        order = np.argsort(self.id, kind="stable").astype(np.int32)
        sorted_ids = self.id[order]
        first = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]]) if len(order) else np.empty(0, int)
        self._groups = {int(sorted_ids[a]): order[a:b] for a, b in zip(first.tolist(), np.r_[first[1:], len(order)].tolist())}

    def rows(self, msg_id: int) -> np.ndarray:
        """Record indices of one message id, in record order."""
        return self._groups.get(msg_id, np.empty(0, dtype=np.int64))

    def fields(self, msg_id: int, rows: np.ndarray) -> np.ndarray:
        start = self.start[rows]
        return decode_payloads(self.data, start + np.where(self.v2[rows], 18, 14), self.length[rows].astype(np.int64),
                               msg_id)

    def packet(self, r: int) -> bytearray:
        s = int(self.start[r]) + 8
        size = (12 + int(self.length[r]) + (13 if self.data[s + 2] & 1 else 0)) if self.v2[r] else 8 + int(self.length[r])
        return bytearray(self.data[s:s + size].tobytes())

    def counts(self) -> Counter:
        """Messages per type (pymavlink's names, UNKNOWN_n for ids it does not know), in the order
        each type first appears."""
        out: Counter = Counter()
        for i, rows in sorted(self._groups.items(), key=lambda g: g[1][0]):
            cls = mavlink2.mavlink_map.get(i)
            out[cls.msgname if cls is not None else f"UNKNOWN_{i}"] = len(rows)
        return out


_NOT_YET = np.iinfo(np.int64).max     # a record number after every record: not seen yet


class _ColumnDecoder:
    """``MavlinkDecoder``'s rules applied to whole columns of a log, one run of records at a time
    (``run``, in record order; ``finish`` once after the last).  What a rule needs from earlier
    records is carried from run to run, so any cut gives the same log: the vehicle (its first
    autopilot heartbeat), the boot clock, the lag of the last boot-timed record, the last GPS fix
    and position, each magnetometer source's unit (judged at its first non-zero sample).  Tables
    go to the builder as arrays, events (statuses, parameters, offsets) as samples in record
    order."""

    def __init__(self, builder: LogBuilder, records: int) -> None:
        """``records``: how many records the log has (to size the tables from the first runs)."""
        self.builder, self.records, self.decoded = builder, records, 0
        self.warnings: Counter = Counter()
        self.counts: Counter = Counter()
        self.autopilot: str | None = None
        self.events: list[tuple[int, object]] = []
        # each table's rows, written in place run by run (``_append``)
        self.tables: dict[str, np.ndarray] = {}
        self.filled = dict.fromkeys(WIDTHS, 0)
        self.vehicle: int | None = None
        self.h0 = _NOT_YET                       # the first autopilot heartbeat's record
        self.start_row, self.start_unix = _NOT_YET, None      # the first SYSTEM_TIME with a UNIX time
        self.clock = BootClock()
        self.lag_before = 0.0                    # the clock's lag after the last boot-timed record
        self.last_gps: tuple[float, int] | None = None    # (time, fix type) of the last GPS_RAW_INT
        self.last_place: tuple[float, float, float] | None = None
        self.mag_scale: dict[int, float] = {}    # magnetometer source -> its judged unit [mG per unit]
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.packet_decoder = MavlinkDecoder()

    # ---------------------------------------------------------------- helpers
    def accepted(self, msg_id: int) -> np.ndarray:
        """Record indices of ``msg_id`` the decoder would use: before the vehicle is known every
        system's, after it the vehicle's only."""
        rows = self.rec.rows(msg_id)
        if self.vehicle is None:
            return rows
        return rows[(rows + self.rec.base < self.h0) | (self.rec.sysid[rows] == self.vehicle)]

    def table(self, name: str, rows: np.ndarray, *columns) -> None:
        if len(rows):
            self.run_parts[name].append(column_table(rows, *columns))

    # ---------------------------------------------------------------- run
    def run(self, rec: _Records) -> None:
        """Decode one run of records (the next after the previous run's)."""
        self.rec = rec
        self.run_parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {name: [] for name in WIDTHS}
        self.counts.update(rec.counts())
        self.decoded += len(rec.start)
        self._heartbeats()
        self._per_packet()
        if self.start_row == _NOT_YET:
            st = self.accepted(_ID["SYSTEM_TIME"])
            usec = rec.fields(_ID["SYSTEM_TIME"], st)["time_unix_usec"]
            ok = np.flatnonzero(usec > 1e15)
            if len(ok):
                self.start_row = int(st[ok[0]]) + rec.base
                self.start_unix = float(usec[ok[0]]) * 1e-6 - float(rec.arrival[st[ok[0]]])
        times = self._clock()
        self._gps_raw()
        self._scaled(times)
        self._highres(times)
        self._attitude(times)
        self._global_position(times[_ID["GLOBAL_POSITION_INT"]])
        self._offsets()
        vfr = self.accepted(_ID["VFR_HUD"])
        thr, valid = dec.vfr_hud_throttle(rec.fields(_ID["VFR_HUD"], vfr)["throttle"])
        self.table("throttle", vfr[valid], self._sent(vfr[valid]), thr[valid])
        sys = self.accepted(_ID["SYS_STATUS"])
        amps, valid = dec.sys_status_current_A(rec.fields(_ID["SYS_STATUS"], sys)["current_battery"])
        self.table("battery", sys[valid], self._sent(sys[valid]), amps[valid])
        del self.rec, rec, self.parts, self.sent_rows, self.sent_lag, self.usec_rows, self.no_boot_time
        for name in WIDTHS:                     # the run's bytes freed first, each table's parts once appended
            parts = self.run_parts.pop(name)
            if parts:
                self._append(name, in_record_order(parts))
            del parts
        del self.run_parts

    def _append(self, name: str, rows: np.ndarray) -> None:
        """A run's rows at the end of its table.  A table is made with room for the whole log at the
        rate of the runs so far (+10 %) and made again, larger, only when a later run outgrows it:
        no run is kept beside its table, and the table is rarely copied."""
        k = self.filled[name]
        need = k + len(rows)
        table = self.tables.get(name)
        if table is None or need > len(table):
            room = max(need, int(need * 1.1 * self.records / max(self.decoded, 1)))
            grown = np.empty((room, WIDTHS[name]))
            if table is not None:
                grown[:k] = table[:k]
            self.tables[name] = table = grown
        table[k:need] = rows
        self.filled[name] = need

    def _heartbeats(self) -> None:
        rows = self.rec.rows(_ID["HEARTBEAT"])
        f = self.rec.fields(_ID["HEARTBEAT"], rows)
        autopilot_hb = (f["type"] != dec.MAV_TYPE_GCS) & (f["autopilot"] != 8)     # 8: MAV_AUTOPILOT_INVALID
        if self.vehicle is None:
            first = np.flatnonzero(autopilot_hb)
            if not len(first):
                return
            self.h0 = int(rows[first[0]]) + self.rec.base
            self.vehicle = int(self.rec.sysid[rows[first[0]]])
        mine = autopilot_hb & (self.rec.sysid[rows] == self.vehicle)
        names = {dec.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", dec.MAV_AUTOPILOT_PX4: "px4"}
        for r, ap in zip(rows[mine].tolist(), f["autopilot"][mine].tolist()):
            name = names.get(ap)
            if name and name != self.autopilot:
                self.autopilot = name
                self.events.append((r + self.rec.base, StatusSample(float(self.rec.arrival[r]), "autopilot", name)))

    def _per_packet(self) -> None:
        rows = np.sort(np.concatenate([self.rec.rows(i) for i in _PER_PACKET]))
        self.param_rows = self.rec.rows(_ID["PARAM_VALUE"])
        decoder, base = self.packet_decoder, self.rec.base
        for r in rows.tolist():
            msg = _decode(self.parser.decode, self.rec.packet(r))
            if msg is None:
                self.warnings[CORRUPT] += 1
                continue
            decoder.vehicle_sysid = self.vehicle if r + base > self.h0 else None
            for s in decoder.decode(msg, float(self.rec.arrival[r])):
                self.events.append((r + base, s))

    def _gps_raw(self) -> None:
        rows = self.accepted(_ID["GPS_RAW_INT"])
        f = self.rec.fields(_ID["GPS_RAW_INT"], rows)
        self.gps_before, self.place_before_run = self.last_gps, self.last_place
        self.gps_rows, self.gps_fix = rows, f["fix_type"].astype(np.int64)
        use = (f["fix_type"] >= 2) & ~((f["lat"] == 0) & (f["lon"] == 0))
        g = f[use]
        lat, lon, alt, vn, ve, vd = dec.gps_raw_int_to_si(g["lat"], g["lon"], g["alt"], g["vel"], g["cog"])
        self.place_rows, self.place = rows[use], np.column_stack([lat, lon, alt]) if len(g) else np.empty((0, 3))
        self.gps_t = self._sent(rows)
        self.table("gps", rows[use], self.gps_t[use], lat, lon, alt, vn, ve, vd, g["fix_type"])
        if len(rows):
            self.last_gps = (float(self.gps_t[-1]), int(self.gps_fix[-1]))
        if len(g):
            self.last_place = tuple(float(v) for v in self.place[-1])

    def _clock(self) -> dict[int, np.ndarray]:
        """Boot-clock times of every message that has them, in record order through one clock
        (RAW_IMU and HIGHRES_IMU where their time_usec is a boot time, ``boot_ms_of_usec``;
        ``self.no_boot_time[id]`` marks their rows timed by ``_sent`` instead)."""
        parts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for name in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "ATTITUDE_QUATERNION",
                     "GLOBAL_POSITION_INT"):
            rows = self.accepted(_ID[name])
            f = self.rec.fields(_ID[name], rows)
            if name == "ATTITUDE":
                self.att_ok = np.isfinite(f["roll"]) & np.isfinite(f["pitch"]) & np.isfinite(f["yaw"])
                rows, f = rows[self.att_ok], f[self.att_ok]
            elif name == "ATTITUDE_QUATERNION":
                self.quat, valid = dec.normalised_quaternion(f["q1"], f["q2"], f["q3"], f["q4"])
                self.quat_bad = int((~valid).sum())
                self.quat, rows, f = self.quat[valid], rows[valid], f[valid]
            parts[_ID[name]] = (rows, f["time_boot_ms"].astype(np.int64))
            del f                                       # decoded again where used: memory, not time
        self.usec_rows, self.no_boot_time = {}, {}
        for name in ("RAW_IMU", "HIGHRES_IMU"):
            rows = self.accepted(_ID[name])
            boot_ms = boot_ms_of_usec(self.rec.fields(_ID[name], rows)["time_usec"] if len(rows) else np.zeros(0))
            on_clock = np.isfinite(boot_ms)
            self.usec_rows[_ID[name]], self.no_boot_time[_ID[name]] = rows, ~on_clock
            parts[_ID[name]] = (rows[on_clock], boot_ms[on_clock])
        rows = np.concatenate([p[0] for p in parts.values()])
        boot = np.concatenate([p[1] for p in parts.values()])
        order = np.argsort(rows, kind="stable")
        t = np.empty(len(rows))
        on_clock_rows = rows[order]
        lag = self.rec.arrival[on_clock_rows]
        times_in_order = self.clock.times(boot[order], lag)
        t[order] = times_in_order
        lag -= times_in_order                               # MavlinkDecoder's clock.lag_s after each
        del times_in_order, boot, order
        # the rows without a boot time keep only the lag before each (the clock's rows are freed)
        self.sent_rows = np.sort(np.concatenate(
            [self.accepted(_ID[name]) for name in ("GPS_RAW_INT", "SYS_STATUS", "VFR_HUD")]
            + [self.usec_rows[i][self.no_boot_time[i]] for i in self.usec_rows]))
        k = np.searchsorted(on_clock_rows, self.sent_rows) - 1
        self.sent_lag = np.where(k >= 0, lag[np.maximum(k, 0)] if len(lag) else 0.0, self.lag_before)
        if len(lag):
            self.lag_before = float(lag[-1])
        del on_clock_rows, lag, k
        out, k = {}, 0
        self.parts = {i: p[0] for i, p in parts.items()}
        for i, (r, _) in parts.items():
            out[i] = t[k:k + len(r)]
            k += len(r)
        return out

    def _sent(self, rows: np.ndarray) -> np.ndarray:
        """``MavlinkDecoder._sent`` of each row: its arrival less the lag of the last boot-timed
        row before it (none yet: 0; before this run: the last run's)."""
        return self.rec.arrival[rows] - self.sent_lag[np.searchsorted(self.sent_rows, rows)]

    def _usec_times(self, msg_id: int, times: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Rows of RAW_IMU or HIGHRES_IMU and their times: the boot clock's, ``_sent`` where
        time_usec is not a boot time."""
        rows, no_boot_time = self.usec_rows[msg_id], self.no_boot_time[msg_id]
        t = np.empty(len(rows))
        t[~no_boot_time] = times[msg_id]
        t[no_boot_time] = self._sent(rows[no_boot_time])
        return rows, t

    def _place_before(self, r: int) -> tuple[float, float, float] | None:
        k = int(np.searchsorted(self.place_rows, r)) - 1
        return self.place_before_run if k < 0 else tuple(float(v) for v in self.place[k])

    def _judge(self, instance: int, rows: np.ndarray, t: np.ndarray, sent: np.ndarray, units) -> float | None:
        """The scale of a magnetometer source, judged at its first non-zero sample (the decoder's
        ``judge_first_field``; its warning counted) and kept for the later runs; None while every
        sample is zero."""
        if instance in self.mag_scale:
            return self.mag_scale[instance]
        nonzero = np.flatnonzero((sent != 0).any(axis=1))
        if not len(nonzero):
            return None
        k = int(nonzero[0])
        r = int(rows[k])
        start_unix = self.start_unix if self.start_row < r + self.rec.base else None
        unit = dec.judge_first_field(instance, tuple(float(v) for v in sent[k]), units, float(t[k]),
                                     self._place_before(r), start_unix)
        if not unit.plausible:
            self.warnings[f"{unit.source}: implausible magnetometer field ({unit.why})"] += 1
        self.mag_scale[instance] = unit.scale_to_mG
        return unit.scale_to_mG

    def _scaled(self, times: dict[int, np.ndarray]) -> None:
        for msg_id, instance in _SCALED.items():
            if msg_id == _ID["RAW_IMU"]:
                rows, t = self._usec_times(msg_id, times)
            else:
                rows, t = self.parts[msg_id], times[msg_id]
            f = self.rec.fields(msg_id, rows)
            if not len(rows):
                continue
            mag = np.column_stack([f["xmag"], f["ymag"], f["zmag"]])
            self._judge(instance, rows, t, mag.astype(float), dec.MG_UNIT)
            has = (mag != 0).any(axis=1)
            sel = slice(None) if has.all() else has                 # no copies when every row has a field
            self.table("mag", rows[sel], t[sel], *mag[sel].T, np.nan, np.nan, np.nan, instance)
            del mag
            gyro, acc = dec.scaled_imu_to_si(np.column_stack([f["xgyro"], f["ygyro"], f["zgyro"]]),
                                             np.column_stack([f["xacc"], f["yacc"], f["zacc"]]))
            del f
            self.table("imu", rows, t, *gyro.T, *acc.T, instance)

    def _highres(self, times: dict[int, np.ndarray]) -> None:
        rows, t = self._usec_times(_ID["HIGHRES_IMU"], times)
        if not len(rows):
            return
        f = self.rec.fields(_ID["HIGHRES_IMU"], rows)
        upd = f["fields_updated"]
        wanted = ((upd & 0x1C0) != 0) | (upd == 0)
        sent = np.column_stack([f["xmag"], f["ymag"], f["zmag"]]).astype(float)
        finite = np.isfinite(sent).all(axis=1)
        if (wanted & ~finite).any():
            self.warnings["NaN magnetometer field"] += int((wanted & ~finite).sum())
        inst = 20 + f["id"].astype(np.int64)
        use = wanted & finite
        scale = np.full(len(rows), dec.MG_PER_GAUSS)
        for k in np.unique(inst[use]).tolist():
            sel = use & (inst == k)
            s = self._judge(k, rows[sel], t[sel], sent[sel], dec.HIGHRES_MAG_UNITS)
            scale[inst == k] = dec.MG_PER_GAUSS if s is None else s
        m = sent[use] * scale[use, None]
        nan3 = np.full(int(use.sum()), np.nan)
        self.table("mag", rows[use], t[use], *m.T, nan3, nan3, nan3, inst[use])
        imu = np.column_stack([f[c] for c in ("xgyro", "ygyro", "zgyro", "xacc", "yacc", "zacc")]).astype(float)
        ok = np.isfinite(imu).all(axis=1)
        if not ok.all():
            self.warnings["NaN IMU field"] += int((~ok).sum())
        self.table("imu", rows[ok], t[ok], *imu[ok].T, inst[ok])

    def _attitude(self, times: dict[int, np.ndarray]) -> None:
        bad = int((~self.att_ok).sum())
        if bad:
            self.warnings["NaN attitude field"] += bad
        if self.quat_bad:
            self.warnings["invalid attitude quaternion"] += self.quat_bad
        rows = self.parts[_ID["ATTITUDE"]]
        f = self.rec.fields(_ID["ATTITUDE"], rows)
        self.table("attitude", rows, times[_ID["ATTITUDE"]], f["roll"], f["pitch"], f["yaw"])
        rows = self.parts[_ID["ATTITUDE_QUATERNION"]]
        if len(rows):
            self.table("attitude", rows, times[_ID["ATTITUDE_QUATERNION"]], *dec.euler_from_quaternion(*self.quat.T))

    def _global_position(self, t: np.ndarray) -> None:
        rows = self.parts[_ID["GLOBAL_POSITION_INT"]]
        f = self.rec.fields(_ID["GLOBAL_POSITION_INT"], rows)
        k = np.searchsorted(self.gps_rows, rows) - 1            # the last GPS_RAW_INT before each
        t0, fix0 = self.gps_before if self.gps_before is not None else (-math.inf, 3)
        last_t = np.where(k >= 0, self.gps_t[np.maximum(k, 0)] if len(self.gps_rows) else 0.0, t0)
        fix = np.where(k >= 0, self.gps_fix[np.maximum(k, 0)] if len(self.gps_rows) else 0, fix0)
        use = ~(t - last_t < 3.0) & ~((f["lat"] == 0) & (f["lon"] == 0))
        g = f[use]
        cols = dec.global_position_int_to_si(g["lat"], g["lon"], g["alt"], g["vx"], g["vy"], g["vz"])
        self.table("gps", rows[use], t[use], *cols, fix[use])

    def _offsets(self) -> None:
        """SENSOR_OFFSETS: compass 0's offsets as history entries; a record repeating the previous
        one's values (with no PARAM_VALUE between, which could name the same parameter) adds
        nothing to the history (``compact_history`` drops such repeats) and is skipped here (the
        first of each run is kept: a repeat across runs is dropped by ``compact_history``)."""
        rows = self.accepted(_ID["SENSOR_OFFSETS"])
        f = self.rec.fields(_ID["SENSOR_OFFSETS"], rows)
        ofs = np.column_stack([f["mag_ofs_x"], f["mag_ofs_y"], f["mag_ofs_z"]])
        group = np.searchsorted(self.param_rows, rows)
        keep = np.ones(len(rows), dtype=bool)
        keep[1:] = (ofs[1:] != ofs[:-1]).any(axis=1) | (group[1:] != group[:-1])
        for r, v in zip(rows[keep].tolist(), ofs[keep].tolist()):
            self.events.append((r + self.rec.base,
                                OffsetsSample(float(self.rec.arrival[r]), 0, tuple(float(x) for x in v), 1.0)))

    def finish(self) -> None:
        """The tables (the runs' rows, in record order) and the events to the builder."""
        for name, table in self.tables.items():
            self.builder.set_table(name, table[:self.filled[name]])
        self.tables.clear()
        self.warnings.update(self.packet_decoder.warnings)
        self.events.sort(key=lambda e: e[0])
        for _, s in self.events:
            self.builder.add(s)
