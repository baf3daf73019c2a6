"""MAVLink telemetry logs (.tlog): 8-byte big-endian UNIX microseconds + one MAVLink packet per record.

``read_tlog`` (the FlightLog) decodes column-wise: the file is read once, every record is framed
and CRC-checked in bulk (``frame_records``), each message id's payloads become one numpy
structured array (``mavlink_bulk``) and the decoder's rules run on whole columns
(``_ColumnDecoder``); corrupt stamps (``despike_times``) and a clock going back
(``rebase_backwards``) are handled on the time column.  ``tlog_records`` yields (UNIX time,
pymavlink message) per record, streaming in bounded chunks (the station's replay and the
recordings list); both frame the same records with the same resynchronisation after garbage
(linear: candidate starts are found with numpy) and the same corrupt counts.
"""
from __future__ import annotations

import bisect
import io
import math
import struct
from collections import Counter
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from .. import decode as dec
from ..decode import MavlinkDecoder
from ..mavlink import mavlink2
from .builder import LogBuilder
from .mavlink_bulk import CRC_EXTRA, KNOWN, PAYLOAD_SIZE, byte_at, decode_payloads, rows_at, x25_crc_rows
from ...samples import FlightLog, OffsetsSample, StatusSample

__all__ = ["read_tlog", "tlog_records", "frame_records", "despike_times", "rebase_backwards"]

TLOG_STAMP = struct.Struct(">Q")
_PLAUSIBLE_UNIX_S = (946684800.0, 4102444800.0)  # 2000..2100
_PLAUSIBLE_US = (int(_PLAUSIBLE_UNIX_S[0] * 1e6), int(_PLAUSIBLE_UNIX_S[1] * 1e6))
MAX_RECORD = 8 + 10 + 255 + 2 + 13      # stamp + the largest MAVLink 2 packet (signed)
CHUNK_BYTES = 1 << 18
STAMP_JUMP_S = 60.0                      # a record this far from both neighbours has a corrupt stamp
CORRUPT = "corrupt packets skipped (bad CRC or garbage)"
SPIKE = "timestamps corrupt (jumped away and back): replaced by the previous record's"


_KNOWN_IDS = np.array(sorted(mavlink2.mavlink_map), dtype=np.int64)
_MAX_PAYLOAD = np.array([mavlink2.mavlink_map[i].unpacker.size for i in _KNOWN_IDS.tolist()], dtype=np.int64)


