"""The forwarding process (groundstation.io.relay) over real loopback sockets: it starts and stops
with the station and never outlives it, reports errors in one line, stays silent in passive mode,
passes signed packets unchanged while the station signs its own, and keeps its latency when the
station's process is busy."""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import free_tcp_port, free_udp_port, rotation_dance_messages, wait_until
from groundstation.io.errors import IngestError
from groundstation.io.forward import Forwarder, MavlinkFramer
from groundstation.io.link import LinkOptions
from groundstation.io.roster import is_signed_packet
from groundstation.io.signing import key_from_passphrase
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.station.hub.session import Session

ROOT = Path(__file__).resolve().parent.parent


def gone(pid: int) -> bool:
    """The process has exited (a zombie waiting for its parent to reap it counts as exited)."""
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except OSError:
        return True


class UdpSink:
    """A ground station listening on UDP that only counts (it sends nothing)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]

    def packets(self, wait_s: float = 0.3) -> list[bytes]:
        out, framer, deadline = [], MavlinkFramer(), time.monotonic() + wait_s
        while time.monotonic() < deadline:
            try:
                out += framer.feed(self.sock.recv(65535))
            except socket.timeout:
                pass
        return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_process_stops_with_the_station_and_never_outlives_it():
    tcp_port = free_tcp_port()
    fw = Forwarder([f"tcpin:127.0.0.1:{tcp_port}"]).start()
    pid = fw.pid
    assert fw.running and not gone(pid) and fw.snapshot()["process"]["pid"] == pid
    with pytest.raises(IngestError, match=r"^cannot open forwarding output tcpin:127\.0\.0\.1:\d+: .*in use") as err:
        Forwarder([f"tcpin:127.0.0.1:{tcp_port}"]).start()          # the port is the first one's
    assert "\n" not in str(err.value)
    fw.close()
    assert fw.proc.returncode == 0 and gone(pid) and not fw.running
    with socket.socket() as s:                                       # its port is free again
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", tcp_port))

    # a station killed outright (no close): the forwarding process notices and ends by itself
    station = subprocess.Popen([sys.executable, "-c", "import sys, time\n"
                                "from groundstation.io.forward import Forwarder\n"
                                f"fw = Forwarder(['udpout:127.0.0.1:{free_udp_port()}']).start()\n"
                                "print(fw.pid, flush=True)\ntime.sleep(60)"],
                               cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        child = int(station.stdout.readline())
        assert not gone(child)
        os.kill(station.pid, signal.SIGKILL)
        station.wait(5)
        assert wait_until(lambda: gone(child), 5.0, 0.05), f"forwarding process {child} outlived its station"
    finally:
        station.kill()
        station.wait(5)


def test_a_forwarding_process_that_dies_is_reported_in_one_line():
    from groundstation.io.link import LiveLink
    from groundstation.io.mavlink import mavlink2 as m, new_encoder
    from groundstation.samples import StatusSample

    fw = Forwarder([f"udpout:127.0.0.1:{free_udp_port()}"]).start()
    port = free_udp_port()
    link = LiveLink(f"udpin:127.0.0.1:{port}", options=LinkOptions(passive=True), forwarder=fw)
    got: list = []
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as vehicle:
            heartbeat = bytes(m.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(new_encoder(1, 1)))

            def heard() -> bool:     # the vehicle beats until heard: the process drops what comes before "attach"
                vehicle.sendto(heartbeat, ("127.0.0.1", port))
                got.extend(link.poll())
                return link.connected
            assert wait_until(heard, 10.0, 0.05)
        os.kill(fw.pid, signal.SIGKILL)
        assert wait_until(lambda: got.extend(link.poll()) or not link.connected, 5.0, 0.02)
        lost = [s.text for s in got if isinstance(s, StatusSample) and s.kind == "link"][-1]
        assert lost == "link lost: the forwarding process stopped (exit code -9)", got
        assert wait_until(lambda: not fw.running, 5.0, 0.05)
        process = fw.snapshot()["process"]
        assert process["running"] is False and process["error"] == "the forwarding process stopped (exit code -9)"
        with pytest.raises(IngestError, match=r"^the forwarding process stopped \(exit code -9\)$"):
            fw.open_vehicle(f"udpin:127.0.0.1:{free_udp_port()}")
    finally:
        link.close()
        fw.close()


def test_a_link_that_cannot_open_is_one_line_and_the_process_keeps_running(tmp_path):
    with Forwarder([f"udpout:127.0.0.1:{free_udp_port()}"]) as fw:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
            busy.bind(("127.0.0.1", 0))
            port = busy.getsockname()[1]
            with pytest.raises(IngestError, match=rf"^cannot open link 'udpin:127\.0\.0\.1:{port}': .*in use$"):
                fw.open_vehicle(f"udpin:127.0.0.1:{port}")
        link_id, conn = fw.open_vehicle(f"udpin:127.0.0.1:{port}")    # free now: it opens
        conn.close()
        fw.close_vehicle(link_id)
        assert fw.running and fw.error is None


def test_passive_through_the_forwarding_process_sends_nothing_to_the_vehicle(tmp_path):
    sink = UdpSink()
    port = free_udp_port()
    with Forwarder([f"udpout:127.0.0.1:{sink.port}"]) as fw:
        hub = Session(tmp_path, link_options=LinkOptions(passive=True), forwarder=fw)
        hub.connect(f"udpin:127.0.0.1:{port}")
        fv = FakeVehicle(rotation_dance_messages(turn_s=1.0, tumble_s=3.0), port, speed=1.0).start()
        try:
            assert wait_until(lambda: hub.snapshot()["source"]["link"] == "up", 10, 0.02)
            time.sleep(2.5)                  # more than two heartbeat periods of an active station
            forwarded = sink.packets()
            assert fw.refresh()
            snap = hub.snapshot()
        finally:
            fv.stop()
            hub.close()
        sink.sock.close()
    assert len(forwarded) > 100 and snap["rx_count"] > 100 and snap["vehicles"]["passive"]
    assert fv.rx_datagrams == 0                                   # nothing reached the vehicle
    assert snap["vehicles"]["forwarding"]["links"]["1"]["from_station"] == 0


def test_signed_write_through_the_forwarding_process_and_signed_packets_pass_unchanged(tmp_path):
    key = key_from_passphrase("field crew key")
    sink = UdpSink()
    port = free_udp_port()
    with Forwarder([f"udpout:127.0.0.1:{sink.port}"]) as fw:
        hub = Session(tmp_path, link_options=LinkOptions(signing_key=key), forwarder=fw)
        hub.connect(f"udpin:127.0.0.1:{port}")
        fv = FakeVehicle(rotation_dance_messages(turn_s=2.0, tumble_s=8.0), port, autopilot="px4",
                         params={"CAL_MAG0_XOFF": 0.0}, signing_key=key, require_signing=True).start()
        try:
            assert wait_until(lambda: hub.snapshot()["source"]["link"] == "up", 10, 0.02)
            # PX4 offsets are in gauss: 0.125 G (a value beyond +-3 G is refused as impossible)
            confirmed, failed, _ = hub.vehicle.write_params(hub.sources.link, {"CAL_MAG0_XOFF": 0.125},
                                                            progress=lambda c: None, tries=2, timeout_s=1.0)
            forwarded = sink.packets()
            signing = hub.snapshot()["vehicles"]["signing"]
        finally:
            fv.stop()
            hub.close()
        sink.sock.close()
    assert confirmed == ["CAL_MAG0_XOFF"] and failed == [] and fv.params["CAL_MAG0_XOFF"] == 0.125
    assert fv.refused_unsigned == 0 and signing["good"] > 10 and signing["unsigned"] == 0, signing
    assert forwarded and all(is_signed_packet(p) for p in forwarded)     # the vehicle's signatures kept


# The station's own copy this late (median) proves its process was busy: an idle station's copy is
# under 1 ms late. 20 ms was not reached in three runs in a clean-clone suite (15.3 ms; the forwarder's p99
# was 0.25 ms beside it).
BUSY_STATION_MS = 10.0


@pytest.mark.serial     # added forwarding latency in ms against the busy station's
def test_forward_latency_benchmark_quick_with_the_station_busy():
    """benchmarks/forward_latency.py --quick, station process "hog" (estimating the stream, replaying
    a log and holding the interpreter lock in ~40 ms calls): every packet both ways, and the
    forwarding is not held up by the station.  An in-process forwarder waits for the lock as the
    station's own copy does (its median here: 0.2-4 s, the station falls behind), so it fails both
    bounds: median < 5 ms, and p99 below half the station copy's median.  The p99 is not held to
    the 5 ms target here: on a 2-core machine at load 7-9 any forwarder's p99 reached tens of ms
    (MAVProxy's too); the benchmark reports it against the target."""
    for _ in range(3):   # the claim needs a busy station: a run where the hog lost the race for the lock is run again
        out = subprocess.run([sys.executable, "benchmarks/forward_latency.py", "--quick", "--modes", "hog"], cwd=ROOT,
                             capture_output=True, text=True, timeout=180)
        assert out.returncode == 0, out.stderr[-2000:]
        assert re.search(r"^  met     every packet both ways, in order", out.stdout, re.M), out.stdout
        row = re.search(r"^  MagStation \(hog\) .*\|\s+(-?[\d.]+)\s+(-?[\d.]+)\s+[\d.]+ \|\s+(-?[\d.]+|-)\s+(-?[\d.]+|-)\s+\S+ \|",
                        out.stdout, re.M)
        assert row, out.stdout
        # "-": the busy station had not even opened its recording within the run (seen at load 2 in
        # the full suite): its copy is later than any packet forwarded
        fwd_p50, fwd_p99, station_p50, _ = (float("inf") if v == "-" else float(v) for v in row.groups())
        if station_p50 > BUSY_STATION_MS:
            break
    assert station_p50 > BUSY_STATION_MS, out.stdout    # the station's process really was busy
    assert fwd_p50 < 5.0 and fwd_p99 < station_p50 / 2, out.stdout


def _foreign_packets(text: str) -> list[bytes]:
    """What another local process would send the station: a HEARTBEAT and a STATUSTEXT of its own."""
    from groundstation.io.mavlink import mavlink2 as m
    mav = m.MAVLink(None, srcSystem=77, srcComponent=1)
    return [m.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav),
            m.MAVLink_statustext_message(2, text.encode()).pack(mav)]


