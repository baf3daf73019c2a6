"""Live MAVLink links (UDP/TCP/serial through pymavlink) as a typed sample stream."""
from __future__ import annotations

import time

from .decode import MAV_CMD_SET_MESSAGE_INTERVAL, MavlinkDecoder
from .errors import IngestError
from .mavlink import mavlink2
from ..samples import Sample, StatusSample

__all__ = ["LiveLink", "STREAMED_MESSAGES", "validate_connection_string"]

STREAMED_MESSAGES = ("SCALED_IMU", "RAW_IMU", "ATTITUDE", "GPS_RAW_INT", "GLOBAL_POSITION_INT",
                     "HIGHRES_IMU")


def _drop_partial_packets_between_datagrams(conn) -> None:
    """UDP carries whole MAVLink packets per datagram, so an incomplete packet left in the
    parser when the next datagram arrives can only be garbage: drop it, or the parser would
    complete it with the next (good) packet's bytes and lose that packet to a CRC error.
    (Wraps pymavlink's mavudp.recv; serial/TCP streams are left alone.)"""
    from pymavlink import mavutil

    if not isinstance(conn, mavutil.mavudp):
        return
    parser = conn.mav
    raw_recv = conn.recv

    def recv(n=None):
        data = raw_recv(n)
        if data and 0 < parser.buf_len() < parser.expected_length:
            parser.buf = bytearray()
            parser.buf_index = 0
            parser.expected_length = mavlink2.HEADER_LEN_V1 + 2
            parser.have_prefix_error = False
        return data

    conn.recv = recv


class LiveLink:
    """A live MAVLink link through a pymavlink connection string.

    ``udpin:127.0.0.1:14550``, ``tcp:HOST:PORT``, ``/dev/ttyUSB0,57600``.  Sends a GCS
    heartbeat every second, asks for the streams we need with SET_MESSAGE_INTERVAL and falls
    back to REQUEST_DATA_STREAM when the vehicle does not acknowledge it, and records every
    packet received (raw bytes) through ``recorder`` when given.
    """

    RATE_HZ = 50
    LOST_AFTER_S = 3.0

    def __init__(self, url: str, recorder=None) -> None:
        from pymavlink import mavutil

        self.url = url
        device, baud = (url.split(",", 1) + ["57600"])[:2] if "," in url else (url, "57600")
        try:
            self.mav = mavutil.mavlink_connection(
                device, baud=int(baud), source_system=255, source_component=190,
                robust_parsing=True, autoreconnect=True, dialect="ardupilotmega")
        except Exception as err:
            raise IngestError(f"cannot open link '{url}': {err}") from err
        _drop_partial_packets_between_datagrams(self.mav)
        self.recorder = recorder
        self.decoder = MavlinkDecoder()
        self.t0_unix = time.time()
        self.last_rx_unix: float | None = None
        self.connected = False
        self.bad_packets = 0
        self._last_heartbeat = 0.0
        self._streams_requested_at: float | None = None
        self._interval_acked = False
        self._fallback_sent = False

    def t_s(self, unix_s: float | None = None) -> float:
        return (time.time() if unix_s is None else unix_s) - self.t0_unix

    def poll(self, max_messages: int = 1000) -> list[Sample]:
        """Everything that arrived since the last call (non-blocking), as samples."""
        now = time.time()
        out: list[Sample] = []
        self._housekeeping(now, out)
        for _ in range(max_messages):
            try:
                msg = self.mav.recv_msg()
            except (OSError, ValueError, TypeError, IndexError) as err:
                self.bad_packets += 1
                self.decoder.warnings[f"link read error: {type(err).__name__}"] += 1
                break
            if msg is None:
                break
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                self.bad_packets += 1
                continue
            unix = time.time()
            if self.recorder is not None:
                self.recorder.write_packet(bytes(msg.get_msgbuf()), unix)
            if msg.get_srcSystem() == 255:  # our own or another GCS's traffic
                continue
            self.last_rx_unix = unix
            if not self.connected:
                self.connected = True
                out.append(StatusSample(self.t_s(unix), "link", f"link up on {self.url}"))
            if mtype == "COMMAND_ACK" and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and msg.result == 0:
                self._interval_acked = True
            out.extend(self.decoder.decode(msg, self.t_s(unix)))
        return out

    def _housekeeping(self, now: float, out: list[Sample]) -> None:
        from pymavlink import mavutil

        if now - self._last_heartbeat >= 1.0:
            self._last_heartbeat = now
            try:
                self.mav.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                            mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except OSError:
                pass  # UDP-in before the vehicle has spoken has no peer yet
        if self.connected and self.last_rx_unix is not None and now - self.last_rx_unix > self.LOST_AFTER_S:
            self.connected = False
            self._streams_requested_at = None
            out.append(StatusSample(self.t_s(now), "link",
                                    f"link lost: nothing heard for {self.LOST_AFTER_S:.0f} s, waiting"))
        if self.connected and self.decoder.vehicle_sysid is not None:
            if self._streams_requested_at is None:
                self._request_streams(now)
            elif (not self._interval_acked and not self._fallback_sent
                  and now - self._streams_requested_at > 2.0):
                self._request_data_stream_fallback()

    def _request_streams(self, now: float) -> None:
        self._streams_requested_at = now
        self._interval_acked = False
        self._fallback_sent = False
        sysid = self.decoder.vehicle_sysid
        interval_us = 1e6 / self.RATE_HZ
        for name in STREAMED_MESSAGES:
            msg_id = getattr(mavlink2, "MAVLINK_MSG_ID_" + name)
            try:
                self.mav.mav.command_long_send(sysid, 0, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               msg_id, interval_us, 0, 0, 0, 0, 0)
            except OSError:
                return

    def _request_data_stream_fallback(self) -> None:
        self._fallback_sent = True
        try:
            # MAV_DATA_STREAM_ALL (0) at our rate: the pre-MAVLink-2 way ArduPilot still honours.
            self.mav.mav.request_data_stream_send(self.decoder.vehicle_sysid, 0, 0, self.RATE_HZ, 1)
        except OSError:
            pass

    def close(self) -> None:
        try:
            self.mav.close()
        except Exception:
            pass
        if self.recorder is not None:
            self.recorder.flush()


def validate_connection_string(url: str) -> str:
    """Accept pymavlink connection strings we support: udpin/udp/udpout/tcp/tcpin and serial."""
    url = (url or "").strip()
    prefixes = ("udpin:", "udp:", "udpout:", "tcp:", "tcpin:")
    if url.startswith(prefixes):
        rest = url.split(":", 1)[1]
        host, _, port = rest.rpartition(":")
        if host and port.isdigit() and 0 < int(port) < 65536:
            return url
    elif url.startswith("/dev/") or (url.upper().startswith("COM") and url[3:].split(",")[0].isdigit()):
        dev, _, baud = url.partition(",")
        if not baud or baud.isdigit():
            return url
    raise IngestError(f"'{url}' is not a supported connection string "
                       "(udpin:HOST:PORT, tcp:HOST:PORT, /dev/ttyUSB0,57600)")