class _Candidates:
    """Next plausible record start (a 2000..2100 stamp, a MAVLink magic byte, a known message
    id) at or after a position, found with numpy over windows that double while garbage lasts:
    linear in the garbage, whatever it holds."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.lo = self.hi = 0
        self.found: list[int] = []
        self.window = 4096

    def next(self, buf: bytes, start: int, end: int) -> int | None:
        """Smallest candidate k with start <= k < end (k + 8 < len(buf)), None when there is none."""
        while start < end:
            if not (self.lo <= start < self.hi):
                self._scan(buf, start, min(end, start + self.window))
                self.window = min(self.window * 2, CHUNK_BYTES)
            idx = bisect.bisect_left(self.found, start)
            if idx < len(self.found):
                return self.found[idx]
            start = self.hi
        return None

    def _scan(self, buf: bytes, lo: int, hi: int) -> None:
        data = np.frombuffer(buf, dtype=np.uint8)
        magic = data[lo + 8:hi + 8]
        k = np.flatnonzero((magic == 0xFD) | (magic == 0xFE)) + lo
        if len(k):
            stamps = data[k[:, None] + np.arange(8)].view(">u8").ravel()
            k = k[(stamps > _PLAUSIBLE_US[0]) & (stamps < _PLAUSIBLE_US[1])]
        if len(k):       # a known message id (bytes 7..9 of v2, 5 of v1) with a payload it can have
            v2 = data[k + 8] == 0xFD
            at = np.minimum((k + 8 + np.where(v2, 7, 5))[:, None] + np.arange(3), len(data) - 1)
            b = data[at].astype(np.int64)
            ids = np.where(v2, b[:, 0] | b[:, 1] << 8 | b[:, 2] << 16, b[:, 0])
            idx = np.minimum(np.searchsorted(_KNOWN_IDS, ids), len(_KNOWN_IDS) - 1)
            length = data[k + 9].astype(np.int64)
            k = k[(_KNOWN_IDS[idx] == ids) & (length >= 1) & (length <= _MAX_PAYLOAD[idx])]
        self.lo, self.hi, self.found = lo, hi, k.tolist()


def _as_stream(source) -> BinaryIO:
    return source if hasattr(source, "read") else io.BytesIO(source)


def tlog_records(source, warnings: Counter) -> Iterator[tuple[float, object]]:
    """(UNIX time, message) of each good record of a .tlog (bytes or a binary file).

    A record is an 8-byte big-endian microsecond stamp and one MAVLink 1 (0xFE) or 2 (0xFD)
    packet, so the packet length is known from its header and pymavlink's ``decode`` (CRC
    checked) gets whole packets; that skips its byte-at-a-time stream parser, which is built
    for serial links.  After garbage or a bad CRC we resynchronise on the next position whose
    stamp is a plausible date and whose packet decodes (with a known message id, so the CRC is
    checked); a cut-off last record is reported.
    """
    stream = _as_stream(source)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    decode, known = parser.decode, mavlink2.mavlink_map
    candidates = _Candidates()
    buf, i, eof, searching, resynced = b"", 0, False, False, False
    while True:
        if not eof and len(buf) - i <= MAX_RECORD:
            chunk = stream.read(CHUNK_BYTES)
            if chunk:
                buf, i = buf[i:] + chunk, 0
                candidates.clear()
                continue
            eof = True
        if i + 10 > len(buf):
            break
        if searching:
            k = candidates.next(buf, i, len(buf) - 9)
            if k is None:
                i = max(i, len(buf) - 9)
                if eof:
                    break
                continue
            i, searching, resynced = k, False, True
        magic = buf[i + 8]
        if magic == 0xFD:
            size = 12 + buf[i + 9] + (13 if i + 10 < len(buf) and buf[i + 10] & 1 else 0)   # flags cut off: incomplete
        elif magic == 0xFE:
            size = 8 + buf[i + 9]
        else:
            size = 0
        unix = TLOG_STAMP.unpack_from(buf, i)[0] * 1e-6
        if size and _PLAUSIBLE_UNIX_S[0] < unix < _PLAUSIBLE_UNIX_S[1]:
            if i + 8 + size > len(buf):
                warnings["log truncated: last record cut off"] += 1
                return
            packet = bytearray(buf[i + 8:i + 8 + size])
            # after garbage only a known message with a good CRC re-establishes the record chain
            msg = None if resynced and not _crc_ok(packet, known) else _decode(decode, packet)
            if msg is not None:
                i += 8 + size
                resynced = False
                candidates.window = 4096
                yield unix, msg
                continue
        warnings[CORRUPT] += 1
        i += 1
        searching = True
    if i < len(buf):
        warnings["log truncated: last record cut off"] += 1


def _crc_ok(packet: bytearray, known: dict) -> bool:
    """A known message id and a matching X.25 CRC (with the message's CRC_EXTRA), checked before
    pymavlink's decode: cheap when garbage is full of near-records."""
    v2 = packet[0] == 0xFD
    if len(packet) < (12 if v2 else 8):
        return False
    cls = known.get(packet[7] | packet[8] << 8 | packet[9] << 16 if v2 else packet[5])
    if cls is None:
        return False
    end = len(packet) - 2 - (13 if v2 and packet[2] & 1 else 0)
    crc = mavlink2.x25crc(bytes(packet[1:end]) + bytes((cls.crc_extra,))).crc
    return crc == packet[end] | packet[end + 1] << 8


def _decode(decode, packet: bytearray):
    try:
        return decode(packet)
    except (mavlink2.MAVError, struct.error, IndexError, ValueError, TypeError):
        return None


TRUNCATED = "log truncated: last record cut off"


def _msg_ids(data: np.ndarray, pos: np.ndarray, v2: np.ndarray, last: int | None = None) -> np.ndarray:
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


_TRUNC, _PLAIN, _RESYNC, _CAND = 1, 2, 4, 8   # frame_records: what a position is
_BLOCK = 1 << 18                              # file bytes judged at once (bounds the temporaries)


def _judge_block(data: np.ndarray, n: int, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions, record sizes, flags) of the positions a <= p < b whose byte 8 is a MAVLink magic
    (p <= n - 10); flags: _TRUNC a plausible record cut off by the end, _PLAIN a record on the
    chain, _CAND a resynchronisation candidate, _RESYNC a candidate that is a record."""
    magic = data[a + 8:min(b, n - 9) + 8]
    pos = np.flatnonzero((magic - np.uint8(0xFD)) < 2) + a        # 0xFD or 0xFE (uint8 wraps the rest)
    stamp_us = rows_at(data, pos, 8).copy().view(">u8").ravel()
    unix = stamp_us.astype(np.float64) * 1e-6
    plausible = (unix > _PLAUSIBLE_UNIX_S[0]) & (unix < _PLAUSIBLE_UNIX_S[1])
    v2 = data[pos + 8] == 0xFD
    mlen = data[pos + 9].astype(np.int64)
    signed = v2 & (byte_at(data, pos + 10) & 1).astype(bool)
    size = np.where(v2, 12 + mlen + 13 * signed, 8 + mlen)
    complete = pos + 8 + size <= n
    ids = _msg_ids(data, pos, v2)
    ids_clamped = ids.copy()                   # the candidate scan reads the id bytes clamped to the end
    near = np.flatnonzero(pos + 17 > n - 1)
    if len(near):
        last = max(n - 1, 0)
        ids_clamped[near] = _msg_ids(data, np.minimum(pos[near], last), v2[near], last)
    known = (ids < len(KNOWN)) & KNOWN[np.minimum(ids, len(KNOWN) - 1)]
    known_c = (ids_clamped < len(KNOWN)) & KNOWN[np.minimum(ids_clamped, len(KNOWN) - 1)]
    cand = ((stamp_us > _PLAUSIBLE_US[0]) & (stamp_us < _PLAUSIBLE_US[1]) & known_c & (mlen >= 1)
            & (mlen <= PAYLOAD_SIZE[np.where(known_c, ids_clamped, 0)]))
    crc_ok = np.zeros(len(pos), dtype=bool)
    check = np.flatnonzero(plausible & complete & known)
    width = np.where(v2[check], 9, 5) + mlen[check]           # header after the magic + payload
    for w in np.flatnonzero(np.bincount(width)).tolist() if len(width) else []:
        sel = check[width == w]
        rows = np.empty((len(sel), w + 1), dtype=np.uint8)
        rows[:, :w] = rows_at(data, pos[sel] + 9, w)
        rows[:, w] = CRC_EXTRA[ids[sel]]
        end = pos[sel] + 8 + size[sel] - 2 - 13 * signed[sel]
        sent = data[end].astype(np.uint16) | data[end + 1].astype(np.uint16) << 8
        crc_ok[sel] = x25_crc_rows(rows) == sent
    flags = ((plausible & ~complete) * _TRUNC + (plausible & complete & (~known | crc_ok)) * _PLAIN
             + (cand & plausible & complete & crc_ok) * _RESYNC + cand * _CAND).astype(np.uint8)
    return pos, size.astype(np.int16), flags


def frame_records(data: np.ndarray, n: int, warnings: Counter) -> np.ndarray:
    """Start offsets of the good records of a .tlog held in ``data[:n]``, the
    records ``tlog_records`` yields, with the same corrupt and truncation counts.

    Every position whose byte 8 is a MAVLink magic is judged at once (``_judge_block``, a block
    of the file at a time): stamp plausible, packet complete, message id known, X.25 CRC
    (``mavlink_bulk.x25_crc_rows``, grouped by checked length).  A record chain is then followed:
    from a good record the next is at start + 8 + size, and while the next good position is
    exactly that one a whole run is taken at once; only where the chain breaks (garbage, a bad
    CRC, a false start inside a payload) is it walked position by position with the rules of
    ``tlog_records``: on the chain an unknown message id is a record (pymavlink decodes it as
    UNKNOWN_n); after a failure the next candidate (plausible stamp, known id, a payload length
    it can have) must have a good CRC; a plausible record cut off by the end stops the reading.
    """
    blocks = [_judge_block(data, n, a, a + _BLOCK) for a in range(0, max(n - 9, 0), _BLOCK)]
    pos, size, flags = (np.concatenate([b[k] for b in blocks]) if blocks else np.empty(0, int) for k in range(3))
    del blocks
    plain = (flags & _PLAIN) != 0
    chain = pos[plain]
    after = chain + 8 + size[plain]
    breaks = np.flatnonzero(after[:-1] != chain[1:])
    candidates = pos[(flags & _CAND) != 0]
    runs: list[tuple[int, int]] = []
    i, searching, corrupt = 0, False, 0
    while True:
        if i + 10 > n:
            if i < n:
                warnings[TRUNCATED] += 1
            break
        if searching:
            c = int(np.searchsorted(candidates, i))
            if c == len(candidates):
                warnings[TRUNCATED] += 1
                break
            i = int(candidates[c])
        k = int(np.searchsorted(pos, i))
        flag = int(flags[k]) if k < len(pos) and pos[k] == i else 0
        if flag & _TRUNC:
            warnings[TRUNCATED] += 1
            break
        if flag & (_RESYNC if searching else _PLAIN):
            j = int(np.searchsorted(chain, i))
            b = int(np.searchsorted(breaks, j))
            e = int(breaks[b]) if b < len(breaks) else len(chain) - 1
            runs.append((j, e + 1))
            i, searching = int(after[e]), False
            continue
        corrupt += 1
        i += 1
        searching = True
    if corrupt:
        warnings[CORRUPT] += corrupt
    return np.concatenate([chain[a:b] for a, b in runs]) if runs else np.empty(0, dtype=np.int64)


def despike_times(unix: np.ndarray, warnings: Counter, jump_s: float = STAMP_JUMP_S) -> np.ndarray:
    """Record stamps with single corrupt ones replaced: a stamp more than ``jump_s`` from the
    previous record's whose successor comes back gets the previous record's stamp (counted); a
    jump that persists (a new connection, the clock set) is kept.  The state machine runs only
    around the jumps; between them every stamp is kept as it is."""
    out = unix.copy()
    n = len(unix)
    if n < 2:
        return out
    jumps = np.flatnonzero(np.abs(np.diff(unix)) > jump_s) + 1
    prev, pending, spikes = float(unix[0]), None, 0
    k, q = 1, 0
    while k < n:
        if pending is None and prev == unix[k - 1]:        # a normal stretch: on to the next jump
            while q < len(jumps) and jumps[q] < k:
                q += 1
            if q == len(jumps):
                break
            k = int(jumps[q])
            prev = float(out[k - 1])
        u = float(unix[k])
        if pending is not None:
            p = float(unix[pending])
            if abs(u - prev) <= jump_s < abs(u - p):
                spikes += 1
                out[pending] = prev
            else:
                prev = p
            pending = None
        if abs(u - prev) > jump_s:
            pending = k
        else:
            prev = u
        k += 1
    if spikes:
        warnings[SPIKE] += spikes
    return out


def rebase_backwards(unix: np.ndarray, warnings: Counter) -> np.ndarray:
    """Arrival times on the log's time base: unix - first + shift, where the shift grows whenever
    the recorder's clock went back, so the arrival continues from where it was (counted)."""
    arrival = np.empty(len(unix))
    if not len(unix):
        return arrival
    first, shift, last, k, window, events = float(unix[0]), 0.0, -math.inf, 0, 1024, 0
    while k < len(unix):
        a = (unix[k:k + window] - first) + shift
        back = a < np.concatenate(([last], a[:-1]))
        e = int(np.argmax(back)) if back.any() else len(a)
        arrival[k:k + e] = a[:e]
        if e:
            last = float(a[e - 1])
        k += e
        if e < len(a):
            events += 1
            shift += last - float(a[e])
            arrival[k] = last
            k += 1
            window = 1024
        else:
            window = min(window * 2, 1 << 16)
    if events:
        warnings["timestamps going backwards (re-based)"] += events
    return arrival


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
    """The good records of one .tlog as columns (record order): start offset, message id, payload
    offset and length, source system, arrival time [s] on the log's time base."""

    def __init__(self, data: np.ndarray, starts: np.ndarray, arrival: np.ndarray) -> None:
        self.data, self.start, self.arrival = data, starts, arrival
        v2 = data[starts + 8] == 0xFD
        self.v2 = v2
        self.id = _msg_ids(data, starts, v2).astype(np.int32)
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


def _read_file(path: Path) -> tuple[np.ndarray, int]:
    """The file mapped read-only (the page cache holds it; no copy), and its length."""
    n = path.stat().st_size
    return (np.memmap(path, dtype=np.uint8, mode="r") if n else np.zeros(0, dtype=np.uint8)), n


def read_tlog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """A .tlog as a FlightLog, decoded column-wise: records framed and CRC-checked in bulk
    (``frame_records``), each message id's payloads one numpy structured array
    (``mavlink_bulk.payload_dtype``, pymavlink's layout), converted by the functions the live
    decoder uses (``decode.scaled_imu_to_si`` ...) with its rules: the vehicle is the first
    autopilot heartbeat's system, times from time_boot_ms through ``_BootClock.times``, each
    magnetometer source's unit judged at its first sample.  Parameters, status text, missions
    and calibration events (``_PER_PACKET``, a few a second) go through pymavlink and
    ``MavlinkDecoder`` packet by packet.  The same FlightLog as decoding every packet with
    ``MavlinkDecoder`` (tests/test_ingest_vectorised.py)."""
    data, n = _read_file(path)
    builder = LogBuilder(str(path))
    log, warnings = builder.log, builder.log.warnings
    starts = frame_records(data, n, warnings)
    if progress is not None:
        progress(0.3)
    stamps = rows_at(data, starts, 8).copy().view(">u8").ravel()
    unix = despike_times(stamps.astype(np.float64) * 1e-6, warnings)
    arrival = rebase_backwards(unix, warnings)
    start_unix = float(unix[0]) if len(unix) else None
    del stamps, unix
    rec = _Records(data, starts, arrival)
    del data, starts, arrival
    log.message_counts.update(rec.counts())
    decoder = _ColumnDecoder(rec, builder)
    decoder.run()
    del rec, decoder.rec, decoder.parts          # the file and its records: only the tables are left
    if progress is not None:
        progress(0.9)
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = start_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True  # ArduPilot sends the corrected field
    return log


class _ColumnDecoder:
    """``MavlinkDecoder``'s rules applied to whole columns of one log (its per-message state, the
    vehicle, the boot clock, the last GPS fix, the units judged, found with searchsorted over the
    record order).  Tables go to the builder as arrays, events (statuses, parameters, offsets) as
    samples in record order."""

    def __init__(self, rec: _Records, builder: LogBuilder) -> None:
        self.rec, self.builder = rec, builder
        self.warnings: Counter = Counter()
        self.autopilot: str | None = None
        self.events: list[tuple[int, object]] = []
        self.tables: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {
            "mag": [], "imu": [], "attitude": [], "gps": [], "battery": [], "throttle": []}
        self.vehicle: int | None = None
        self.h0 = len(rec.start)

    # ---------------------------------------------------------------- helpers
    def accepted(self, msg_id: int) -> np.ndarray:
        """Record indices of ``msg_id`` the decoder would use: before the vehicle is known every
        system's, after it the vehicle's only."""
        rows = self.rec.rows(msg_id)
        if self.vehicle is None:
            return rows
        return rows[(rows < self.h0) | (self.rec.sysid[rows] == self.vehicle)]

    def table(self, name: str, rows: np.ndarray, *columns) -> None:
        if len(rows):
            out = np.empty((len(rows), len(columns)))
            for j, c in enumerate(columns):          # converted column by column: no float copy of each
                out[:, j] = c
            self.tables[name].append((rows, out))

    # ---------------------------------------------------------------- run
    def run(self) -> None:
        rec = self.rec
        self._heartbeats()
        self._per_packet()
        st = self.accepted(_ID["SYSTEM_TIME"])
        usec = rec.fields(_ID["SYSTEM_TIME"], st)["time_unix_usec"]
        ok = np.flatnonzero(usec > 1e15)
        self.start_row = int(st[ok[0]]) if len(ok) else len(rec.start)
        self.start_unix = float(usec[ok[0]]) * 1e-6 - float(rec.arrival[st[ok[0]]]) if len(ok) else None
        self._gps_raw()
        times = self._clock()
        self._scaled(times)
        self._highres()
        self._attitude(times)
        self._global_position(times[_ID["GLOBAL_POSITION_INT"]])
        self._offsets()
        vfr = self.accepted(_ID["VFR_HUD"])
        thr, valid = dec.vfr_hud_throttle(rec.fields(_ID["VFR_HUD"], vfr)["throttle"])
        self.table("throttle", vfr[valid], rec.arrival[vfr[valid]], thr[valid])
        sys = self.accepted(_ID["SYS_STATUS"])
        amps, valid = dec.sys_status_current_A(rec.fields(_ID["SYS_STATUS"], sys)["current_battery"])
        self.table("battery", sys[valid], rec.arrival[sys[valid]], amps[valid])
        self._finish()

    def _heartbeats(self) -> None:
        rows = self.rec.rows(_ID["HEARTBEAT"])
        f = self.rec.fields(_ID["HEARTBEAT"], rows)
        autopilot_hb = (f["type"] != dec.MAV_TYPE_GCS) & (f["autopilot"] != 8)     # 8: MAV_AUTOPILOT_INVALID
        first = np.flatnonzero(autopilot_hb)
        if not len(first):
            return
        self.h0 = int(rows[first[0]])
        self.vehicle = int(self.rec.sysid[self.h0])
        mine = autopilot_hb & (self.rec.sysid[rows] == self.vehicle)
        names = {dec.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", dec.MAV_AUTOPILOT_PX4: "px4"}
        for r, ap in zip(rows[mine].tolist(), f["autopilot"][mine].tolist()):
            name = names.get(ap)
            if name and name != self.autopilot:
                self.autopilot = name
                self.events.append((r, StatusSample(float(self.rec.arrival[r]), "autopilot", name)))

    def _per_packet(self) -> None:
        rows = np.sort(np.concatenate([self.rec.rows(i) for i in _PER_PACKET]))
        self.param_rows = self.rec.rows(_ID["PARAM_VALUE"])
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        decoder = MavlinkDecoder()
        for r in rows.tolist():
            msg = _decode(parser.decode, self.rec.packet(r))
            if msg is None:
                self.warnings[CORRUPT] += 1
                continue
            decoder.vehicle_sysid = self.vehicle if r > self.h0 else None
            for s in decoder.decode(msg, float(self.rec.arrival[r])):
                self.events.append((r, s))
        self.warnings.update(decoder.warnings)

    def _gps_raw(self) -> None:
        rows = self.accepted(_ID["GPS_RAW_INT"])
        f = self.rec.fields(_ID["GPS_RAW_INT"], rows)
        self.gps_rows, self.gps_fix = rows, f["fix_type"].astype(np.int64)
        use = (f["fix_type"] >= 2) & ~((f["lat"] == 0) & (f["lon"] == 0))
        g = f[use]
        lat, lon, alt, vn, ve, vd = dec.gps_raw_int_to_si(g["lat"], g["lon"], g["alt"], g["vel"], g["cog"])
        self.place_rows, self.place = rows[use], np.column_stack([lat, lon, alt]) if len(g) else np.empty((0, 3))
        self.table("gps", rows[use], self.rec.arrival[rows[use]], lat, lon, alt, vn, ve, vd, g["fix_type"])

    def _clock(self) -> dict[int, np.ndarray]:
        """Boot-clock times of every message that has them, in record order through one clock."""
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
        rows = np.concatenate([p[0] for p in parts.values()])
        boot = np.concatenate([p[1] for p in parts.values()])
        order = np.argsort(rows, kind="stable")
        t = np.empty(len(rows))
        t[order] = dec._BootClock().times(boot[order], self.rec.arrival[rows[order]])
        out, k = {}, 0
        self.parts = {i: p[0] for i, p in parts.items()}
        for i, (r, _) in parts.items():
            out[i] = t[k:k + len(r)]
            k += len(r)
        return out

    def _place_before(self, r: int) -> tuple[float, float, float] | None:
        k = int(np.searchsorted(self.place_rows, r)) - 1
        return None if k < 0 else tuple(float(v) for v in self.place[k])

    def _judge(self, instance: int, rows: np.ndarray, t: np.ndarray, sent: np.ndarray, units) -> float | None:
        """The scale of a magnetometer source judged at its first non-zero sample (the decoder's
        ``judge_first_field``), its warning counted; None when every sample is zero."""
        nonzero = np.flatnonzero((sent != 0).any(axis=1))
        if not len(nonzero):
            return None
        k = int(nonzero[0])
        r = int(rows[k])
        unit = dec.judge_first_field(instance, tuple(float(v) for v in sent[k]), units, float(t[k]),
                                     self._place_before(r), self.start_unix if self.start_row < r else None)
        if not unit.plausible:
            self.warnings[f"{unit.source}: implausible magnetometer field ({unit.why})"] += 1
        return unit.scale_to_mG

    def _scaled(self, times: dict[int, np.ndarray]) -> None:
        for msg_id, instance in _SCALED.items():
            if msg_id == _ID["RAW_IMU"]:
                rows = self.accepted(msg_id)
                f, t = self.rec.fields(msg_id, rows), self.rec.arrival[rows]
            else:
                rows = self.parts[msg_id]
                f = self.rec.fields(msg_id, rows)
                t = times[msg_id]
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

    def _highres(self) -> None:
        rows = self.accepted(_ID["HIGHRES_IMU"])
        if not len(rows):
            return
        f = self.rec.fields(_ID["HIGHRES_IMU"], rows)
        t = self.rec.arrival[rows]
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
        last_t = np.where(k >= 0, self.rec.arrival[self.gps_rows[np.maximum(k, 0)]] if len(self.gps_rows) else 0.0,
                          -math.inf)
        fix = np.where(k >= 0, self.gps_fix[np.maximum(k, 0)] if len(self.gps_rows) else 0, 3)
        use = ~(t - last_t < 3.0) & ~((f["lat"] == 0) & (f["lon"] == 0))
        g = f[use]
        cols = dec.global_position_int_to_si(g["lat"], g["lon"], g["alt"], g["vx"], g["vy"], g["vz"])
        self.table("gps", rows[use], t[use], *cols, fix[use])

    def _offsets(self) -> None:
        """SENSOR_OFFSETS: compass 0's offsets as history entries; a record repeating the previous
        one's values (with no PARAM_VALUE between, which could name the same parameter) adds
        nothing to the history (``compact_history`` drops such repeats) and is skipped here."""
        rows = self.accepted(_ID["SENSOR_OFFSETS"])
        f = self.rec.fields(_ID["SENSOR_OFFSETS"], rows)
        ofs = np.column_stack([f["mag_ofs_x"], f["mag_ofs_y"], f["mag_ofs_z"]])
        group = np.searchsorted(self.param_rows, rows)
        keep = np.ones(len(rows), dtype=bool)
        keep[1:] = (ofs[1:] != ofs[:-1]).any(axis=1) | (group[1:] != group[:-1])
        for r, v in zip(rows[keep].tolist(), ofs[keep].tolist()):
            self.events.append((r, OffsetsSample(float(self.rec.arrival[r]), 0, tuple(float(x) for x in v), 1.0)))

    def _finish(self) -> None:
        for name, parts in self.tables.items():
            if len(parts) == 1:
                self.builder.set_table(name, parts[0][1])            # one message type: in record order
            elif parts:
                rows = np.concatenate([p[0] for p in parts])
                order = np.argsort(rows, kind="stable")
                self.builder.set_table(name, np.concatenate([p[1] for p in parts])[order])
        self.tables.clear()
        self.events.sort(key=lambda e: e[0])
        for _, s in self.events:
            self.builder.add(s)
