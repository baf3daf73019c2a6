"""Browser tests: headless Debian chromium (Playwright) against a running station.

Screenshots go to tests/artifacts/ (gitignored)."""
from __future__ import annotations

import time

import httpx
import pytest

from conftest import free_udp_port
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate


def _console_errors(page) -> list[str]:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    return errors


def test_pages_load(station, page, artifacts):
    errors = _console_errors(page)
    page.goto(station.url + "/index.html")
    page.wait_for_selector("#status:has-text('no source')", timeout=10_000)
    assert page.locator("#alarm-banner").inner_text() == "No interference alarm"
    src = page.locator("#viewer").get_attribute("src")
    assert f":{station.viser_port}/" in src
    page.screenshot(path=str(artifacts / "index_empty.png"))
    page.goto(station.url + "/calibrate.html")
    page.wait_for_selector("#instruction:has-text('Press Start')", timeout=10_000)
    assert page.locator("#steps li").count() == 5
    page.screenshot(path=str(artifacts / "calibrate_empty.png"))
    assert errors == []


def test_wizard_with_fake_vehicle(station, page, artifacts):
    """Fake vehicle (simulator 'calibration' scenario as real MAVLink over UDP, x6) does the
    rotation dance; the page steps X -> Y -> Z -> tumble -> result; accept writes the params."""
    sim = simulate("calibration", 0)
    port = free_udp_port()
    with httpx.Client(base_url=station.url) as c:
        assert c.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}).status_code == 200
    errors = _console_errors(page)
    page.goto(station.url + "/calibrate.html")
    page.click("#start")
    page.wait_for_selector("#steps li[data-step='x'].current", timeout=5000)
    with FakeVehicle(sim.messages, port, speed=6.0) as fv:
        page.wait_for_selector("#steps li[data-step='x'].done", timeout=20_000)
        page.screenshot(path=str(artifacts / "calibrate_progress.png"))
        page.wait_for_selector("#result-card:not([hidden])", timeout=30_000)
        assert page.locator("#result-status").inner_text() == "ok"
        for step in "x", "y", "z", "tumble":
            assert "done" in page.locator(f"#steps li[data-step='{step}']").get_attribute("class")
        assert "WMM" not in page.locator("#warnings").inner_text()   # fitted field agrees with WMM
        page.wait_for_timeout(700)          # let the 3-D view draw the cloud and ellipsoid
        page.screenshot(path=str(artifacts / "calibrate_result.png"))
        page.click("#accept")
        page.wait_for_selector("#param-write .good", timeout=10_000)
        page.screenshot(path=str(artifacts / "calibrate_accepted.png"))
        result = httpx.get(station.url + "/api/calibration").json()["result"]
        exported = httpx.get(station.url + "/api/calibration/params?autopilot=px4")
        assert exported.status_code == 200 and "CAL_MAG0_XOFF" in exported.text
        for name, value in result["ardupilot_params"].items():
            assert abs(fv.params[name] - value) <= 1e-5 * max(1.0, abs(value)), name
    truth = sim.truth["mag"]["offsets_mG"]
    assert max(abs(a - b) for a, b in zip(result["offsets_mG"], truth)) < 5.0
    assert station.scene.cloud_points_shown > 500
    assert errors == []


@pytest.fixture
def interference_recording(recordings_dir):
    simulate("mission-slow", 0).write(recordings_dir / "mission-slow.tlog")
    return "mission-slow.tlog"


def test_replayed_interference_shows_alarm_and_red_route(station, page, artifacts, interference_recording):
    errors = _console_errors(page)
    page.goto(station.url + "/index.html")
    page.wait_for_selector(f"#recording option:has-text('{interference_recording}')", state="attached", timeout=5000)
    page.fill("#speed", "6")
    page.click("#replay")
    page.wait_for_selector("#alarm-banner.alarm", timeout=40_000)
    httpx.post(station.url + "/api/replay/pause", json={"paused": True})   # freeze while we look
    page.wait_for_selector("#pause:has-text('Resume')", timeout=10_000)
    assert httpx.get(station.url + "/api/state").json()["alarm"]["active"]
    page.wait_for_selector("#alarm-banner.alarm", timeout=10_000)
    banner = page.locator("#alarm-banner").inner_text()
    assert "ALARM" in banner
    # a mission log without a calibration dance: the page says the headings are uncorrected
    assert not httpx.get(station.url + "/api/state").json()["calibration_in_use"]
    assert page.locator("#v-cal").inner_text().startswith("none")
    deadline = time.monotonic() + 5
    while station.scene.red_segments == 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert station.scene.red_segments > 0
    page.wait_for_timeout(1500)
    page.screenshot(path=str(artifacts / "replay_alarm.png"))
    alarms = httpx.get(station.url + "/api/alarms").json()
    assert alarms and alarms[0]["start_s"] > 55      # onset ~59 s: no false alarm before it
    assert errors == []
