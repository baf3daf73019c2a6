"""MAVLink telemetry logs (.tlog): 8-byte big-endian UNIX microseconds + one MAVLink packet per record.

``read_tlog`` (the FlightLog) decodes column-wise with bounded temporaries: the file is read a
window at a time (``_FileBytes``), its records framed and CRC-checked in bulk (``frame_records``),
then decoded a run of records at a time (``DECODE_RECORDS``): each message id's payloads one numpy
structured array (``mavlink_bulk``), the decoder's rules on the run's columns with what they need
from earlier runs carried (``_ColumnDecoder``).  The process holds the tables it builds and 16
bytes a record, not the file.  Corrupt stamps (``despike_times``) and a clock going back
(``rebase_backwards``) are handled on the time column.  ``tlog_records`` yields (UNIX time,
pymavlink message) per record, streaming in bounded chunks (the station's replay and the
recordings list); both frame the same records with the same resynchronisation after garbage
(linear: candidate starts are found with numpy) and the same corrupt counts.
"""
from __future__ import annotations

import bisect
import io
import math
import os
import struct
from collections import Counter
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from ..decode import MavlinkDecoder
from ..mavlink import mavlink2
from .builder import LogBuilder
from .mavlink_bulk import CORRUPT, decode_packet as _decode, CRC_EXTRA, KNOWN, PAYLOAD_SIZE, byte_at, rows_at, x25_crc_rows
from .mavlink_columns import _ColumnDecoder, _Records, msg_ids as _msg_ids
from ...samples import FlightLog

__all__ = ["read_tlog", "tlog_records", "frame_records", "despike_times", "rebase_backwards"]

TLOG_STAMP = struct.Struct(">Q")
_PLAUSIBLE_UNIX_S = (946684800.0, 4102444800.0)  # 2000..2100
_PLAUSIBLE_US = (int(_PLAUSIBLE_UNIX_S[0] * 1e6), int(_PLAUSIBLE_UNIX_S[1] * 1e6))
MAX_RECORD = 8 + 10 + 255 + 2 + 13      # stamp + the largest MAVLink 2 packet (signed)
CHUNK_BYTES = 1 << 18
DECODE_RECORDS = 1 << 15                 # records decoded at once (read_tlog: bounds the temporaries)
STAMP_JUMP_S = 60.0                      # a record this far from both neighbours has a corrupt stamp
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


TRUNCATED = "log truncated: last record cut off"


_TRUNC, _PLAIN, _RESYNC, _CAND = 1, 2, 4, 8   # frame_records: what a position is
_BLOCK = 1 << 18                              # file bytes judged at once (bounds the temporaries)


