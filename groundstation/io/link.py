"""Live MAVLink links (UDP/TCP/serial through pymavlink) as a typed sample stream."""
from __future__ import annotations

import errno
import ipaddress
import os
import re
import stat
import time
from dataclasses import dataclass

from .decode import MAV_CMD_SET_MESSAGE_INTERVAL, MavlinkDecoder
from .errors import IngestError
from .mavlink import mavlink2
from ..samples import Sample, StatusSample

__all__ = ["LiveLink", "STREAMED_MESSAGES", "Endpoint", "parse_connection_string", "validate_connection_string",
           "open_endpoint"]

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

    ``udpin:127.0.0.1:14550``, ``tcp:HOST:PORT``, ``/dev/ttyUSB0,57600`` (checked by
    ``parse_connection_string``; refused strings raise IngestError).  Sends a GCS
    heartbeat every second, asks for the streams we need with SET_MESSAGE_INTERVAL and falls
    back to REQUEST_DATA_STREAM when the vehicle does not acknowledge it, and records every
    packet received (raw bytes) through ``recorder`` when given.
    """

    RATE_HZ = 50
    LOST_AFTER_S = 3.0

    def __init__(self, url: str, recorder=None, *, listen_any: bool = True) -> None:
        endpoint = parse_connection_string(url, listen_any=listen_any)
        self.url = endpoint.text
        self.mav = open_endpoint(endpoint)
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


# ------------------------------------------------------------------------------ connection strings

NETWORK_KINDS = ("udpin", "udp", "udpout", "tcp", "tcpin")
LISTENING_KINDS = ("udpin", "udp", "tcpin")        # pymavlink binds these ("udp:" listens too)
DEFAULT_BAUD = 57600
_HOST_RE = re.compile(r"^[A-Za-z0-9](?:[A-Za-z0-9.-]{0,252})$")
_COM_RE = re.compile(r"^COM[1-9][0-9]{0,2}$", re.IGNORECASE)
_USAGE = "use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial port /dev/ttyUSB0,57600"
_NOT_SERIAL = ("/dev/tty", "/dev/console", "/dev/ptmx")   # the controlling terminal, not a port


@dataclass(frozen=True)
class Endpoint:
    """A checked live-link endpoint: ``kind`` is one of NETWORK_KINDS or "serial".

    host / port:  network endpoints (host a name or an IPv4 address, port 1..65535).
    device / baud: serial ports (device the resolved node under /dev, or COMn on Windows).
    """
    kind: str
    text: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = DEFAULT_BAUD

    @property
    def listens(self) -> bool:
        return self.kind in LISTENING_KINDS


def _is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _refuse(text: str, why: str) -> IngestError:
    shown = text if len(text) <= 80 else text[:77] + "..."
    return IngestError(f"{shown.encode('unicode_escape').decode('ascii')!s} is not a connection string we "
                       f"open: {why} ({_USAGE})")


def _network_endpoint(text: str, kind: str, rest: str, listen_any: bool) -> Endpoint:
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise _refuse(text, f"{kind} needs HOST:PORT with a port 1..65535")
    if not _HOST_RE.match(host):
        raise _refuse(text, "the host must be a name or an IPv4 address")
    if kind in LISTENING_KINDS and not listen_any and not _is_loopback(host):
        raise _refuse(text, f"a request may only listen on loopback (127.0.0.1); {host} listens on "
                            "other interfaces (start the station with --connect, or with --allow-remote)")
    return Endpoint(kind, text, host=host, port=int(port))


def _serial_endpoint(text: str) -> Endpoint:
    device, sep, baud = text.partition(",")
    if sep and not (baud.isdigit() and 50 <= int(baud) <= 20_000_000):
        raise _refuse(text, "the baud rate after ',' must be a number")
    baud_rate = int(baud) if sep else DEFAULT_BAUD
    if os.name == "nt" and _COM_RE.match(device):
        return Endpoint("serial", text, device=device.upper(), baud=baud_rate)
    if not device.startswith("/dev/"):
        raise _refuse(text, "serial ports are device nodes under /dev (or COMn on Windows)")
    resolved = os.path.realpath(device)
    if not resolved.startswith("/dev/"):
        raise _refuse(text, f"it resolves to {resolved}, outside /dev")
    try:
        mode = os.stat(resolved).st_mode
    except OSError:
        raise _refuse(text, f"no such device {device} (is the radio or autopilot plugged in?)") from None
    if not stat.S_ISCHR(mode):
        raise _refuse(text, f"{resolved} is not a character device")
    if resolved in _NOT_SERIAL or re.fullmatch(r"/dev/tty[0-9]+", resolved) or resolved in _own_terminals():
        raise _refuse(text, f"{resolved} is a console or this program's own terminal, not a serial port")
    return Endpoint("serial", text, device=resolved, baud=baud_rate)


def _own_terminals() -> set[str]:
    names = set()
    for fd in (0, 1, 2):
        try:
            names.add(os.path.realpath(os.ttyname(fd)))
        except OSError:
            pass
    return names


def parse_connection_string(url: str, *, listen_any: bool = True) -> Endpoint:
    """Check a live-link connection string and say exactly what it opens.

    Accepted: ``udpin|udp|tcpin:HOST:PORT`` (listen), ``udpout|tcp:HOST:PORT`` (connect), and
    serial ports: a character device under /dev (symlinks such as /dev/serial/by-id/... are
    resolved first) or ``COMn`` on Windows, with an optional ``,BAUD``.  Anything else, above all
    files, folders and programs (pymavlink replays unknown strings as log files and runs paths
    containing /bin/ or ending in .elf), is refused.

    Args:
        url: the connection string.
        listen_any: allow listeners (udpin/udp/tcpin) on non-loopback addresses such as 0.0.0.0;
            the operator on the command line may, a request over HTTP may not (unless remote).
    Returns:
        the Endpoint to open with ``open_endpoint``.
    Raises:
        IngestError: with a one-line message saying why.
    """
    text = (url or "").strip() if isinstance(url, str) else ""
    if not text:
        raise _refuse(str(url or ""), "it is empty")
    if len(text) > 512 or any(ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0 for c in text):
        raise _refuse(text, "it is too long or holds control characters")
    kind, sep, rest = text.partition(":")
    if sep and kind in NETWORK_KINDS:
        return _network_endpoint(text, kind, rest, listen_any)
    if sep and not (os.name == "nt" and _COM_RE.match(text.split(",")[0])):
        raise _refuse(text, f"'{kind}:' is not a link type we open")
    return _serial_endpoint(text)


def validate_connection_string(url: str, *, listen_any: bool = True) -> str:
    """The checked connection string (stripped); see ``parse_connection_string``.

    Raises:
        IngestError: with a one-line message when the string is refused.
    """
    return parse_connection_string(url, listen_any=listen_any).text


def open_endpoint(endpoint: Endpoint):
    """Open a checked endpoint with the matching pymavlink class directly (never through
    ``mavlink_connection``, whose fall-through branches replay files and run programs).

    Raises:
        IngestError: one line, e.g. a busy or missing serial port, pyserial missing, a port in use.
    """
    from pymavlink import mavutil

    mavutil.set_dialect("ardupilotmega")
    ids = {"source_system": 255, "source_component": 190}
    address = f"{endpoint.host}:{endpoint.port}"
    try:
        if endpoint.kind == "serial":
            return _open_serial(mavutil, endpoint, ids)
        if endpoint.kind in ("udpin", "udp"):
            return mavutil.mavudp(address, input=True, **ids)
        if endpoint.kind == "udpout":
            return mavutil.mavudp(address, input=False, **ids)
        if endpoint.kind == "tcp":
            return mavutil.mavtcp(address, autoreconnect=True, retries=3, **ids)
        if endpoint.kind == "tcpin":
            return mavutil.mavtcpin(address, **ids)
    except IngestError:
        raise
    except OSError as err:
        why = os.strerror(err.errno) if err.errno else str(err)
        raise IngestError(f"cannot open link '{endpoint.text}': {why}") from err
    except Exception as err:
        raise IngestError(f"cannot open link '{endpoint.text}': {type(err).__name__}: "
                          f"{str(err).splitlines()[0] if str(err) else ''}") from err
    raise IngestError(f"cannot open link '{endpoint.text}': unknown kind {endpoint.kind}")


def _open_serial(mavutil, endpoint: Endpoint, ids: dict):
    try:
        import serial
    except ImportError:
        raise IngestError("serial links need pyserial (pip install pyserial)") from None
    try:
        return mavutil.mavserial(endpoint.device, baud=endpoint.baud, autoreconnect=True, **ids)
    except (serial.SerialException, OSError) as err:
        code = getattr(err, "errno", None)
        if code is None and err.args and isinstance(err.args[0], int):
            code = err.args[0]
        why = {errno.EBUSY: "busy (another program has it open: close it, e.g. a second ground station)",
               errno.EACCES: "permission denied (add your user to the dialout group)",
               errno.ENOENT: "no such device (unplugged?)",
               errno.ENOTTY: "not a serial port", errno.EINVAL: "not a serial port"}.get(code)
        if why is None:
            text = str(err).splitlines()[0] if str(err) else type(err).__name__
            why = "busy" + f" ({text})" if "busy" in text.lower() else text
        raise IngestError(f"cannot open serial port {endpoint.device}: {why}") from err
