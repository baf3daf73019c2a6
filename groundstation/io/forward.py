"""MAVLink forwarding: the station owns the vehicle link and passes it on to other ground stations.

``Forwarder`` starts the forwarding process (``groundstation.io.relay``), which opens the outputs
(``udpout:HOST:PORT`` sends to a ground station listening there, ``tcpin:127.0.0.1:PORT`` lets
ground stations connect) and, for each live link the station opens through it
(``open_vehicle``), the vehicle link itself.  It sends every packet from the vehicle to all
outputs and its copy to the station (loopback UDP), and passes what the outputs and the station
send to the vehicle.  In its own process the forwarding never waits for the station's
interpreter lock.  Packets are passed as received, bytes unchanged (signed packets stay signed,
unknown message ids pass): ``MavlinkFramer`` only cuts a byte stream into whole packets by their
header (length, signature flag), it does not check CRCs or decode.
"""
from __future__ import annotations

import atexit
import itertools
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from .errors import IngestError
from .endpoints import Endpoint, open_endpoint, parse_connection_string

__all__ = ["Forwarder", "MavlinkFramer", "parse_forward_url", "FORWARD_KINDS"]

FORWARD_KINDS = ("udpout", "tcpin")
START_TIMEOUT_S = 20.0          # a cold interpreter importing pymavlink on a loaded machine
OPEN_TIMEOUT_S = 20.0           # a tcp: link retries a few times
STOP_TIMEOUT_S = 3.0
STX_V1, STX_V2 = 0xFE, 0xFD
SIGNATURE_LEN = 13


def parse_forward_url(url: str, *, listen_any: bool = False) -> Endpoint:
    """Check a forwarding output: ``udpout:HOST:PORT`` or ``tcpin:HOST:PORT`` (loopback unless
    ``listen_any``), with the same checks as the vehicle link (``parse_connection_string``).

    Raises:
        IngestError: one line saying why the string is refused.
    """
    endpoint = parse_connection_string(url, listen_any=listen_any)
    if endpoint.kind not in FORWARD_KINDS:
        raise IngestError(f"{endpoint.text} cannot be a forwarding output: use udpout:HOST:PORT (send to a ground "
                          "station listening there) or tcpin:127.0.0.1:PORT (ground stations connect to it)")
    return endpoint


class MavlinkFramer:
    """Cuts a MAVLink 1/2 byte stream into whole packets (header-length framing, no CRC check);
    bytes before a start marker are skipped and counted."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        buf = self._buf
        while buf:
            if buf[0] not in (STX_V1, STX_V2):
                nxt = min((i for i in (buf.find(STX_V1), buf.find(STX_V2)) if i > 0), default=len(buf))
                self.skipped_bytes += nxt
                del buf[:nxt]
                continue
            if len(buf) < 3:
                break
            if buf[0] == STX_V2:
                size = 10 + buf[1] + 2 + (SIGNATURE_LEN if buf[2] & 0x01 else 0)
            else:
                size = 6 + buf[1] + 2
            if len(buf) < size:
                break
            out.append(bytes(buf[:size]))
            del buf[:size]
        return out




def _drop_waiting(sock) -> int:
    """Read and drop every datagram waiting on a socket (without blocking); returns how many."""
    blocking = sock.getblocking()
    sock.setblocking(False)
    n = 0
    try:
        while True:
            sock.recv(65535)
            n += 1
    except OSError:
        return n
    finally:
        sock.setblocking(blocking)


def _child_env() -> dict:
    """The station's environment, with this copy of ``groundstation`` first on the path and
    without the signing passphrase's variable (the forwarding process never holds the key)."""
    from .signing import passphrase_variables

    fold = str.upper if os.name == "nt" else str          # Windows names ignore case
    secret = {fold(name) for name in passphrase_variables()}
    env = {k: v for k, v in os.environ.items() if fold(k) not in secret}
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


