"""Stream requests and their arrival, reboot and stale data, the magnetometer unit rule, the
source choice, outgoing packets in the recording, a repeated MAG_CAL_REPORT counted once, and who
changed a compass parameter (issue 25; the same against ArduPilot's firmware in tests/sitl/)."""
from __future__ import annotations

import socket
import time
from types import SimpleNamespace

import pytest

from groundstation.io.decode import MavlinkDecoder, judge_field_unit, HIGHRES_MAG_UNITS
from groundstation.io.link import LiveLink
from groundstation.io.logs import read_log
from groundstation.io.logs.builder import LogBuilder
from groundstation.io.mavlink import TlogWriter, mavlink2 as m
from groundstation.io.streams import StreamTracker
from groundstation.jobs.log_summary import distinct_reports
from groundstation.samples import MagCalSample, MagSample, StatusSample
from groundstation.station.hub.param_watch import autopilot_change


def test_tracker_matches_acks_in_order_and_says_why_each_is_missing():
    tr = StreamTracker()
    tr.requested(["ATTITUDE", "RAW_IMU", "SCALED_IMU3", "MAG_CAL_REPORT"], 100.0)
    assert tr.ack(0) == "ATTITUDE" and tr.ack(3) == "RAW_IMU" and tr.ack(0) == "SCALED_IMU3"
    tr.seen("ATTITUDE", 100.5)
    tr.seen("ATTITUDE", 101.0)
    snap = {r["name"]: r for r in tr.snapshot(101.0, passive=False)["messages"]}
    assert snap["ATTITUDE"]["state"] == "arriving" and snap["ATTITUDE"]["rate_hz"] == 2.0
    assert snap["RAW_IMU"]["state"] == "missing" and "unsupported" in snap["RAW_IMU"]["why"]
    assert "accepted by the vehicle but not sent" in snap["SCALED_IMU3"]["why"]
    assert snap["MAG_CAL_REPORT"]["state"] == "on demand"
    assert tr.retry_due(104.0) == ["SCALED_IMU3"]         # accepted, not arriving: asked again; refused: not
    later = {r["name"]: r for r in tr.snapshot(105.0, passive=False)["messages"]}
    assert later["ATTITUDE"]["state"] == "missing" and "ATTITUDE" in tr.snapshot(105.0, False)["missing"]
    passive = StreamTracker()
    passive.seen("RAW_IMU", 10.0)
    rows = {r["name"]: r for r in passive.snapshot(10.5, passive=True)["messages"]}
    assert rows["RAW_IMU"]["why"] == "provided by the other ground station"
    assert rows["SCALED_IMU2"]["state"] == "missing" and "only listens" in rows["SCALED_IMU2"]["why"]


def test_highres_unit_judged_by_field_length_against_the_wmm_or_the_plausible_range():
    ardupilot = judge_field_unit("HIGHRES_IMU[0]", 488_000.0, HIGHRES_MAG_UNITS)     # get_field() * 1000
    assert ardupilot.scale_to_mG == 1e-3 and ardupilot.magnitude_mG == pytest.approx(488.0) and ardupilot.plausible
    px4 = judge_field_unit("HIGHRES_IMU[0]", 0.45, HIGHRES_MAG_UNITS, expected_mG=460.0)   # gauss
    assert px4.scale_to_mG == 1000.0 and px4.plausible and "WMM" in px4.why
    odd = judge_field_unit("RAW_IMU", 5000.0, expected_mG=480.0)
    assert not odd.plausible and "implausible" in odd.why
    dec = MavlinkDecoder()
    enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3)
    hb.pack(enc)
    dec.decode(hb, 0.0)
    msg = m.MAVLink_highres_imu_message(0, 0, 0, -9.8, 0, 0, 0, 200_000.0, -50_000.0, 440_000.0, 0, 0, 0, 0, 0x1FF, 0)
    msg.pack(enc)
    mag = [s for s in dec.decode(msg, 1.0) if isinstance(s, MagSample)][0]
    assert mag.mag_body_mG == pytest.approx((200.0, -50.0, 440.0))
    assert dec.mag_units["HIGHRES_IMU[0]"]["unit"].startswith("mG x 1000")


