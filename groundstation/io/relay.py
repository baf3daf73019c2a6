"""The forwarding process: owns the vehicle link and the forwarding outputs, passes bytes.

Run as ``python -m groundstation.io.relay`` by ``groundstation.io.forward.Forwarder`` (never by
hand).  It relays MAVLink packets between the vehicle link, the other ground stations (outputs
``udpout:HOST:PORT`` / ``tcpin:HOST:PORT``) and the station, which gets its copy over a loopback
UDP socket and sends its own packets back the same way.  Being its own process, it never waits
for the station's interpreter lock (estimators, viser, uvicorn): how busy the station is no
longer matters, only whether the machine has a core free when a packet comes
(``ask_short_time_slice``; benchmarks/forward_latency.py measures both).

Nothing is decoded: ``MavlinkFramer`` cuts streams into packets by their header (payload length,
signature flag) only.  Packets go on unchanged, signed ones included (a changed byte would break
the signature; checking them is the station's job, with its key, and each ground station's);
the process sends nothing of its own (a passive station stays silent on the wire).

The loopback link to the station is connected at both ends, so no other local process can
inject packets into it or read the station's: the station opens its socket and names its port
(``open``); this process connects a fresh socket to that port (bound and connected in one step)
and answers its own port; the station connects its socket to that, drops anything that reached
it before, and says ``attach``; only then does this process send it the vehicle's packets.

Control: JSON lines on stdin (first the outputs, then ``open`` / ``attach`` / ``forward`` /
``close`` / ``stats`` / ``quit``), answers and statistics as JSON lines on stdout.  The process ends on
``quit``, when stdin closes or when its parent dies (checked every LOOP_TIMEOUT_S).
"""
from __future__ import annotations

import json
import os
import queue
import select
import signal
import socket
import sys
import threading
import time

from .endpoints import open_endpoint, parse_connection_string
from .errors import IngestError
from .forward import MavlinkFramer, parse_forward_url
from .forward_outputs import open_output

__all__ = ["Relay", "main"]

LOOP_TIMEOUT_S = 0.2
STATS_INTERVAL_S = 0.25
POLL_S = 0.002                 # links without a selectable descriptor (serial ports on Windows)
STATION_BUFFER_BYTES = 4 << 20  # ~1 s of a busy link while the station is held up
DATAGRAM_KINDS = ("udpin", "udp", "udpout")
SHORT_SLICE_NS = 100_000        # the shortest slice Linux grants (0.1 ms)
SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "armv7l": 380, "i686": 351}   # syscall numbers


def ask_short_time_slice(slice_ns: int = SHORT_SLICE_NS) -> bool:
    """Ask Linux for a short scheduler time slice for this thread (``sched_setattr(2)``,
    SCHED_OTHER with ``sched_runtime``; no privilege needed).  On kernels with the EEVDF scheduler
    (Linux 6.6+, custom slices since 6.12) a waking thread with a shorter slice may preempt a
    busy one at once instead of waiting for the end of its slice (~1-3 ms), which is what a
    process that sleeps until a packet comes needs on a loaded machine.  Elsewhere (other
    systems, older kernels) nothing changes.  Returns whether the kernel took it."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes
    import platform
    import struct

    number = SCHED_SETATTR.get(platform.machine())
    if number is None:
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        # struct sched_attr (SCHED_ATTR_SIZE_VER0): size, policy, flags, nice, priority, runtime, deadline, period
        attr = ctypes.create_string_buffer(struct.pack("IIQiIQQQ", 48, 0, 0, nice, 0, int(slice_ns), 0, 0))
        return libc.syscall(number, 0, attr, 0) == 0
    except (OSError, AttributeError):
        return False


class VehicleLink:
    """One vehicle link (a pymavlink connection, used only to open the port, read and write bytes)
    and the loopback UDP socket to the station's side of it."""

    def __init__(self, url: str, listen_any: bool, station_port: int) -> None:
        endpoint = parse_connection_string(url, listen_any=listen_any)
        self.datagrams = endpoint.kind in DATAGRAM_KINDS
        self.conn = open_endpoint(endpoint)
        self.station = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.station.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, STATION_BUFFER_BYTES)
            # connect() of an unbound socket binds and connects in one step: from its first moment
            # the socket takes datagrams from the station's port only (no bind-then-connect gap)
            self.station.connect(("127.0.0.1", int(station_port)))
        except OSError:
            self.close()
            raise
        self.station.setblocking(False)
        self.foreign = _drain(self.station)     # none can be the station's: it does not know our port yet
        self.attached = False                  # the station connected its side too (the "attach" command)
        self.framer = MavlinkFramer()
        self.from_vehicle = self.to_station_dropped = self.from_station = self.errors = 0
        self.before_attach = 0

    @property
    def port(self) -> int:
        return self.station.getsockname()[1]

    def vehicle_fd(self):
        return getattr(self.conn, "fd", None)

    def read_vehicle(self) -> list[bytes]:
        """Whole packets now readable from the vehicle (a datagram holds whole packets: a partial
        one at its end is garbage, not the start of the next datagram's)."""
        try:
            data = self.conn.recv(65536)
        except (OSError, ValueError):         # a serial port unplugged, a TCP peer gone: pymavlink retries
            self.errors += 1
            return []
        if not data:
            return []
        framer = MavlinkFramer() if self.datagrams else self.framer
        packets = framer.feed(bytes(data, "latin-1") if isinstance(data, str) else bytes(data))
        if framer is not self.framer:
            self.framer.skipped_bytes += framer.skipped_bytes
        self.from_vehicle += len(packets)
        return packets

    def to_station(self, packet: bytes) -> None:
        if not self.attached:          # the station's socket may still take anyone's datagrams
            self.before_attach += 1
            return
        try:
            self.station.send(packet)
        except OSError:          # the station's buffer is full (held up a long time) or it closed
            self.to_station_dropped += 1

    def to_vehicle(self, packet: bytes) -> bool:
        try:
            self.conn.write(packet)
            return True
        except (OSError, ValueError):
            self.errors += 1
            return False

    def from_station_readable(self) -> None:
        """The station's own packets (heartbeats, requests, signed writes) to the vehicle, as sent."""
        try:
            data = self.station.recv(65535)
        except OSError:
            return
        self.from_station += 1
        self.to_vehicle(data)

    def close(self) -> None:
        self.station.close()
        try:
            self.conn.close()
        except Exception:
            pass

    def snapshot(self) -> dict:
        return {"from_vehicle": self.from_vehicle, "to_station_dropped": self.to_station_dropped,
                "before_attach": self.before_attach, "foreign_dropped": self.foreign,
                "from_station": self.from_station, "skipped_bytes": self.framer.skipped_bytes, "errors": self.errors}


