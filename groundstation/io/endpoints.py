"""Live-link connection strings: checked before anything is opened, then opened directly.

``parse_connection_string`` refuses files, folders and programs (pymavlink's
``mavlink_connection`` would replay or run them); ``open_endpoint`` opens a checked endpoint
with the matching pymavlink class.
"""
from __future__ import annotations

import errno
import ipaddress
import os
import re
import stat
import sys
from dataclasses import dataclass

from .errors import IngestError

__all__ = ["Endpoint", "parse_connection_string", "validate_connection_string", "open_endpoint",
           "NETWORK_KINDS", "LISTENING_KINDS"]


# ------------------------------------------------------------------------------ connection strings

NETWORK_KINDS = ("udpin", "udp", "udpout", "tcp", "tcpin")
LISTENING_KINDS = ("udpin", "udp", "tcpin")        # pymavlink binds these ("udp:" listens too)
DEFAULT_BAUD = 57600
_HOST_RE = re.compile(r"^[A-Za-z0-9](?:[A-Za-z0-9.-]{0,252})$")
_COM_RE = re.compile(r"^COM[1-9][0-9]{0,2}$", re.IGNORECASE)
_USAGE = "use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial port /dev/ttyUSB0,57600"
_NOT_SERIAL = ("/dev/tty", "/dev/console", "/dev/ptmx", "/dev/pts/ptmx")   # terminals, not ports
_NOT_SERIAL_NUMBERS = ((5, 0), (5, 1), (5, 2))    # Linux (major, minor) of /dev/tty, console, ptmx wherever mounted


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


def _ascii_number(text: str) -> bool:
    """Only the digits 0-9 (``str.isdigit`` also takes '²', Arabic-Indic and full-width digits,
    which ``int`` then reads as another number than the page shows, or not at all)."""
    return text.isascii() and text.isdigit()


def _network_endpoint(text: str, kind: str, rest: str, listen_any: bool) -> Endpoint:
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not _ascii_number(port) or len(port) > 5 or not 0 < int(port) < 65536:
        raise _refuse(text, f"{kind} needs HOST:PORT with a port 1..65535 (digits 0-9)")
    if not _HOST_RE.match(host):
        raise _refuse(text, "the host must be a name or an IPv4 address")
    if kind in LISTENING_KINDS and not listen_any and not _is_loopback(host):
        raise _refuse(text, f"a request may only listen on loopback (127.0.0.1); {host} listens on "
                            "other interfaces (start the station with --connect, or with --allow-remote)")
    return Endpoint(kind, text, host=host, port=int(port))


def _serial_endpoint(text: str) -> Endpoint:
    device, sep, baud = text.partition(",")
    if sep and not (_ascii_number(baud) and len(baud) <= 8 and 50 <= int(baud) <= 20_000_000):
        raise _refuse(text, "the baud rate after ',' must be a number 50..20000000 (digits 0-9)")
    baud_rate = int(baud) if sep else DEFAULT_BAUD
    if os.name == "nt" and _COM_RE.match(device):
        return Endpoint("serial", text, device=device.upper(), baud=baud_rate)
    if not device.startswith("/dev/"):
        raise _refuse(text, "serial ports are device nodes under /dev (or COMn on Windows)")
    resolved = os.path.realpath(device)
    if not resolved.startswith("/dev/"):
        raise _refuse(text, f"it resolves to {resolved}, outside /dev")
    try:
        info = os.stat(resolved)
    except OSError:
        raise _refuse(text, f"no such device {device} (is the radio or autopilot plugged in?)") from None
    if not stat.S_ISCHR(info.st_mode):
        raise _refuse(text, f"{resolved} is not a character device")
    number = (os.major(info.st_rdev), os.minor(info.st_rdev)) if sys.platform.startswith("linux") else None
    if resolved in _NOT_SERIAL or number in _NOT_SERIAL_NUMBERS or re.fullmatch(r"/dev/tty[0-9]+", resolved) \
            or resolved in _own_terminals():
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

    # MAVLink 2 from the start: pymavlink would switch at the first MAVLink 2 packet by replacing
    # the connection's parser, which drops its signing set-up (and it sets the same variable then)
    os.environ["MAVLINK20"] = "1"
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
