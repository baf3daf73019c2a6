"""UDP links parsed datagram by datagram, with the sender of each packet (for the live link)."""
from __future__ import annotations

import platform
import socket
import struct
import sys
from collections import deque

from .mavlink import mavlink2

__all__ = ["parse_each_datagram_alone", "UDP_RECEIVE_BUFFER_BYTES"]

UDP_RECEIVE_BUFFER_BYTES = 4 << 20
# the kernel's receive time, SO_TIMESTAMPNS (Linux asm-generic value; Python's socket module does
# not name it): asked for only where the number is known to mean it, on 64-bit Linux
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", None) or (
    35 if sys.platform == "linux" and platform.machine() in ("x86_64", "aarch64") else None)
_TIMESPEC = struct.Struct("@qq")                                # struct timespec on 64-bit Linux


def parse_each_datagram_alone(conn) -> None:
    """UDP carries whole MAVLink packets in each datagram (one or several), so every datagram is
    parsed on its own: bytes left over from one (garbage, or a packet cut short) must not be joined
    to the next, or a good packet would be read as the tail of a bad one and lost to its CRC.
    pymavlink's mavudp keeps one byte buffer across datagrams; this replaces its recv_msg for the
    link (serial/TCP are byte streams and keep pymavlink's parser as it is)."""
    from pymavlink import mavutil

    if not isinstance(conn, mavutil.mavudp):
        return
    try:    # room for ~1 s of a busy link while the station is held up (capped by net.core.rmem_max)
        conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER_BYTES)
    except OSError:
        pass
    conn.port = _AddressRecordingSocket(conn.port)
    conn.port.ask_kernel_times()
    parser = conn.mav
    pending: deque = deque()

    def forget_partial() -> None:
        parser.buf = bytearray()
        parser.buf_index = 0
        parser.expected_length = mavlink2.HEADER_LEN_V1 + 2
        parser.have_prefix_error = False

    def recv_msg():
        while not pending:
            conn.pre_message()
            data = conn.recv()
            if not data:
                return None
            if conn.first_byte:
                conn.auto_mavlink_version(data)
            forget_partial()        # what the last datagram left (garbage, a cut-short packet)
            for m in parser.parse_buffer(data) or ():
                m._src_addr = conn.port.last_from      # who sent it (the link's param_guard asks)
                m._arrival_unix = conn.port.last_arrival_unix
                pending.append(m)
        msg = pending.popleft()
        conn.post_message(msg)
        return msg

    conn.recv_msg = recv_msg


class _AddressRecordingSocket:
    """A UDP socket that remembers the address of the last datagram it received (pymavlink's
    mavudp keeps no per-datagram address in udpin mode) and when the kernel received it
    (``last_arrival_unix``, SO_TIMESTAMPNS; None where the system has no such stamp); everything
    else is the socket's.

    The kernel's time is the datagram's arrival even when the station reads it late: a reader
    thread kept from Python's interpreter lock by busy estimation threads (each read gives the
    lock up and waits for it again) would otherwise stamp a backlog as a link delay, and the boot
    clock re-anchors after 5 s of such lateness, jumping the samples' times by seconds."""

    def __init__(self, sock) -> None:
        self._sock = sock
        self.last_from = None
        self.last_arrival_unix: float | None = None
        self._kernel_times = False

    def ask_kernel_times(self) -> None:
        if _SO_TIMESTAMPNS is None:
            return
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self._kernel_times = True
        except OSError:
            pass

    def recvfrom(self, bufsize: int, *args):
        if not self._kernel_times:
            data, addr = self._sock.recvfrom(bufsize, *args)
            self.last_from, self.last_arrival_unix = addr, None
            return data, addr
        data, ancillary, _flags, addr = self._sock.recvmsg(bufsize, socket.CMSG_SPACE(_TIMESPEC.size), *args)
        self.last_from, self.last_arrival_unix = addr, _kernel_time(ancillary)
        return data, addr

    def __getattr__(self, name):
        return getattr(self._sock, name)


def _kernel_time(ancillary: list) -> float | None:
    """The SO_TIMESTAMPNS stamp among a datagram's ancillary items, in UNIX seconds."""
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
            seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
            return seconds + nanoseconds * 1e-9
    return None
