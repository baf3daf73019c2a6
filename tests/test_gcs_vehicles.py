"""Several vehicles on one UDP link (real loopback sockets): the station follows the chosen one,
no sample of the other enters the estimates, and its outputs equal those of the vehicle alone."""
from __future__ import annotations

import math
import multiprocessing

import time
from collections import Counter

import numpy as np
import pytest
from fastapi.testclient import TestClient

from conftest import free_udp_port, wait_until
from groundstation.io.decode import MavlinkDecoder
from groundstation.io.link import LinkOptions
from groundstation.io.logs import read_log
from groundstation.io.mavlink import mavlink2
from groundstation.jobs.record import COL
from groundstation.samples import StatusSample
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate
from groundstation.station.app import create_app
from groundstation.station.hub.session import Session

SPEED = 1.5        # x real time (faster compresses the flight's time past the step's alarm; at 2, the
                   # four stations of one test on a loaded 2-core machine fell behind real time)
SIM_S = 80.0
STEP_ON_S, STEP_LONG_S = 50.0, 25.0     # vehicle 1's step, flight time
IMU_HZ = 50.0                           # the simulation's IMU rows per second of flight


def wait_for(cond, timeout=30.0) -> bool:
    return wait_until(cond, timeout, 0.05)


class CapturingSession(Session):
    """A hub that keeps every sample it was given since the last vehicle switch."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.captured: list = []

    def process_batch(self, samples) -> None:
        for s in samples:
            if isinstance(s, StatusSample) and s.kind == "vehicle":
                self.captured = []
            else:
                self.captured.append(s)
        super().process_batch(samples)


def values(samples) -> list[tuple]:
    """The samples without their times (arrival times differ between runs, values must not)."""
    out = []
    for s in samples:
        if isinstance(s, StatusSample):
            continue
        fields = tuple(getattr(s, f) for f in s.__slots__ if f != "t_s")
        out.append((type(s).__name__, fields))
    return out


@pytest.fixture(scope="module")
def sims():
    """Two vehicles calibrated on board (an uncalibrated compass is no evidence: its tests are off).
    The step starts at 50 s of flight, 33 s of the station's time at SPEED 1.5: after the field-vector
    test's 20 s of learning, or the step would be learned as part of the Earth field."""
    return {1: simulate("mission-step", 1, duration_s=SIM_S, onboard_calibration=True,
                        interference=dict(onset_s=STEP_ON_S, duration_s=STEP_LONG_S, amplitude_mG=250.0)),
            2: simulate("mission-clean", 2, duration_s=SIM_S, onboard_calibration=True)}


class VehicleProcess:
    """A FakeVehicle streaming from a child process of its own, as a real vehicle does: in the
    test's process, six senders share the interpreter lock with four busy stations, fall behind
    real time on a loaded 2-core machine, and the stations' boot clocks re-anchor (times jump by
    2 s; CI 2026-12-06: a step's alarm missed).  Forked before the stations start, so the child
    holds no station thread or lock."""

    def __init__(self, messages: list, port: int, system_id: int) -> None:
        context = multiprocessing.get_context("fork")
        self._go, self._stop = context.Event(), context.Event()
        self._results, child_end = context.Pipe(duplex=False)
        self._process = context.Process(target=_stream_vehicle, daemon=True,
                                        args=(messages, port, system_id, self._go, self._stop, child_end))
        self._process.start()
        child_end.close()

    def start(self) -> None:
        self._go.set()

    def finish(self, timeout_s: float) -> tuple[dict, list[bytes]]:
        """(packets put on the wire per message type, every packet) once the stream has ended."""
        assert self._results.poll(timeout_s), "the vehicle's stream did not end in time"
        return self._results.recv()

    def stop(self) -> None:
        self._stop.set()
        self._process.join(5.0)
        if self._process.is_alive():
            self._process.kill()


def _stream_vehicle(messages, port, system_id, go, stop, results) -> None:
    vehicle = FakeVehicle(messages, port, speed=SPEED, system_id=system_id)
    vehicle.delivered_packets = []
    go.wait()
    vehicle.start()
    while not vehicle.finished.wait(0.1) and not stop.is_set():
        pass
    results.send((dict(vehicle.delivered), vehicle.delivered_packets))
    vehicle.stop()