def test_another_local_process_can_neither_inject_into_nor_read_the_station_link(tmp_path):
    """The loopback socket between the forwarding process and the station is connected at both
    ends: datagrams from any other port are dropped, and the station's packets (heartbeats,
    parameter writes) go to the forwarding process only."""
    port = free_udp_port()
    with Forwarder([f"udpout:127.0.0.1:{free_udp_port()}"]) as fw:
        hub = Session(tmp_path, forwarder=fw)                  # active: heartbeats every second
        hub.connect(f"udpin:127.0.0.1:{port}")
        fv = FakeVehicle(rotation_dance_messages(turn_s=1.0, tumble_s=4.0), port, speed=1.0).start()
        intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        intruder.bind(("127.0.0.1", 0))
        intruder.settimeout(0.1)
        try:
            assert wait_until(lambda: hub.snapshot()["source"]["link"] == "up", 10, 0.02)
            station_port = hub.sources.link.mav.port.getsockname()[1]
            ports = [station_port, *{a[1] for a in hub.sources.link.mav.clients}]   # and the process's side
            for _ in range(5):
                for packet in _foreign_packets("INJECTED by another process"):
                    for p in ports:
                        intruder.sendto(packet, ("127.0.0.1", p))
                time.sleep(0.1)
            heard, deadline = [], time.monotonic() + 2.5        # > 2 heartbeat periods of the station
            while time.monotonic() < deadline:
                try:
                    heard.append(intruder.recv(65535))
                except socket.timeout:
                    pass
            systems = {s["sysid"] for s in hub.snapshot()["vehicles"]["systems"]}
        finally:
            intruder.close()
            fv.stop()
            hub.close()
    assert heard == [], f"the intruder received {len(heard)} datagrams of the station's"
    assert 77 not in systems and 1 in systems, systems
    assert fv.rx_datagrams > 0                    # the station's own heartbeats reach the vehicle


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_signing_passphrase_never_reaches_the_forwarding_process(tmp_path, monkeypatch):
    """``--signing-passphrase-env MS_PASS``: the station reads the key; the forwarding process it
    starts gets an environment without MS_PASS (README: it never holds the key)."""
    from groundstation.cli import _signing_key, build_parser

    monkeypatch.setenv("MS_PASS", "the field crew's words")
    monkeypatch.setenv("MS_OTHER", "kept")
    args = build_parser().parse_args(["serve", "--signing-passphrase-env", "MS_PASS"])
    assert _signing_key(args) == key_from_passphrase("the field crew's words")
    with Forwarder([f"udpout:127.0.0.1:{free_udp_port()}"]) as fw:
        environ = open(f"/proc/{fw.pid}/environ", "rb").read().split(b"\0")
    assert b"MS_OTHER=kept" in environ                       # the environment is read, and passed on
    assert not [v for v in environ if v.startswith(b"MS_PASS=") or b"field crew" in v]