class Forwarder:
    """The forwarding process, seen from the station.

    ``start`` runs it (``python -m groundstation.io.relay``) and opens the outputs; ``open_vehicle``
    opens a vehicle link in it and returns the station's side (a pymavlink connection over
    loopback UDP, used as the link itself would be); ``forward`` chooses the link passed to the
    outputs; ``close`` stops the process (it also ends by itself when the station dies).

    Args:
        urls: forwarding outputs (checked here with ``parse_forward_url``).
        listen_any: allow ``tcpin`` on non-loopback addresses (the operator's remote mode).
    Raises:
        IngestError: a refused string (constructor); an output that cannot open, or a process
            that does not start (``start``); all one line.
    """

    def __init__(self, urls, *, listen_any: bool = False) -> None:
        self.urls = tuple(parse_forward_url(u, listen_any=listen_any).text for u in urls)
        self.listen_any = listen_any
        self.proc: subprocess.Popen | None = None
        self.pid: int | None = None
        self.short_slice = False         # Linux granted the process a short time slice (io.relay)
        self.error: str | None = None
        self._stats: dict = {}
        self._stats_seen = 0
        self._replies: dict[int, dict] = {}
        self._ready = self._exited = self._closing = False
        self._cond = threading.Condition()
        self._write_lock = threading.Lock()
        self._ids = itertools.count(1)
        self._reader: threading.Thread | None = None

    def __enter__(self) -> "Forwarder":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ process
    def start(self, timeout_s: float = START_TIMEOUT_S) -> "Forwarder":
        """Run the forwarding process and open its outputs (returns when they are open)."""
        if self.proc is not None:
            return self
        try:
            self.proc = subprocess.Popen([sys.executable, "-m", "groundstation.io.relay"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True, bufsize=1, env=_child_env())
        except OSError as err:
            raise IngestError(f"cannot start the forwarding process: {err.strerror or err}") from err
        self._reader = threading.Thread(target=self._read_loop, daemon=True, name="forwarder-reader")
        self._reader.start()
        self._send({"outputs": list(self.urls), "listen_any": self.listen_any})
        with self._cond:
            self._cond.wait_for(lambda: self._ready or self._exited, timeout_s)
            error = None if self._ready else (self.error or "the forwarding process did not start "
                                              f"within {timeout_s:.0f} s")
        if error is not None:
            self.close()
            raise IngestError(error)
        atexit.register(self.close)
        return self

    def _read_loop(self) -> None:
        for line in self.proc.stdout:          # read all of it always: a full pipe would stop the process
            try:
                self._received(json.loads(line))
            except (ValueError, KeyError, TypeError, AttributeError):
                continue
        code = self.proc.wait()
        with self._cond:
            self._exited = True
            if self.error is None and not self._closing:
                self.error = f"the forwarding process stopped (exit code {code})"
            self._cond.notify_all()

    def _received(self, msg: dict) -> None:
        with self._cond:
            op = msg.get("op")
            if op == "stats":
                self._stats, self._stats_seen = msg, self._stats_seen + 1
            elif op in ("opened", "failed"):
                self._replies[int(msg["id"])] = msg
            elif op == "ready":
                self._ready, self.pid = True, int(msg["pid"])
                self.short_slice = bool(msg.get("short_slice"))
            elif op == "error":
                self.error = str(msg.get("error"))
            self._cond.notify_all()

    def _send(self, cmd: dict) -> bool:
        proc = self.proc
        if proc is None or self._exited:
            return False
        try:
            with self._write_lock:
                proc.stdin.write(json.dumps(cmd) + "\n")
                proc.stdin.flush()
            return True
        except (OSError, ValueError):       # the process is gone (its reader says why)
            return False

    @property
    def running(self) -> bool:
        return self.proc is not None and self._ready and not self._exited

    def close(self) -> None:
        """Stop the process (outputs and vehicle links close with it); waits STOP_TIMEOUT_S, then kills."""
        proc = self.proc
        if proc is None:
            return
        atexit.unregister(self.close)
        self._closing = True
        self._send({"op": "quit"})
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(STOP_TIMEOUT_S)
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(STOP_TIMEOUT_S)
        proc.stdout.close()

    # ------------------------------------------------------------------ vehicle links
    def open_vehicle(self, url: str, *, listen_any: bool = True, timeout_s: float = OPEN_TIMEOUT_S):
        """Open a vehicle link in the forwarding process.

        Returns:
            (link id, the station's side: a pymavlink connection whose reads are the vehicle's
            packets and whose writes go to the vehicle).
        Raises:
            IngestError: the link cannot open (one line), or the process is not running.
        """
        if not self.running:
            raise IngestError(self.error or "the forwarding process is not running")
        conn = open_endpoint(Endpoint("udpin", "udpin:127.0.0.1:0", host="127.0.0.1", port=0))
        link_id = next(self._ids)
        self._send({"op": "open", "id": link_id, "url": url, "listen_any": listen_any,
                    "station_port": conn.port.getsockname()[1]})
        with self._cond:
            self._cond.wait_for(lambda: link_id in self._replies or self._exited, timeout_s)
            reply = self._replies.pop(link_id, None)
        if reply is None or reply["op"] != "opened":
            conn.close()
            self.close_vehicle(link_id)
            raise IngestError(reply["error"] if reply else self.error or f"cannot open link '{url}': "
                              "the forwarding process did not answer")
        relay_address = ("127.0.0.1", int(reply["port"]))
        try:        # from now on only the process's socket reaches ours (io.relay: both ends connected)
            conn.port.connect(relay_address)
        except OSError as err:
            conn.close()
            self.close_vehicle(link_id)
            raise IngestError(f"cannot open link '{url}': loopback to the forwarding process: "
                              f"{err.strerror or err}") from err
        _drop_waiting(conn.port)        # what came before the connect is another process's
        conn.last_address = relay_address          # writes go to the process from the start
        if isinstance(getattr(conn, "clients", None), set):        # pymavlink >= 2.4.4x: its peers
            conn.clients.add(relay_address)
            conn.clients_last_alive[relay_address] = time.time()
        self._send({"op": "attach", "id": link_id})
        return link_id, conn

    def forward(self, link_id: int | None) -> None:
        """Pass this link's packets to the outputs and theirs to it (None: no link)."""
        self._send({"op": "forward", "id": link_id})

    def close_vehicle(self, link_id: int) -> None:
        self._send({"op": "close", "id": link_id})

    # ------------------------------------------------------------------ counts
    def refresh(self, timeout_s: float = 2.0) -> bool:
        """Ask for fresh counts and wait for them (they also come by themselves 4 times a second)."""
        with self._cond:
            seen = self._stats_seen
        if not self._send({"op": "stats"}):
            return False
        with self._cond:
            return self._cond.wait_for(lambda: self._stats_seen > seen or self._exited, timeout_s) and not self._exited

    def snapshot(self) -> dict:
        """Outputs (url, clients, to_gcs, from_gcs, dropped), packets passed to the vehicle, the process."""
        with self._cond:
            stats = dict(self._stats)
        outputs = stats.get("outputs") or [{"url": u, "clients": 0, "to_gcs": 0, "from_gcs": 0, "dropped": 0}
                                           for u in self.urls]
        return {"outputs": outputs, "to_vehicle": stats.get("to_vehicle", 0),
                "to_vehicle_dropped": stats.get("to_vehicle_dropped", 0), "links": stats.get("links", {}),
                "process": {"pid": self.pid, "running": self.running, "error": self.error,
                            "short_slice": self.short_slice}}