def _rows(builder: LogBuilder, instance: int, field_mG, n: int, t0: float = 0.0) -> None:
    for k in range(n):
        builder.add(MagSample(t0 + k * 0.02, tuple(field_mG), instance))


def test_log_source_choice_prefers_a_plausible_field_then_raw_imu_for_ardupilot():
    b = LogBuilder("x.tlog")
    b.add(StatusSample(0.0, "autopilot", "ardupilot"))
    _rows(b, 0, (200.0, -50.0, 400.0), 50)            # RAW_IMU, fewer samples
    _rows(b, 20, (200.0, -50.0, 400.0), 200)          # HIGHRES_IMU (read right), more
    log = b.finish()
    c0 = log.compass_tables()[0]
    assert c0.source == "RAW_IMU" and "preferred to HIGHRES_IMU" in c0.source_note
    b = LogBuilder("y.tlog")                           # not ArduPilot; HIGHRES misread by 10^6
    _rows(b, 10, (200.0, -50.0, 400.0), 50)
    _rows(b, 20, (2e8, -5e7, 4e8), 200)
    c0 = b.finish().compass_tables()[0]
    assert c0.source == "SCALED_IMU" and "HIGHRES_IMU[0] (|B| 4.5e+08 mG" in c0.source_note


def test_a_repeated_report_counts_once_and_a_new_start_counts_again():
    rep = lambda t, k: MagCalSample(t, "report", k, 0, 100.0, 4, 0, 0.03, (1.0, 2.0, 3.0))  # noqa: E731
    events = [MagCalSample(0.0, "start", -1)] + [rep(1 + 0.1 * i, i % 3) for i in range(38)]
    assert len(distinct_reports(events)) == 3
    events += [MagCalSample(10.0, "start", -1), rep(11.0, 0)]
    assert len(distinct_reports(events)) == 4


