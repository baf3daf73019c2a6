"""LiveLink over real loopback sockets: UDP and TCP, stream requests, recording, garbage."""
from __future__ import annotations

import socket
import threading
import time
from collections import Counter

import pytest

import groundstation  # noqa: F401
from groundstation.io.link import LinkOptions, LiveLink
from groundstation.io.logs import read_log
from groundstation.io.logs.tlog import tlog_records
from groundstation.io.mavlink import TlogWriter, mavlink2 as m
from groundstation.samples import MagSample, StatusSample


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def vehicle_packets(enc: m.MAVLink, k: int) -> list[bytes]:
    hb = m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3)
    imu = m.MAVLink_scaled_imu_message(1000 + 20 * k, 0, 0, -1000, 0, 0, 0, 200 + k, -50, 400)
    return [bytes(hb.pack(enc)), bytes(imu.pack(enc))]


def poll_until(link: LiveLink, predicate, timeout_s: float = 5.0) -> list:
    got: list = []
    deadline = time.time() + timeout_s
    while time.time() < deadline and not predicate(got):
        got += link.poll()
        time.sleep(0.01)
    return got


def decode_all(parser: m.MAVLink, data: bytes) -> list:
    try:
        return parser.parse_buffer(data) or []
    except m.MAVError:
        return []


def test_udp_link_requests_streams_falls_back_and_records(tmp_path):
    port = free_port()
    recorder = TlogWriter(tmp_path / "session.tlog")
    link = LiveLink(f"udpin:127.0.0.1:{port}", recorder=recorder)
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.settimeout(0.05)
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = m.MAVLink(None)
    parser.robust_parsing = True
    received: list = []
    try:
        vehicle.sendto(b"\x00garbage datagram\xff" * 3, ("127.0.0.1", port))
        deadline = time.time() + 6
        samples: list = []
        k = 0
        while time.time() < deadline:
            for pkt in vehicle_packets(enc, k):
                vehicle.sendto(pkt, ("127.0.0.1", port))
            k += 1
            samples += link.poll()
            try:
                while True:
                    received += decode_all(parser, vehicle.recv(4096))
            except (socket.timeout, BlockingIOError):
                pass
            if any(msg.get_type() == "REQUEST_DATA_STREAM" for msg in received):
                break
            time.sleep(0.02)
    finally:
        vehicle.close()
        link.close()
        recorder.close()
    types = [msg.get_type() for msg in received]
    assert "HEARTBEAT" in types  # the station's GCS heartbeat
    intervals = [msg for msg in received if msg.get_type() == "COMMAND_LONG" and msg.command == 511]
    asked = {int(msg.param1) for msg in intervals}        # an ArduPilot heartbeat: compass 1 in RAW_IMU
    assert asked >= {m.MAVLINK_MSG_ID_RAW_IMU, m.MAVLINK_MSG_ID_SCALED_IMU2, m.MAVLINK_MSG_ID_SCALED_IMU3,
                     m.MAVLINK_MSG_ID_ATTITUDE, m.MAVLINK_MSG_ID_SYS_STATUS, m.MAVLINK_MSG_ID_MAG_CAL_REPORT}
    assert m.MAVLINK_MSG_ID_HIGHRES_IMU not in asked
    assert intervals[0].param2 == pytest.approx(20000)  # 50 Hz
    assert "REQUEST_DATA_STREAM" in types  # no COMMAND_ACK came, so it fell back
    mags = [s for s in samples if isinstance(s, MagSample)]
    assert mags and mags[0].mag_body_mG == (200.0, -50.0, 400.0)
    assert any(isinstance(s, StatusSample) and "link up" in s.text for s in samples)
    assert link.bad_packets >= 1
    recorded = read_log(tmp_path / "session.tlog")
    assert len(recorded.mag) == len(mags)


