"""UDP links parsed datagram by datagram, with the sender of each packet (for the live link)."""
from __future__ import annotations

import socket
from collections import deque

from .mavlink import mavlink2

__all__ = ["parse_each_datagram_alone", "UDP_RECEIVE_BUFFER_BYTES"]

UDP_RECEIVE_BUFFER_BYTES = 4 << 20


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
                pending.append(m)
        msg = pending.popleft()
        conn.post_message(msg)
        return msg

    conn.recv_msg = recv_msg


class _AddressRecordingSocket:
    """A UDP socket that remembers the address of the last datagram it received (pymavlink's
    mavudp keeps no per-datagram address in udpin mode); everything else is the socket's."""

    def __init__(self, sock) -> None:
        self._sock = sock
        self.last_from = None

    def recvfrom(self, *args):
        data, addr = self._sock.recvfrom(*args)
        self.last_from = addr
        return data, addr

    def __getattr__(self, name):
        return getattr(self._sock, name)
