"""MAVLink 2 (ardupilotmega dialect, a superset of common) encoding and `.tlog` writing.

A `.tlog` is a sequence of records: 8-byte big-endian microseconds since the UNIX epoch,
followed by one raw MAVLink packet.  That is what Mission Planner and QGroundControl write,
and what pymavlink's reader expects.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = ["mavlink2", "TlogWriter", "new_encoder"]


def new_encoder(system_id: int = 1, component_id: int = 1) -> mavlink2.MAVLink:
    """A MAVLink 2 packer with its own sequence counter (no file attached)."""
    enc = mavlink2.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    enc.robust_parsing = True
    return enc


class TlogWriter:
    """Append MAVLink messages to a `.tlog`, each stamped with its UNIX time.

    ``write_packet`` takes raw bytes already on the wire (a live link being recorded);
    ``write_message`` packs a pymavlink message object first.  ``flush_every_s`` bounds how much a
    crash can lose.
    """

    def __init__(self, path: str | Path, system_id: int = 1, component_id: int = 1) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = open(self.path, "ab")
        self.encoder = new_encoder(system_id, component_id)

    def write_packet(self, packet: bytes, unix_s: float) -> None:
        self._file.write(struct.pack(">Q", int(round(unix_s * 1e6))) + packet)

    def write_message(self, msg: mavlink2.MAVLink_message, unix_s: float) -> None:
        self.write_packet(bytes(msg.pack(self.encoder)), unix_s)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> "TlogWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
