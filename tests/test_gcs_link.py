"""Beside another ground station, over real loopback sockets: passive mode sends nothing (counted
on the wire), forwarding passes every packet both ways with little added latency, MAVLink 2
signing makes writes to a signing vehicle work and unsigned ones fail."""
from __future__ import annotations

import socket
import threading
import time

import pytest

from conftest import free_tcp_port, free_udp_port, rotation_dance_messages, wait_until
from groundstation.io.errors import IngestError
from groundstation.io.forward import Forwarder, MavlinkFramer, parse_forward_url
from groundstation.io.link import LinkOptions
from groundstation.io.mavlink import mavlink2 as m, new_encoder
from groundstation.io.signing import key_from_passphrase, read_key_file
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.station.hub.session import ConflictError, Session

GCS_COMMAND = 31010          # MAV_CMD_USER_1: a command only the fake ground station sends


def wait_for(cond, timeout=10.0) -> bool:
    return wait_until(cond, timeout, 0.02)


def gcs_heartbeat(enc) -> bytes:
    return bytes(m.MAVLink_heartbeat_message(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(enc))


# ------------------------------------------------------------------------------------ passive

def test_passive_sends_nothing_on_the_wire_and_refuses_writes(tmp_path):
    port = free_udp_port()
    hub = Session(tmp_path, link_options=LinkOptions(passive=True))
    hub.connect(f"udpin:127.0.0.1:{port}")
    fv = FakeVehicle(rotation_dance_messages(turn_s=1.0, tumble_s=3.0), port, speed=1.0).start()
    try:
        assert wait_for(lambda: hub.snapshot()["source"]["link"] == "up")
        hub.wizard_start()
        time.sleep(3.0)                   # three heartbeat periods: an active station would have sent
        snap = hub.snapshot()
        assert snap["rx_count"] > 100 and snap["vehicles"]["passive"] is True
        assert fv.rx_datagrams == 0                               # nothing at all reached the vehicle
        with pytest.raises(ConflictError, match=r"\.param"):
            hub.wizard_accept()
        with pytest.raises(ConflictError, match="only listens"):
            hub.vehicle.send_command(hub.sources.link, m.MAV_CMD_DO_START_MAG_CAL, 0)
        assert fv.rx_datagrams == 0 and fv.param_sets == [] and fv.commands == []
    finally:
        fv.stop()
        hub.close()


def test_another_ground_station_heartbeat_makes_the_station_passive(tmp_path):
    port = free_udp_port()
    hub = Session(tmp_path)
    hub.connect(f"udpin:127.0.0.1:{port}")
    fv = FakeVehicle(rotation_dance_messages(turn_s=2.0, tumble_s=6.0), port, speed=1.0).start()
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert wait_for(lambda: fv.rx_datagrams >= 2)             # active: heartbeats, stream requests
        other.sendto(gcs_heartbeat(new_encoder(255, 190)), ("127.0.0.1", port))
        assert wait_for(lambda: hub.snapshot()["vehicles"]["passive"])
        time.sleep(0.2)
        sent = fv.rx_datagrams
        time.sleep(2.5)
        snap = hub.snapshot()
        assert fv.rx_datagrams == sent                            # silent from then on
        assert "another ground station (system 255)" in snap["vehicles"]["passive_reason"]
        assert any("only listens" in e["text"] for e in snap["events"])
        kinds = {s["sysid"]: s["kind"] for s in snap["vehicles"]["systems"]}
        assert kinds == {1: "vehicle", 255: "ground station"}
    finally:
        other.close()
        fv.stop()
        hub.close()


# ------------------------------------------------------------------------------------ forwarding

def stream_400hz(seconds: float) -> list:
    out = []
    for i in range(int(seconds * 400)):
        t = 1.8e9 + i / 400.0
        out.append((t, m.MAVLink_scaled_imu_message(int(i * 2.5), 0, 0, -1000, 1, 2, 3, 200 + i % 50, -50, 400)))
    return out


class FakeGcsUdp:
    """A ground station listening on UDP (Mission Planner's udpin): counts and timestamps what
    arrives, answers with ``n_commands`` COMMAND_LONGs to whoever sent to it."""

    def __init__(self, n_commands: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)   # this test process is busy
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.arrivals: list[tuple[int, float]] = []     # (seq, time.monotonic()) of each packet
        self.n_commands = n_commands
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        enc, peer, sent, framer = new_encoder(255, 190), None, 0, MavlinkFramer()
        while not self.stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65535)
                now = time.monotonic()
                self.arrivals += [(p[4] if p[0] == 0xFD else p[2], now) for p in framer.feed(data)]
            except socket.timeout:
                pass
            if peer is not None and sent < self.n_commands and len(self.arrivals) > 40 * (sent + 1):
                cmd = m.MAVLink_command_long_message(1, 1, GCS_COMMAND, 0, sent, 0, 0, 0, 0, 0, 0)
                self.sock.sendto(bytes(cmd.pack(enc)), peer)
                enc.seq = (enc.seq + 1) % 256
                sent += 1


