"""MAVLink telemetry logs (.tlog): 8-byte big-endian UNIX microseconds + one MAVLink packet per record."""
from __future__ import annotations

import math
import struct
from collections import Counter
from pathlib import Path
from typing import Callable, Iterator

from ..decode import MavlinkDecoder
from ..mavlink import mavlink2
from .builder import LogBuilder
from ...samples import FlightLog

__all__ = ["read_tlog", "tlog_records"]

TLOG_STAMP = struct.Struct(">Q")
_PLAUSIBLE_UNIX_S = (946684800.0, 4102444800.0)  # 2000..2100


def tlog_records(data: bytes, warnings: Counter) -> Iterator[tuple[float, object]]:
    """(UNIX time, message) of each good record of a .tlog image.

    A record is an 8-byte big-endian microsecond stamp and one MAVLink 1 (0xFE) or 2 (0xFD)
    packet, so the packet length is known from its header and pymavlink's ``decode`` (CRC
    checked) gets whole packets; that skips its byte-at-a-time stream parser, which is built
    for serial links.  After garbage or a bad CRC we resynchronise on the next position whose
    stamp is plausible and whose packet decodes; a cut-off last record is reported.
    """
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    n = len(data)
    i = 0
    last_unix: float | None = None
    while i + 10 <= n:
        magic = data[i + 8]
        if magic == 0xFD:
            size = 12 + data[i + 9] + (13 if data[i + 10] & 1 else 0)
        elif magic == 0xFE:
            size = 8 + data[i + 9]
        else:
            size = 0
        unix = TLOG_STAMP.unpack_from(data, i)[0] * 1e-6
        plausible = (_PLAUSIBLE_UNIX_S[0] < unix < _PLAUSIBLE_UNIX_S[1]
                     and (last_unix is None or abs(unix - last_unix) < 86400.0))
        if size and plausible:
            if i + 8 + size > n:
                warnings["log truncated: last record cut off"] += 1
                return
            try:
                msg = parser.decode(bytearray(data[i + 8:i + 8 + size]))
            except (mavlink2.MAVError, struct.error, IndexError, ValueError, TypeError):
                msg = None
            if msg is not None:
                last_unix = unix
                i += 8 + size
                yield unix, msg
                continue
        warnings["corrupt packets skipped (bad CRC or garbage)"] += 1
        i = _next_record(data, i + 1, last_unix)
    if i < n:
        warnings["log truncated: last record cut off"] += 1


def _next_record(data: bytes, start: int, last_unix: float | None) -> int:
    """Index of the next plausible record start (stamp then a MAVLink magic byte) after garbage."""
    n = len(data)
    j = start
    while True:
        hits = [k for k in (data.find(b"\xfd", j + 8), data.find(b"\xfe", j + 8)) if k >= 0]
        if not hits:
            return n
        k = min(hits) - 8
        unix = TLOG_STAMP.unpack_from(data, k)[0] * 1e-6
        if (_PLAUSIBLE_UNIX_S[0] < unix < _PLAUSIBLE_UNIX_S[1]
                and (last_unix is None or abs(unix - last_unix) < 86400.0)):
            return k
        j = k + 1


def read_tlog(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    data = path.read_bytes()
    builder = LogBuilder(str(path))
    decoder = MavlinkDecoder()
    counts = builder.log.message_counts
    warnings = builder.log.warnings
    first_unix = None
    last_arrival = -math.inf
    backwards_shift = 0.0
    decode = decoder.decode
    add = builder.add
    for n, (unix, msg) in enumerate(tlog_records(data, warnings)):
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
            progress(n / max(len(data) / 40, 1))
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = first_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True  # ArduPilot sends the corrected field
    return log