def _drain(sock: socket.socket) -> int:
    """Read and drop every datagram waiting on a non-blocking socket; returns how many."""
    n = 0
    while True:
        try:
            sock.recv(65535)
        except OSError:        # BlockingIOError: empty (ECONNREFUSED and the like: nothing to read)
            return n
        n += 1


class Relay:
    """The forwarding loop: one thread, ``select`` over every socket; commands come from a queue
    (``wake`` is written to when one is queued).

    Args:
        outputs: the forwarding outputs' URLs (checked again here).
        listen_any: allow ``tcpin`` outputs on non-loopback addresses.
        emit: where answers and statistics go (a dict each).
    Raises:
        IngestError: an output that cannot open.
    """

    def __init__(self, outputs, *, listen_any: bool, emit) -> None:
        self.outputs: list = []
        try:
            for url in outputs:
                self.outputs.append(open_output(parse_forward_url(url, listen_any=listen_any)))
        except BaseException:
            self.close()
            raise
        self.emit = emit
        self.links: dict[int, VehicleLink] = {}
        self.forwarding: VehicleLink | None = None
        self.to_vehicle = self.to_vehicle_dropped = 0
        self.commands: queue.Queue = queue.Queue()
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self.running = True
        self._parent = os.getppid()
        self._last_stats: dict | None = None

    def run(self) -> None:
        next_stats = time.monotonic() + STATS_INTERVAL_S
        while self.running:
            owners = {self.wake_r: None}
            for out in self.outputs:
                owners.update((s, out) for s in out.sockets())
            polled = []
            for link in self.links.values():
                fd = link.vehicle_fd()
                owners[link.station] = link
                if fd is None:
                    polled.append(link)
                else:
                    owners[fd] = link
            timeout = POLL_S if polled else LOOP_TIMEOUT_S
            try:
                ready, _, _ = select.select(list(owners), [], [], timeout)
            except (OSError, ValueError):       # a descriptor closed under us (a TCP reconnect): look again
                ready = []
                time.sleep(POLL_S)
            for item in ready:
                self._readable(item, owners[item])
            for link in polled:
                self._from_vehicle(link)
            if time.monotonic() >= next_stats:
                next_stats = time.monotonic() + STATS_INTERVAL_S
                self.send_stats(only_changed=True)
                if os.getppid() != self._parent:    # the station died without telling us
                    self.running = False

    def _readable(self, item, owner) -> None:
        if owner is None:
            self._commands()
        elif isinstance(owner, VehicleLink):
            if item is owner.station:
                owner.from_station_readable()
            else:
                self._from_vehicle(owner)
        else:
            for packet in owner.readable(item):
                self._to_vehicle(packet)

    def _from_vehicle(self, link: VehicleLink) -> None:
        forward = link is self.forwarding
        for packet in link.read_vehicle():
            if forward:                     # the other ground stations first: they are waiting on us
                for out in self.outputs:
                    out.send(packet)
            link.to_station(packet)

    def _to_vehicle(self, packet: bytes) -> None:
        if self.forwarding is None:
            self.to_vehicle_dropped += 1
            return
        if self.forwarding.to_vehicle(packet):
            self.to_vehicle += 1
        else:
            self.to_vehicle_dropped += 1

    def _commands(self) -> None:
        try:
            self.wake_r.recv(4096)
        except OSError:
            pass
        while True:
            try:
                cmd = self.commands.get_nowait()
            except queue.Empty:
                return
            self.command(cmd)

    def command(self, cmd: dict) -> None:
        """One control command (a dict with ``op``); answers through ``emit``."""
        op = cmd.get("op")
        if op == "open":
            self._open(int(cmd["id"]), str(cmd["url"]), bool(cmd.get("listen_any")), int(cmd["station_port"]))
        elif op == "attach":
            link = self.links.get(cmd.get("id"))
            if link is not None:
                link.attached = True
        elif op == "forward":
            self.forwarding = self.links.get(cmd.get("id"))
        elif op == "close":
            link = self.links.pop(int(cmd["id"]), None)
            if link is not None:
                if link is self.forwarding:
                    self.forwarding = None
                link.close()
        elif op == "stats":
            self.send_stats(only_changed=False)
        elif op == "quit":
            self.running = False

    def _open(self, link_id: int, url: str, listen_any: bool, station_port: int) -> None:
        try:
            link = VehicleLink(url, listen_any, station_port)
        except IngestError as err:
            self.emit({"op": "failed", "id": link_id, "error": str(err)})
            return
        except OSError as err:
            self.emit({"op": "failed", "id": link_id, "error": f"cannot open link '{url}': {err.strerror or err}"})
            return
        self.links[link_id] = link
        self.emit({"op": "opened", "id": link_id, "port": link.port})

    def stats(self) -> dict:
        return {"outputs": [o.snapshot() for o in self.outputs], "to_vehicle": self.to_vehicle,
                "to_vehicle_dropped": self.to_vehicle_dropped,
                "links": {str(k): v.snapshot() for k, v in self.links.items()}}

    def send_stats(self, *, only_changed: bool) -> None:
        stats = self.stats()
        if only_changed and stats == self._last_stats:
            return
        self._last_stats = stats
        self.emit({"op": "stats", **stats})

    def close(self) -> None:
        for link in getattr(self, "links", {}).values():
            link.close()
        for out in self.outputs:
            out.close()
        for sock in (getattr(self, "wake_r", None), getattr(self, "wake_w", None)):
            if sock is not None:
                sock.close()