def test_the_autopilots_own_compass_changes_are_not_another_stations():
    vehicle = SimpleNamespace(params={"COMPASS_AUTODEC": 1.0, "COMPASS_LEARN": 0.0}, changed_by_autopilot={},
                              changed_elsewhere={"COMPASS_DEC": (0.0, -0.1), "COMPASS_OFS_X": (5.0, 9.0)})
    link = SimpleNamespace(param_sets_seen={})
    assert "COMPASS_AUTODEC" in autopilot_change(vehicle, link, "COMPASS_DEC", 100.0)
    assert autopilot_change(vehicle, link, "COMPASS_OFS_X", 100.0) is None      # nobody learns: another station
    vehicle.params["COMPASS_LEARN"] = 3.0
    assert "COMPASS_LEARN" in autopilot_change(vehicle, link, "COMPASS_OFS_X", 100.0)
    link.param_sets_seen["COMPASS_DEC"] = (254, 95.0)                          # heard another GCS set it
    assert autopilot_change(vehicle, link, "COMPASS_DEC", 100.0) is None
    vehicle.params["COMPASS_AUTODEC"] = 0.0
    assert autopilot_change(vehicle, link, "COMPASS_DEC", 200.0) is None


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_stale_data_reboot_and_outgoing_packets_recorded(tmp_path):
    """A fake ArduPilot on loopback: acknowledges, streams ATTITUDE + RAW_IMU, then stops the IMU
    while its heartbeats go on (stale: "no attitude data", asked again), then comes back with its
    boot time gone back (a reboot: streams asked again).  The recording holds both directions."""
    port = _free_udp_port()
    recorder = TlogWriter(tmp_path / "s.tlog")
    link = LiveLink(f"udpin:127.0.0.1:{port}", recorder=recorder)
    veh = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    veh.setblocking(False)
    enc, parser = m.MAVLink(None, srcSystem=1, srcComponent=1), m.MAVLink(None)
    parser.robust_parsing = True
    requests: list[float] = []
    asked: list[int] = []                       # the message ids of the SET_MESSAGE_INTERVAL requests
    samples: list = []
    boot_ms, t_start = 100_000, time.monotonic()
    last_hb = 0.0

    def step(imu: bool) -> None:
        nonlocal boot_ms, last_hb
        now = time.monotonic()
        pkts = []
        if now - last_hb > 0.5:
            last_hb = now
            pkts.append(m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3))
        if imu:
            pkts += [m.MAVLink_attitude_message(boot_ms, 0.01, 0.02, 0.3, 0, 0, 0),
                     m.MAVLink_raw_imu_message(boot_ms * 1000, 0, 0, -1000, 0, 0, 0, 200, -50, 400)]
        for p in pkts:
            veh.sendto(bytes(p.pack(enc)), ("127.0.0.1", port))
        boot_ms += 20
        try:
            while True:
                for msg in parser.parse_buffer(veh.recv(4096)) or []:
                    if msg.get_type() == "COMMAND_LONG" and msg.command == 511:
                        requests.append(now - t_start)
                        asked.append(int(msg.param1))
                        denied = int(msg.param1) == m.MAVLINK_MSG_ID_SENSOR_OFFSETS    # as ArduPilot 4.7
                        ack = m.MAVLink_command_ack_message(511, 2 if denied else 0, 0, 0, 255, 0)
                        veh.sendto(bytes(ack.pack(enc)), ("127.0.0.1", port))
        except (BlockingIOError, m.MAVError):
            pass
        samples.extend(link.poll())
        time.sleep(0.02)

    try:
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            step(True)
        first_round = len(requests)
        assert link.stale_reason is None and first_round >= 12      # 14 less SCALED_IMU, HIGHRES_IMU (ArduPilot)
        end = time.monotonic() + 2.5
        while time.monotonic() < end:                    # heartbeats only
            step(False)
        assert link.stale_reason and "no IMU data" in link.stale_reason
        assert len(requests) > first_round               # asked again
        boot_ms = 500                                    # rebooted: boot time back to 0.5 s
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            step(True)
        assert link.stale_reason is None
        rows = {r["name"]: r for r in link.streams_snapshot()["messages"]}
    finally:
        veh.close()
        link.close()
        recorder.close()
    # asked after the connect, the stale data and the reboot; the refused SENSOR_OFFSETS only once
    assert asked.count(m.MAVLINK_MSG_ID_ATTITUDE) >= 3 and asked.count(m.MAVLINK_MSG_ID_SENSOR_OFFSETS) == 1, asked
    assert rows["SENSOR_OFFSETS"]["state"] == "not available" and "denied" in rows["SENSOR_OFFSETS"]["why"]
    kinds = [(s.kind, s.text) for s in samples if isinstance(s, StatusSample)]
    assert any(k == "live_data" and t.startswith("no attitude data") for k, t in kinds)
    assert any(k == "live_data" and t == "live data resumed" for k, t in kinds)
    assert any(k == "reboot" and "boot time went back" in t for k, t in kinds)
    log = read_log(tmp_path / "s.tlog")
    assert log.message_counts["COMMAND_LONG"] >= len(requests)       # what the station sent is recorded
    assert log.message_counts["HEARTBEAT"] > 0 and not log.warnings.get("timestamps going backwards (re-based)")


def test_refused_or_unanswered_requests_fall_back_to_request_data_stream():
    refused = StreamTracker()
    refused.requested(["ATTITUDE", "RAW_IMU"], 0.0)
    refused.ack(3)
    refused.ack(3)
    assert not refused.unanswered_since(1.0) and refused.unanswered_since(2.5)
    silent = StreamTracker()
    silent.requested(["ATTITUDE"], 0.0)
    assert silent.unanswered_since(2.5)
    accepted = StreamTracker()
    accepted.requested(["ATTITUDE", "RAW_IMU"], 0.0)
    accepted.ack(0)
    assert not accepted.unanswered_since(5.0)