class LiveRun:
    """One hub on its own udpin port with the vehicles ``sysids`` streaming to it at once (made in
    two parts: every run's vehicles first, ``connect`` the hubs after)."""

    def __init__(self, folder, sims, sysids, follow: int | None = None, select: int | None = None) -> None:
        self.port = free_udp_port()
        self.folder, self.follow, self.select = folder, follow, select
        self.sysids = list(sysids)
        self.vehicles = [VehicleProcess(sims[k].messages, self.port, k) for k in sysids]
        self.hub: CapturingSession | None = None

    def connect(self) -> None:
        self.hub = CapturingSession(self.folder, link_options=LinkOptions(sysid=self.follow))
        self.hub.connect(f"udpin:127.0.0.1:{self.port}")

    def start(self) -> None:
        for v in self.vehicles:
            v.start()

    def choose(self) -> None:
        if self.select is not None:
            hub = self.hub
            assert wait_for(lambda: self.select in [s["sysid"] for s in hub.vehicles()["systems"]
                                                    if s["kind"] == "vehicle"], 10)
            hub.select_vehicle(self.select)
            assert wait_for(lambda: hub.vehicles()["selected"] == self.select, 5)

    def finish(self) -> dict:
        hub = self.hub
        try:
            ends = [v.finish(SIM_S / SPEED + 60) for v in self.vehicles]
            delivered = sum(sum(counts.values()) for counts, _ in ends)
            assert wait_for(lambda: hub.snapshot()["rx_count"] >= delivered, 15)
            time.sleep(0.3)
            with hub._lock:
                hub.flight.flush_all()
                return {"samples": values(hub.captured), "alarms": hub.alarm_list(),
                        "rows": hub.flight.rows().copy(), "vehicles": hub.vehicles(), "snapshot": hub.snapshot(),
                        "recording": hub.sources.recording_path,
                        "sent": {k: packets for k, (_, packets) in zip(self.sysids, ends)}}
        finally:
            for v in self.vehicles:
                v.stop()
            hub.close()


def sent_values(packets: list[bytes], sysid: int) -> list[tuple]:
    """The sensor samples in the packets one vehicle put on the wire, decoded as the station does.

    Each GLOBAL_POSITION_INT also counts as a GPS sample: the station's decoder, new at a switch,
    takes the autopilot's position until the vehicle's first GPS_RAW_INT (one decoding the whole
    stream does not)."""
    parser, decoder = mavlink2.MAVLink(None), MavlinkDecoder(vehicle_sysid=sysid)
    samples: list = []
    for packet in packets:
        for msg in parser.parse_buffer(packet) or ():
            samples += decoder.decode(msg, 0.0)
            if msg.get_type() == "GLOBAL_POSITION_INT":
                samples += MavlinkDecoder(vehicle_sysid=sysid).decode(msg, 0.0)
    return sensor_values(values(samples))


def _nan_equal(v):
    """NaN as a marker that equals itself (a decoded NaN is a new float each time: nan != nan)."""
    if isinstance(v, tuple):
        return tuple(_nan_equal(x) for x in v)
    return "NaN" if isinstance(v, float) and math.isnan(v) else v


def sensor_values(samples: list[tuple]) -> list[tuple]:
    """Sensor samples only: parameter answers arrive whenever the station asked for them."""
    return [_nan_equal(v) for v in samples if v[0] != "ParamSample"]


TAIL_SLACK = 20     # samples at the start that may differ


def same_tail(a: list, b: list, slack: int = TAIL_SLACK) -> bool:
    """Equal but for the first few samples: a preset --sysid decodes from the first packet, an
    automatic choice from the first heartbeat on, and until the vehicle's first GPS_RAW_INT a new
    decoder takes the autopilot's position (GLOBAL_POSITION_INT).  Both lists are compared over
    their last (shorter length − ``slack``) samples.  Aligned at the shorter one's very first sample
    they failed once (fresh clone, 2026-12-06: lengths 13603 and 13599; that first sample, a
    position from GLOBAL_POSITION_INT with fix 3, faced the other's from GPS_RAW_INT, the compass
    and IMU samples after it equal)."""
    n = min(len(a), len(b)) - slack
    return abs(len(a) - len(b)) <= slack and n > 0 and a[-n:] == b[-n:]


def tail_difference(a: list, b: list, slack: int = TAIL_SLACK) -> str:
    """Where two sample lists, aligned at their ends, first differ (for a failing ``same_tail``)."""
    n = max(min(len(a), len(b)) - slack, 0)
    ta, tb = a[-n:] if n else [], b[-n:] if n else []
    i = next((k for k in range(n) if ta[k] != tb[k]), n)
    return f"lengths {len(a)} and {len(b)}; first difference {n - i} from the end: {ta[i:i + 3]} vs {tb[i:i + 3]}"