def _read_commands(relay: Relay, stdin) -> None:
    """The control thread: stdin lines into the relay's queue; end of stdin (the station closed
    the pipe or died) is a quit."""
    for line in stdin:
        try:
            cmd = json.loads(line)
        except ValueError:
            continue
        relay.commands.put(cmd)
        relay.wake_w.send(b"!")
    relay.commands.put({"op": "quit"})
    try:
        relay.wake_w.send(b"!")
    except OSError:
        pass


def main() -> int:
    """The forwarding process: its first stdin line names the outputs; answers "ready" or one error."""
    if hasattr(signal, "SIGINT"):           # Ctrl-C in the station's terminal: the station stops us
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    out_lock = threading.Lock()
    protocol, sys.stdout = sys.stdout, sys.stderr     # what a library prints stays out of the answers

    def emit(message: dict) -> None:
        with out_lock:
            protocol.write(json.dumps(message) + "\n")
            protocol.flush()

    try:
        config = json.loads(sys.stdin.readline() or "{}")
        relay = Relay(config.get("outputs", []), listen_any=bool(config.get("listen_any")), emit=emit)
    except (IngestError, OSError, ValueError) as err:
        emit({"op": "error", "error": str(err)})
        return 1
    emit({"op": "ready", "pid": os.getpid(), "short_slice": ask_short_time_slice()})
    threading.Thread(target=_read_commands, args=(relay, sys.stdin), daemon=True, name="relay-control").start()
    try:
        relay.run()
    except Exception as err:                # one line to the station, never a traceback
        text = f"forwarding stopped: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        try:
            emit({"op": "error", "error": text})
        except OSError:
            pass
        print(text, file=sys.stderr)
        return 1
    finally:
        relay.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