def test_forwarding_passes_every_packet_both_ways(tmp_path):
    gcs = FakeGcsUdp(n_commands=60)
    tcp_port = free_tcp_port()
    forwarder = Forwarder([f"udpout:127.0.0.1:{gcs.port}", f"tcpin:127.0.0.1:{tcp_port}"]).start()
    port = free_udp_port()
    hub = Session(tmp_path, forwarder=forwarder)
    hub.connect(f"udpin:127.0.0.1:{port}")
    tcp = socket.create_connection(("127.0.0.1", tcp_port))
    tcp.settimeout(0.05)
    tcp_packets: list[bytes] = []
    tcp_framer = MavlinkFramer()
    fv = FakeVehicle(stream_400hz(8.0), port, speed=1.0)
    fv.record_send_times = True
    gcs.thread.start()
    try:
        assert wait_for(lambda: forwarder.refresh() and forwarder.snapshot()["outputs"][1]["clients"] == 1, 5)
        fv.start()
        assert wait_for(lambda: hub.snapshot()["source"]["link"] == "up", 3)    # the vehicle has a peer now
        enc = new_encoder(255, 191)
        for k in range(20):                     # the TCP ground station's commands
            tcp.sendall(bytes(m.MAVLink_command_long_message(1, 1, GCS_COMMAND + 1, 0, k, 0, 0, 0, 0, 0, 0).pack(enc)))
            enc.seq = (enc.seq + 1) % 256
        deadline = time.monotonic() + 30
        while not fv.finished.is_set() and time.monotonic() < deadline:
            try:
                tcp_packets += tcp_framer.feed(tcp.recv(65536))
            except socket.timeout:
                pass
        time.sleep(1.2)                         # the last packets and one more heartbeat
        try:
            while True:
                tcp_packets += tcp_framer.feed(tcp.recv(65536))
        except socket.timeout:
            pass
        sent = sum(fv.delivered.values())
        commands = [args for cmd, args in fv.commands if cmd == GCS_COMMAND]
        tcp_commands = [args for cmd, args in fv.commands if cmd == GCS_COMMAND + 1]
        assert forwarder.refresh()
        snapshot = hub.snapshot()["vehicles"]["forwarding"]
        station_rx = hub.snapshot()["rx_count"]
    finally:
        gcs.stop.set()
        gcs.thread.join(2)
        fv.stop()
        tcp.close()
        hub.close()
    counts = (sent, station_rx, len(gcs.arrivals), len(tcp_packets), snapshot)
    assert len(gcs.arrivals) == sent and len(tcp_packets) == sent, counts  # vehicle -> both ground stations
    assert len(commands) == 60 and [int(a[0]) for a in commands] == list(range(60))   # and back, in order
    assert len(tcp_commands) == 20
    assert snapshot["to_vehicle"] == 80 and snapshot["outputs"][0]["to_gcs"] == sent
    sends = fv.send_log                         # and in the order the vehicle sent them
    assert [q for q, _ in sends] == [q for q, _ in gcs.arrivals][:len(sends)]