def headings(rows: np.ndarray, n: int) -> np.ndarray:
    return rows[-n:, COL["heading_deg"]]


def alarm_rows_before_end(out: dict) -> list[int]:
    """Where each alarm starts, as the number of IMU rows from it to the end of the record.

    Live times count from the hub's connection, and four hubs on two cores connect up to seconds
    apart (CI: the same alarm at 26.49 s and 28.74 s, both 0.16 s after the step): the samples,
    counted from the same last one, are what the hubs share."""
    t = out["rows"][:, COL["t_s"]]
    return [len(t) - int(np.searchsorted(t, a["start_s"])) for a in out["alarms"]]


def alarms_in_the_step(out: dict) -> list[dict]:
    """The alarms that start while vehicle 1's step is on (from 2 s of flight before it), placed
    by IMU rows from the end of the record (the streams end together; live times count from each
    hub's connection and stretch where a hub falls behind)."""
    on_rows, off_rows = (SIM_S - STEP_ON_S + 2.0) * IMU_HZ, (SIM_S - STEP_ON_S - STEP_LONG_S) * IMU_HZ
    return [a for a, rows in zip(out["alarms"], alarm_rows_before_end(out)) if off_rows <= rows <= on_rows]


def assert_same_outputs(mixed: dict, alone: dict) -> None:
    got, want = sensor_values(mixed["samples"]), sensor_values(alone["samples"])
    assert same_tail(got, want), tail_difference(got, want)     # all, only the vehicle's
    # the same IMU sample starts the step's alarm, within 0.2 s of data (100 Hz) of arrival-time
    # jitter. Only the first: whether a long alarm ends and starts again inside the step turns on
    # GPS arrival times, which jitter by milliseconds on a loaded machine (CI: the second alarm of
    # the step 3.2 s before the end in one hub, 11.1 s in the other, the first at the same sample)
    first_mixed, first_alone = alarm_rows_before_end(mixed)[:1], alarm_rows_before_end(alone)[:1]
    assert first_mixed == pytest.approx(first_alone, abs=20)
    assert bool(alarms_in_the_step(mixed)) == bool(alarms_in_the_step(alone))
    n = min(len(mixed["rows"]), len(alone["rows"]))
    assert abs(len(mixed["rows"]) - len(alone["rows"])) <= 20
    # the same samples at (almost) the same times: GPS times are arrival times, which jitter by
    # milliseconds on a loaded machine, so the headings agree closely, not bit for bit (medians
    # 0.01-0.7 deg measured with four stations on 2 cores; the sample check above is the proof
    # that nothing of the other vehicle gets in).  Compared up to vehicle 1's step: inside it the
    # heading follows the alarm (held on the gyros while it is on), and where a long alarm ends
    # and starts again turns on that jitter (2026-12-07: one hub's heading 32 deg off the other's
    # over the step's last seconds, its alarm released there, the other's not)
    before_step = n - int((SIM_S - STEP_ON_S) * IMU_HZ)
    h1 = headings(mixed["rows"], n)[n // 5:before_step]
    h2 = headings(alone["rows"], n)[n // 5:before_step]
    ok = np.isfinite(h1) & np.isfinite(h2)
    diff = np.abs((h1[ok] - h2[ok] + 180.0) % 360.0 - 180.0)
    assert ok.mean() > 0.9 and np.median(diff) < 1.0 and np.percentile(diff, 99) < 5.0, \
        (np.median(diff), np.percentile(diff, 99))


def test_two_vehicles_each_followed_in_turn_equals_each_alone(tmp_path, sims):
    """Four hubs at once (same streams, same time): vehicle 1 alone, vehicle 2 alone, both on one
    link following 1 (serve --sysid 1), both on one link switched to 2 (chosen on the page)."""
    runs = {"alone1": LiveRun(tmp_path / "a1", sims, [1]), "alone2": LiveRun(tmp_path / "a2", sims, [2]),
            "mixed1": LiveRun(tmp_path / "m1", sims, [1, 2], follow=1),
            "mixed2": LiveRun(tmp_path / "m2", sims, [1, 2], follow=1, select=2)}
    for run in runs.values():
        run.connect()
    for run in runs.values():
        run.start()
    runs["mixed2"].choose()
    out = {name: run.finish() for name, run in runs.items()}
    assert abs(len(out["alone1"]["rows"]) - SIM_S * IMU_HZ) <= 5
    # the step alarms vehicle 1 only (vehicle 2's clean flight sped up twice ended in a marginal
    # alarm in its last second in 2 of 16 vehicle-2 hubs; analyze of that recording too: score 1.27)
    assert len(alarms_in_the_step(out["alone1"])) >= 1 and not alarms_in_the_step(out["alone2"])

    first = out["mixed1"]
    assert_same_outputs(first, out["alone1"])
    listed = {s["sysid"]: s for s in first["vehicles"]["systems"]}
    assert set(listed) == {1, 2} and first["vehicles"]["selected"] == 1
    for s in listed.values():
        assert s["kind"] == "vehicle" and s["autopilot"] == "ardupilot" and s["type"] == "quadrotor"
        assert s["packets"] > 1000 and s["loss_pct"] < 5.0
    recorded = read_log(first["recording"]).message_counts      # every vehicle's packets recorded
    assert recorded["SCALED_IMU"] == sum(1 for _, m in sims[1].messages + sims[2].messages
                                         if m.get_type() == "SCALED_IMU")

    second = out["mixed2"]                                       # switched to 2: a clean start
    assert second["vehicles"]["selected"] == 2
    assert not alarms_in_the_step(second)
    assert any("following vehicle 2" in e["text"] for e in second["snapshot"]["events"])
    # from the switch on vehicle 2's samples, none of vehicle 1
    alone2, got2 = sensor_values(out["alone2"]["samples"]), sensor_values(second["samples"])
    # (as multisets against what vehicle 2 sent this hub: a datagram lost by either hub on a loaded
    # machine must not shift the rest, nor count as a foreign sample)
    extra = Counter(got2) - Counter(sent_values(second["sent"][2], 2))
    assert len(got2) > 0.8 * len(alone2) and not extra, (len(got2), len(alone2), list(extra.items())[:5])
    n = min(len(second["rows"]), len(out["alone2"]["rows"]))    # the switched hub may hold a row more
    h, h2 = headings(second["rows"], n), headings(out["alone2"]["rows"], n)
    ok = np.isfinite(h) & np.isfinite(h2)
    late = ok & (np.arange(n) > n // 2)                          # after its own start-up
    assert np.median(np.abs((h[late] - h2[late] + 180.0) % 360.0 - 180.0)) < 0.5


def test_vehicles_api_lists_and_selects_behind_the_guard(tmp_path, sims):
    port = free_udp_port()
    hub = Session(tmp_path / "rec")
    client = TestClient(create_app(hub), base_url="http://127.0.0.1")
    assert client.post("/api/vehicles/select", json={"sysid": 1}).status_code == 409
    hub.connect(f"udpin:127.0.0.1:{port}")
    vehicles = [FakeVehicle(sims[k].messages, port, speed=2.0, system_id=k).start() for k in (1, 2)]
    try:
        assert wait_for(lambda: [s["kind"] for s in client.get("/api/vehicles").json()["systems"]] == ["vehicle"] * 2, 10)
        got = client.get("/api/vehicles").json()
        assert got["selected"] in (1, 2) and got["passive"] is False
        for system in got["systems"]:          # what the page's table shows, per system heard
            assert (system["type"], system["autopilot"]) == ("quadrotor", "ardupilot"), system
            assert 0 <= system["last_seen_s"] < 2.0 and system["rate_hz"] > 5, system
            assert system["packets"] > 0 and 0 <= system["loss_pct"] < 5, system
        pushed = hub.snapshot()["vehicles"]                       # what /ws pushes to the page
        assert [s["sysid"] for s in pushed["systems"]] == [1, 2] and pushed["selected"] == got["selected"]
        state = client.get("/api/state").json()["vehicles"]       # and the state's schema keeps it
        assert [s["sysid"] for s in state["systems"]] == [1, 2] and state["selected"] == got["selected"]
        assert client.post("/api/vehicles/select", json={"sysid": 7}).status_code == 404
        cross_site = client.post("/api/vehicles/select", json={"sysid": 2},
                                 headers={"Origin": "http://evil.example"})
        assert cross_site.status_code == 403 and hub.vehicles()["selected"] == got["selected"]
        other = 3 - got["selected"]
        r = client.post("/api/vehicles/select", json={"sysid": other})
        assert r.status_code == 200, r.text
        assert wait_for(lambda: client.get("/api/state").json().get("source", {}).get("kind") == "live"
                        and hub.snapshot()["vehicles"]["selected"] == other, 5)
    finally:
        for v in vehicles:
            v.stop()
        hub.close()
