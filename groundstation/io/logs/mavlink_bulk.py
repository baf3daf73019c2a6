"""MAVLink packets in bulk: X.25 CRC over many packets at once and payloads as numpy structured arrays.

pymavlink stays the definition of every message: the payload layout of message id ``i`` is
``mavlink2.mavlink_map[i]``'s ``unpacker.format`` (little-endian, fields in wire order, sorted by
size) with the names of ``ordered_fieldnames``; its ``crc_extra`` seeds the CRC.  A payload shorter
than the layout (MAVLink 2 trims trailing zero bytes) is zero-extended, a longer one is cut, as
pymavlink's ``decode`` does.

CRC: MAVLink's X.25 (CRC-16/MCRF4XX: reflected polynomial 0x8408, initial 0xFFFF) over the header
after the magic byte, the payload and the message's CRC_EXTRA byte.  Packets of one checked length
are one 2-D array; two bytes are folded per step with a 65536-entry table, T16[crc ^ word], where
T16[x] is the CRC state after the two bytes of x from state 0 (the CRC is linear: after two bytes
the state depends only on crc ^ word).
"""
from __future__ import annotations

import re
import struct
from functools import lru_cache

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..mavlink import mavlink2

CORRUPT = "corrupt packets skipped (bad CRC or garbage)"

__all__ = ["CORRUPT", "payload_dtype", "x25_crc_rows", "rows_at", "byte_at", "decode_packet", "KNOWN_IDS", "CRC_EXTRA", "PAYLOAD_SIZE"]

KNOWN_IDS = np.array(sorted(mavlink2.mavlink_map), dtype=np.int64)
_MAX_ID = int(KNOWN_IDS.max()) + 1
CRC_EXTRA = np.zeros(_MAX_ID, dtype=np.uint8)        # by message id (0 where unknown: see KNOWN)
PAYLOAD_SIZE = np.zeros(_MAX_ID, dtype=np.int64)     # the full payload of each known id
KNOWN = np.zeros(_MAX_ID, dtype=bool)
for _i in KNOWN_IDS.tolist():
    CRC_EXTRA[_i] = mavlink2.mavlink_map[_i].crc_extra
    PAYLOAD_SIZE[_i] = mavlink2.mavlink_map[_i].unpacker.size
    KNOWN[_i] = True

_STRUCT_TO_NUMPY = {"B": "u1", "b": "i1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "q": "<i8",
                    "Q": "<u8", "f": "<f4", "d": "<f8", "c": "S1"}


def _table8() -> np.ndarray:
    """T8[x]: the term of one X.25 step (pymavlink's ``x25crc.accumulate``) that depends on
    x = (crc ^ byte) & 0xFF; the step is crc' = (crc >> 8) ^ T8[x]."""
    x = np.arange(256, dtype=np.uint32)
    tmp = (x ^ (x << 4)) & 0xFF
    return ((tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


_T8 = _table8()                                  # crc' = (crc >> 8) ^ T8[(crc ^ b) & 0xFF]
_x = np.arange(65536, dtype=np.uint32)
_c1 = (_x >> 8) ^ _T8[_x & 0xFF]                 # one byte (the low byte of x) from state x, then
_T16 = ((_c1 >> 8) ^ _T8[_c1 & 0xFF]).astype(np.uint16)   # the second from state 0: T16[crc ^ word]
del _x, _c1


def x25_crc_rows(rows: np.ndarray) -> np.ndarray:
    """X.25 CRC of each row of a 2-D uint8 array (all rows one length), as uint16 per row; the same
    value as ``mavlink2.x25crc(bytes(row)).crc``."""
    n, width = rows.shape
    crc = np.full(n, 0xFFFF, dtype=np.uint16)
    if width % 2:
        crc = ((crc >> 8) ^ _T8[(crc ^ rows[:, 0]) & 0xFF]).astype(np.uint16)
        rows = rows[:, 1:]
    if rows.shape[1]:
        words = np.ascontiguousarray(rows).view("<u2")
        for j in range(words.shape[1]):
            crc = _T16[crc ^ words[:, j]]
    return crc


def rows_at(data: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """``data[s:s + width]`` for each start, as one (n, width) uint8 array; bytes past the end of
    ``data`` read as zero."""
    starts = np.asarray(starts, dtype=np.int64)
    if width == 0:
        return np.zeros((len(starts), 0), dtype=np.uint8)
    n = len(data)
    if not len(starts) or (width <= n and int(starts.max()) + width <= n):
        return sliding_window_view(data, width)[starts]
    out = np.zeros((len(starts), width), dtype=np.uint8)
    inside = starts + width <= n
    if width <= n and inside.any():
        out[inside] = sliding_window_view(data, width)[starts[inside]]
    for i in np.flatnonzero(~inside).tolist():
        tail = data[int(starts[i]):n]
        out[i, :len(tail)] = tail
    return out


def byte_at(data: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``data[idx]``, zero past the end."""
    n = len(data)
    if not len(idx) or int(idx.max()) < n:
        return data[idx]
    return np.where(idx < n, data[np.minimum(idx, max(n - 1, 0))], 0).astype(np.uint8)


@lru_cache(maxsize=None)
def payload_dtype(msg_id: int) -> np.dtype:
    """The structured dtype of message ``msg_id``'s payload, from pymavlink's own definition:
    ``unpacker.format`` read token by token (``16s`` one string field, ``4f`` one array field,
    ``lengths`` the array lengths) in the wire order of ``ordered_fieldnames``."""
    cls = mavlink2.mavlink_map[msg_id]
    tokens = re.findall(r"(\d*)([a-zA-Z?])", cls.unpacker.format.lstrip("<>=!@"))
    names, formats, offsets, offset = [], [], [], 0
    lengths = list(cls.lengths)
    for pos, (count, char) in enumerate(tokens):
        n = int(count) if count else 1
        name = cls.ordered_fieldnames[pos]
        if char == "s":
            fmt, size = f"S{n}", n
        else:
            base = np.dtype(_STRUCT_TO_NUMPY[char])
            if n != lengths[pos]:
                raise ValueError(f"{cls.msgname}: format {cls.unpacker.format} does not match lengths {lengths}")
            fmt, size = ((base, (n,)) if n > 1 else base), base.itemsize * n
        names.append(name)
        formats.append(fmt)
        offsets.append(offset)
        offset += size
    if offset != cls.unpacker.size:
        raise ValueError(f"{cls.msgname}: layout {offset} bytes, pymavlink {cls.unpacker.size}")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": offset})


def decode_payloads(data: np.ndarray, starts: np.ndarray, lengths: np.ndarray, msg_id: int) -> np.ndarray:
    """Payloads of one message id (at ``starts``, ``lengths`` bytes as sent) as a structured array:
    zero-extended where shorter than the layout, cut where longer (pymavlink's ``decode``)."""
    dtype = payload_dtype(msg_id)
    rows = rows_at(data, starts, dtype.itemsize)          # a copy (fancy indexing)
    short = lengths < dtype.itemsize
    if short.any():
        for length in np.unique(lengths[short]).tolist():     # a few lengths: no (n, size) mask
            rows[lengths == length, length:] = 0
    return rows.view(dtype).ravel()


def decode_packet(decode, packet: bytearray):
    """pymavlink's ``decode`` of one whole packet, None when it refuses it (bad CRC, damage)."""
    try:
        return decode(packet)
    except (mavlink2.MAVError, struct.error, IndexError, ValueError, TypeError):
        return None