def test_forward_urls_are_checked():
    assert parse_forward_url("udpout:127.0.0.1:14550").kind == "udpout"
    for bad in ("udpin:127.0.0.1:14550", "tcpin:0.0.0.0:5760", "/bin/sh", "file:/etc/passwd", "tcp:127.0.0.1:5"):
        with pytest.raises(IngestError):
            parse_forward_url(bad)
    assert parse_forward_url("tcpin:0.0.0.0:5760", listen_any=True).kind == "tcpin"


def test_framer_cuts_streams_into_packets():
    enc = new_encoder(1, 1)
    packets = [bytes(m.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(enc)) for _ in range(3)]
    signed_enc = new_encoder(1, 1)
    signed_enc.signing.secret_key, signed_enc.signing.sign_outgoing = b"k" * 32, True
    packets.append(bytes(m.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(signed_enc)))
    stream = b"\x00junk" + b"".join(packets)
    framer = MavlinkFramer()
    got = [p for i in range(0, len(stream), 7) for p in framer.feed(stream[i:i + 7])]
    assert got == packets and framer.skipped_bytes == 5 and len(packets[-1]) == len(packets[0]) + 13


# ------------------------------------------------------------------------------------ signing

def test_signing_key_from_passphrase_and_files(tmp_path):
    import hashlib

    key = key_from_passphrase("correct horse")
    assert key == hashlib.sha256(b"correct horse").digest() and len(key) == 32
    (tmp_path / "pass.txt").write_text("correct horse\n")
    (tmp_path / "hex.txt").write_text(key.hex())
    (tmp_path / "raw.key").write_bytes(key)
    assert {read_key_file(tmp_path / n) for n in ("pass.txt", "hex.txt", "raw.key")} == {key}
    with pytest.raises(IngestError):
        read_key_file(tmp_path)
    assert key.hex() not in repr(LinkOptions(signing_key=key))


def write_one(hub: Session, name: str, value: float) -> tuple:
    assert wait_for(lambda: hub.snapshot()["source"]["link"] == "up")
    return hub.vehicle.write_params(hub.sources.link, {name: value}, progress=lambda c: None, tries=2,
                                    timeout_s=0.5)