def _judge_block(data: np.ndarray, n: int, a: int,
                 b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(positions, record sizes, flags, stamps [us]) of the positions a <= p < b whose byte 8 is a
    MAVLink magic (p <= n - 10); flags: _TRUNC a plausible record cut off by the end, _PLAIN a
    record on the chain, _CAND a resynchronisation candidate, _RESYNC a candidate that is a record."""
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
    return pos, size.astype(np.int16), flags, stamp_us


def frame_records(read: Callable[[int, int], np.ndarray], n: int,
                  warnings: Counter) -> tuple[np.ndarray, np.ndarray]:
    """(start offsets, stamps [us]) of the good records of a .tlog of ``n`` bytes, the records
    ``tlog_records`` yields, with the same corrupt and truncation counts; ``read(lo, hi)`` gives
    the file's bytes lo..hi (fewer at its end).

    The file is framed a window (``_BLOCK`` bytes and the longest record after them) at a time,
    so the bytes held and the temporaries are bounded: every position of the window whose byte 8
    is a MAVLink magic is judged at once (``_judge_block``: stamp plausible, packet complete,
    message id known, X.25 CRC, grouped by checked length).  A record chain is then followed:
    from a good record the next is at start + 8 + size, and while the next good position is
    exactly that one a whole run is taken at once; only where the chain breaks (garbage, a bad
    CRC, a false start inside a payload) is it walked position by position with the rules of
    ``tlog_records``: on the chain an unknown message id is a record (pymavlink decodes it as
    UNKNOWN_n); after a failure the next candidate (plausible stamp, known id, a payload length
    it can have) must have a good CRC; a plausible record cut off by the end stops the reading.
    """
    starts: list[np.ndarray] = []
    stamps: list[np.ndarray] = []
    i, searching, corrupt = 0, False, 0
    lo = hi = 0                                  # the window judged: positions lo <= p < hi
    judged_end = max(n - 9, 0)                   # positions judged: p < judged_end
    while True:
        if i + 10 > n:
            if i < n:
                warnings[TRUNCATED] += 1
            break
        if not lo <= i < hi:                     # the window holding i
            lo = i - i % _BLOCK
            hi = lo + _BLOCK
            data = read(lo, hi + MAX_RECORD + 9)
            pos, size, flags, stamp_us = _judge_block(data, len(data), 0, hi - lo)
            pos += lo
            plain = (flags & _PLAIN) != 0
            chain, chain_us = pos[plain], stamp_us[plain].astype(np.uint64)
            after = chain + 8 + size[plain]
            breaks = np.flatnonzero(after[:-1] != chain[1:])
            candidates = pos[(flags & _CAND) != 0]
        if searching:
            c = int(np.searchsorted(candidates, i))
            if c == len(candidates):
                if hi >= judged_end:
                    warnings[TRUNCATED] += 1
                    break
                i = hi                           # none in this window: search on in the next
                continue
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
            starts.append(chain[j:e + 1])
            stamps.append(chain_us[j:e + 1])
            i, searching = int(after[e]), False
            continue
        corrupt += 1
        i += 1
        searching = True
    if corrupt:
        warnings[CORRUPT] += corrupt
    if not starts:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.uint64)
    starts_all = np.concatenate(starts)
    del starts                                   # one list of pieces held beside its whole at a time
    return starts_all, np.concatenate(stamps)


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


def _arrival(stamps_us: np.ndarray, warnings: Counter) -> tuple[np.ndarray, float | None]:
    """(arrival time of each record on the log's time base [s], the first record's UNIX time):
    corrupt stamps replaced (``despike_times``), a clock going back re-based (``rebase_backwards``)."""
    unix = despike_times(stamps_us.astype(np.float64) * 1e-6, warnings)
    return rebase_backwards(unix, warnings), (float(unix[0]) if len(unix) else None)


class _FileBytes:
    """Byte ranges of an open file of ``n`` bytes (its size when opened), read when asked: a reader
    going through the file holds a window of it, not the file, and a file cut short while it is
    read gives fewer bytes, never a fault of a mapped page."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.n = os.fstat(f.fileno()).st_size

    def read(self, lo: int, hi: int) -> np.ndarray:
        """The bytes lo..hi as read-only uint8 (fewer at the end of the file)."""
        self.f.seek(lo)
        return np.frombuffer(self.f.read(max(min(hi, self.n) - lo, 0)), dtype=np.uint8)


def read_tlog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """A .tlog as a FlightLog, decoded column-wise: records framed and CRC-checked in bulk
    (``frame_records``), each message id's payloads one numpy structured array
    (``mavlink_bulk.payload_dtype``, pymavlink's layout), converted by the functions the live
    decoder uses (``decode.scaled_imu_to_si`` ...) with its rules: the vehicle is the first
    autopilot heartbeat's system, times from time_boot_ms (and RAW_IMU/HIGHRES_IMU time_usec where
    it is a boot time) through ``BootClock.times``, each magnetometer source's unit judged at its
    first sample.  Parameters, status text, missions
    and calibration events (``_PER_PACKET``, a few a second) go through pymavlink and
    ``MavlinkDecoder`` packet by packet.  The same FlightLog as decoding every packet with
    ``MavlinkDecoder`` (tests/test_ingest_vectorised.py)."""
    builder = LogBuilder(str(path))
    log, warnings = builder.log, builder.log.warnings
    with open(path, "rb") as f:
        file = _FileBytes(f)
        starts, stamps = frame_records(file.read, file.n, warnings)
        if progress is not None:
            progress(0.3)
        arrival, start_unix = _arrival(stamps, warnings)
        del stamps
        decoder = _ColumnDecoder(builder, len(starts))
        for a in range(0, len(starts), DECODE_RECORDS):     # bounded temporaries: a run of records at a time
            run = starts[a:a + DECODE_RECORDS]
            lo = int(run[0])     # the run's bytes are held by its _Records only: freed before its rows are kept
            decoder.run(_Records(file.read(lo, int(run[-1]) + MAX_RECORD), run - lo, arrival[a:a + DECODE_RECORDS],
                                 base=a))
            if progress is not None:
                progress(0.3 + 0.6 * (a + len(run)) / len(starts))
        del starts, arrival, file                # the records: only the tables are left
    decoder.finish()
    log.message_counts.update(decoder.counts)
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = start_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True  # ArduPilot sends the corrected field
    return log