def test_udp_garbage_never_swallows_the_next_datagram_and_packed_datagrams_all_parse():
    """A garbage datagram that starts like a MAVLink 2 packet and claims more bytes than it holds
    is followed by a good packet: the good one must be read (pymavlink alone joins the two and
    loses the good packet to a CRC error).  A datagram carrying two packets gives both."""
    port = free_port()
    link = LiveLink(f"udpin:127.0.0.1:{port}", options=LinkOptions(passive=True))
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    n_pairs = 60
    try:
        for k in range(n_pairs):
            # a whole packet with a wrong CRC, then 0xFD with payload length 200 and 30 more bytes:
            # the parser reads the first as bad data and waits for ~180 bytes more of the second
            bad_crc = bytes([0xFD, 4, 0, 0, k, 1, 1, 30, 0, 0, 1, 2, 3, 4, 0xAB, 0xCD])
            vehicle.sendto(bad_crc + bytes([0xFD, 200]) + bytes(range(k, k + 30)), ("127.0.0.1", port))
            vehicle.sendto(b"".join(vehicle_packets(enc, k)), ("127.0.0.1", port))   # two in one
            time.sleep(0.002)
        got = poll_until(link, lambda g: sum(isinstance(s, MagSample) for s in g) >= n_pairs)
    finally:
        vehicle.close()
        link.close()
    mags = [s.mag_body_mG[0] for s in got if isinstance(s, MagSample)]
    assert mags == [200.0 + k for k in range(n_pairs)]


def test_tcp_link_and_loss_is_reported():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    stop = threading.Event()

    def vehicle() -> None:
        conn, _ = server.accept()
        enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
        for k in range(25):
            conn.sendall(b"".join(vehicle_packets(enc, k)))
            time.sleep(0.02)
        stop.wait(5)
        conn.close()

    thread = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    link = LiveLink(f"tcp:127.0.0.1:{port}")
    link.LOST_AFTER_S = 0.5
    try:
        got = poll_until(link, lambda g: sum(isinstance(s, MagSample) for s in g) >= 25)
        assert sum(isinstance(s, MagSample) for s in got) == 25
        lost = poll_until(link, lambda g: any(isinstance(s, StatusSample) and "lost" in s.text for s in g))
        assert any("link lost" in s.text for s in lost if isinstance(s, StatusSample))
    finally:
        stop.set()
        link.close()
        server.close()


def test_udp_packets_read_late_keep_their_kernel_arrival_times(tmp_path):
    """A reader held up (here 0.6 s, as by busy estimation threads on a loaded station) reads a
    backlog: each packet keeps the time the kernel received it, not the time it was read, in the
    recording and on the samples (a late stamp looks like link delay and moves the boot clock)."""
    port = free_port()
    recorder = TlogWriter(tmp_path / "session.tlog")
    link = LiveLink(f"udpin:127.0.0.1:{port}", recorder=recorder, options=LinkOptions(passive=True))
    hold = threading.Event()
    select = link.mav.select

    def held_select(timeout):
        hold.wait(5.0)                      # the reader waits here while the packets arrive
        return select(timeout)

    link.mav.select = held_select
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    sent_unix: list[float] = []
    try:
        time.sleep(0.2)                     # the reader is now waiting in held_select
        for k in range(3):
            for pkt in vehicle_packets(enc, k):
                vehicle.sendto(pkt, ("127.0.0.1", port))
            sent_unix.append(time.time())
            time.sleep(0.3)
        read_from = time.time()
        hold.set()
        got = poll_until(link, lambda g: sum(isinstance(s, MagSample) for s in g) >= 3)
    finally:
        vehicle.close()
        link.close()
        recorder.close()
    assert sum(isinstance(s, MagSample) for s in got) == 3
    with open(tmp_path / "session.tlog", "rb") as f:
        everything = list(tlog_records(f, Counter()))
    stamps = [t for t, msg in everything if msg.get_type() == "SCALED_IMU"]
    assert len(stamps) == 3
    assert read_from - sent_unix[-1] >= 0.25
    for stamp, sent in zip(stamps, sent_unix):
        assert abs(stamp - sent) < 0.05, (stamps, sent_unix)