def test_signed_write_succeeds_unsigned_is_refused_and_reported(tmp_path):
    key = key_from_passphrase("field crew key")
    msgs = rotation_dance_messages(turn_s=2.0, tumble_s=8.0)

    port = free_udp_port()
    hub = Session(tmp_path / "a", link_options=LinkOptions(signing_key=key))
    hub.connect(f"udpin:127.0.0.1:{port}")
    fv = FakeVehicle(msgs, port, autopilot="px4", params={"CAL_MAG0_XOFF": 0.0}, signing_key=key,
                     require_signing=True).start()
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        confirmed, failed, _ = write_one(hub, "CAL_MAG0_XOFF", 0.125)    # gauss (beyond ±3 G a PARAM_VALUE is refused)
        assert confirmed == ["CAL_MAG0_XOFF"] and failed == [] and fv.params["CAL_MAG0_XOFF"] == 0.125
        before, bad_before = hub.snapshot()["rx_count"], hub.sources.link.bad_packets
        spoof = new_encoder(1, 1)                                 # unsigned, as if from the vehicle
        wrong = new_encoder(1, 1)
        wrong.signing.secret_key, wrong.signing.sign_outgoing = key_from_passphrase("wrong"), True
        wrong.signing.timestamp = int((time.time() - 1420070400 + 3600) * 1e5)     # an hour ahead
        for enc in (spoof,) * 5 + (wrong,) * 3:
            intruder.sendto(bytes(m.MAVLink_scaled_imu_message(1, 0, 0, 0, 0, 0, 0, 9999, 9999, 9999).pack(enc)),
                            ("127.0.0.1", port))
        assert wait_for(lambda: hub.snapshot()["vehicles"]["signing"]["unsigned"] >= 5
                        and hub.snapshot()["vehicles"]["signing"]["bad_signature"] >= 3)
        signing = hub.snapshot()["vehicles"]["signing"]
        assert signing["on"] and signing["good"] > 10 and signing["key_id"] and before > 0, signing
        assert signing["unsigned"] == 5 and signing["bad_signature"] == 3, signing
        # the forged packets' future timestamp did not lock the vehicle's own stream out
        assert wait_for(lambda: hub.snapshot()["vehicles"]["signing"]["good"] > signing["good"] + 20)
        assert hub.snapshot()["vehicles"]["signing"]["bad_signature"] == 3
        assert hub.sources.link.bad_packets == bad_before + 8    # refused whole: never decoded
    finally:
        intruder.close()
        fv.stop()
        hub.close()

    port = free_udp_port()
    hub = Session(tmp_path / "b")                                  # no key: the vehicle refuses its writes
    hub.connect(f"udpin:127.0.0.1:{port}")
    fv = FakeVehicle(msgs, port, autopilot="px4", params={"CAL_MAG0_XOFF": 0.0}, signing_key=key,
                     require_signing=True).start()
    try:
        confirmed, failed, echoed = write_one(hub, "CAL_MAG0_XOFF", 0.07)
        assert confirmed == [] and failed == ["CAL_MAG0_XOFF"] and echoed == {}
        assert fv.params["CAL_MAG0_XOFF"] == 0.0 and fv.param_sets == [] and fv.refused_unsigned >= 2
        snap = hub.snapshot()
        assert any("signs its packets" in e["text"] and "key" in e["text"] for e in snap["events"])
        assert [s["signed"] for s in snap["vehicles"]["systems"]] == [True]
    finally:
        fv.stop()
        hub.close()


# ------------------------------------------------------------------------------------ parameter cache

def test_compass_params_loaded_by_another_station_are_seen_and_the_calibration_follows(tmp_path):
    """The passive way: the station fits, cannot write; the other ground station loads the result
    (its PARAM_SETs go straight to the vehicle); the station sees the unrequested PARAM_VALUEs and
    stops applying its own copy, since the vehicle now corrects its field itself."""
    port = free_udp_port()
    hub = Session(tmp_path, link_options=LinkOptions(passive=True))
    hub.connect(f"udpin:127.0.0.1:{port}")
    hub.wizard_start()
    fv = FakeVehicle(rotation_dance_messages(turn_s=2.0, tumble_s=10.0), port, speed=4.0).start()
    other, enc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), new_encoder(255, 190)
    vehicle_addr = fv._sock.getsockname()

    def other_sends(msg) -> None:
        other.sendto(bytes(msg.pack(enc)), vehicle_addr)
        enc.seq = (enc.seq + 1) % 256

    try:
        other_sends(m.MAVLink_param_request_list_message(1, 1))     # the other station's download
        assert wait_for(lambda: "COMPASS_OFS_X" in hub.params, 5)
        assert wait_for(lambda: hub.snapshot()["wizard"]["state"] == "result", 30)
        with pytest.raises(ConflictError, match=r"\.param"):
            hub.wizard_accept()
        ours = hub.snapshot()["wizard"]["result"]["ardupilot_params"]
        assert abs(ours["COMPASS_OFS_X"]) > 10                        # a real change to load
        for name, value in ours.items():
            other_sends(m.MAVLink_param_set_message(1, 1, name.encode(), value, m.MAV_PARAM_TYPE_REAL32))
        assert wait_for(lambda: hub.snapshot()["wizard"].get("in_use") == "vehicle", 5)
        snap = hub.snapshot()
        changed = snap["vehicles"]["params_changed_elsewhere"]
        assert changed["COMPASS_OFS_X"][1] == pytest.approx(ours["COMPASS_OFS_X"], abs=1e-3)
        texts = [e["text"] for e in snap["events"]]
        assert any("changed by another ground station" in t for t in texts)
        assert any("now holds this station's calibration" in t for t in texts)
        assert snap["calibration_in_use"] and hub.flight.calibration is None    # the vehicle's, not a copy
        assert fv.rx_datagrams == 1 + len(ours)                       # all from the other station, none from us
    finally:
        other.close()
        fv.stop()
        hub.close()


