"""MAVLink telemetry logs (.tlog): 8-byte big-endian UNIX microseconds + one MAVLink packet per record.

The file is read in chunks (memory bounded by the chunk, not the file), garbage is skipped in
linear time (candidate record starts are found with numpy over growing windows), and a record
whose stamp jumps away and straight back (a flipped bit) gets its neighbour's time.
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

from ..decode import MavlinkDecoder
from ..mavlink import mavlink2
from .builder import LogBuilder
from ...samples import FlightLog

__all__ = ["read_tlog", "tlog_records", "despiked"]

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
            size = 12 + buf[i + 9] + (13 if buf[i + 10] & 1 else 0)
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


def despiked(records: Iterator[tuple[float, object]], warnings: Counter,
             jump_s: float = STAMP_JUMP_S) -> Iterator[tuple[float, object]]:
    """Records whose stamp jumps more than ``jump_s`` away from the previous record and whose
    successor comes back (one corrupt stamp, e.g. a flipped bit) get the previous record's
    stamp and are counted; a jump that persists (a new connection, the clock set) is kept."""
    prev: float | None = None
    pending: tuple[float, object] | None = None
    for unix, msg in records:
        if pending is not None:
            p_unix, p_msg = pending
            pending = None
            if abs(unix - prev) <= jump_s < abs(unix - p_unix):
                warnings[SPIKE] += 1
                yield prev, p_msg
            else:
                prev = p_unix
                yield p_unix, p_msg
        if prev is not None and abs(unix - prev) > jump_s:
            pending = (unix, msg)
            continue
        prev = unix
        yield unix, msg
    if pending is not None:
        yield pending


def read_tlog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    builder = LogBuilder(str(path))
    decoder = MavlinkDecoder()
    counts = builder.log.message_counts
    warnings = builder.log.warnings
    first_unix = None
    last_arrival = -math.inf
    backwards_shift = 0.0
    decode = decoder.decode
    add = builder.add
    size = max(path.stat().st_size, 1)
    with open(path, "rb") as f:
        for n, (unix, msg) in enumerate(despiked(tlog_records(f, warnings), warnings)):
            counts[msg.get_type()] += 1
            if first_unix is None:
                first_unix = unix
            arrival = unix - first_unix + backwards_shift
            if arrival < last_arrival:  # the recorder's clock went back: continue from where it was
                warnings["timestamps going backwards (re-based)"] += 1
                backwards_shift += last_arrival - arrival
                arrival = last_arrival
            last_arrival = arrival
            for s in decode(msg, arrival):
                add(s)
            if progress is not None and n % 20000 == 0:
                progress(min(f.tell() / size, 1.0))
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = first_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True  # ArduPilot sends the corrected field
    return log