# ------------------------------------------------------------------------------------ command line

def test_serve_link_options_are_checked_in_one_line_and_the_key_never_shown(tmp_path, capsys, monkeypatch):
    from groundstation.cli import main
    from groundstation.station.app import link_lines
    from groundstation.station.settings import StationSettings

    monkeypatch.setenv("MAGSTATION_TEST_PASS", "very secret words")
    demo = str(tmp_path / "x.tlog")
    (tmp_path / "x.tlog").write_bytes(b"")
    for args, why in ((["--forward", "udpin:127.0.0.1:14550"], "cannot be a forwarding output"),
                      (["--forward", "/usr/bin/python3"], "not a connection string"),
                      (["--forward", "tcpin:0.0.0.0:5760"], "only listen on loopback"),
                      (["--sysid", "0"], "system id is 1..255"),
                      (["--signing-passphrase-env", "MAGSTATION_NO_SUCH_VAR"], "holds no signing passphrase")):
        code = main(["serve", "--replay", demo, "--signing-passphrase-env", "MAGSTATION_TEST_PASS", *args]
                    if "--signing-passphrase-env" not in args else ["serve", "--replay", demo, *args])
        err = capsys.readouterr().err
        assert code == 1 and why in err and err.count("\n") == 1, err
        assert "very secret" not in err
    key = key_from_passphrase("very secret words")
    settings = StationSettings(viser_port=None, signing_key=key, sysid=3, passive=True,
                               forward=("udpout:127.0.0.1:14550",))
    shown = " ".join(link_lines(settings)) + repr(settings)
    assert key.hex() not in shown and str(key) not in shown and "very secret" not in shown
    assert "key id" in shown and "following vehicle (system id) 3" in shown and "passive" in shown


def test_a_vehicle_without_heartbeat_is_followed_after_a_while():
    """Some bridges forward sensor messages without the autopilot's heartbeat: after
    NO_HEARTBEAT_FOLLOW_S the busiest system is followed, and its samples come through."""
    from groundstation.io.link import NO_HEARTBEAT_FOLLOW_S, LiveLink
    from groundstation.samples import MagSample, StatusSample

    port = free_udp_port()
    link = LiveLink(f"udpin:127.0.0.1:{port}", options=LinkOptions(passive=True))
    sender, enc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), new_encoder(7, 1)
    got: list = []
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < NO_HEARTBEAT_FOLLOW_S + 1.0:
            imu = m.MAVLink_scaled_imu_message(int((time.monotonic() - t0) * 1000), 0, 0, -1000, 0, 0, 0, 200, -50, 400)
            sender.sendto(bytes(imu.pack(enc)), ("127.0.0.1", port))
            enc.seq = (enc.seq + 1) % 256
            got += link.poll()
            time.sleep(0.02)
    finally:
        sender.close()
        link.close()
    found = [s for s in got if isinstance(s, StatusSample) and s.kind == "vehicle_found"]
    assert link.sysid == 7 and len(found) == 1 and "following vehicle 7" in found[0].text
    first_mag = next(i for i, s in enumerate(got) if isinstance(s, MagSample))
    assert first_mag > got.index(found[0])                        # none before it was chosen
