"""The calibration page in headless chromium against the fake vehicle (MAVLink over loopback UDP).

One station and one browser for the module; each test connects a fresh fake vehicle.  Screenshots
of every step at 1280x720 go to tests/artifacts/calibration/ (gitignored)."""
from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from browser_checks import set_value, wait_until
from conftest import CHROMIUM, CHROMIUM_ARGS, free_tcp_port, free_udp_port
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.vehicle_streams import (MORE_TILTS, ROTATION_ROLL_180, ROTATION_YAW_90, TILTS,
                                               attitude_from_moves, guided_dance_attitude, hold_attitude,
                                               make_hardware, pack_stream, three_compasses, walk_attitude)

SPEED = 4.0          # x real time; 35 deg/s turns arrive at 140 deg/s, under the 172 deg/s warning
WAIT_MS = 60_000     # generous: 2 cores shared with other test runs


def shown(page, selector: str, timeout_ms: float = WAIT_MS) -> None:
    """Wait until ``selector`` (Playwright syntax) is visible, polling from Python: Playwright's
    own waits poll on animation frames, which the software-rendered 3-D view can starve for
    seconds on a loaded machine (tests/browser_checks.py, ``wait_js``)."""
    if not wait_until(lambda: page.locator(selector).first.is_visible(), timeout_ms / 1000.0, 0.1):
        state = page.evaluate("[document.getElementById('status').textContent, (document.getElementById('hint')||{}).textContent, document.querySelector('#steps li.current') && document.querySelector('#steps li.current').dataset.step, document.getElementById('cal-error').textContent, document.querySelector('#modes input:checked').value, document.getElementById('start').textContent, !document.getElementById('discard-confirm').hidden]")
        station = page.evaluate("""fetch("/api/state").then(r => r.json()).then(s => [s.wizard.state, s.wizard.mode, s.wizard.step,
          s.source.name, s.source.pending, s.events.slice(-14).map(e => e.text || e.message || JSON.stringify(e))])""")
        raise AssertionError(f"{selector} not shown; page: {state}; station: {station}; errors: {getattr(page, 'errors', None)}")


def press(page, selector: str) -> None:
    """Click once the element is shown, without animation-frame actionability checks."""
    shown(page, selector)
    page.locator(selector).first.dispatch_event("click")


def set_checked(page, selector: str, checked: bool) -> None:
    shown(page, selector)
    box = page.locator(selector).first
    if box.is_checked() != checked:
        box.dispatch_event("click")


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    from groundstation.station.app import Station
    st = Station(port=0, viser_port=free_tcp_port(), recordings_dir=tmp_path_factory.mktemp("rec"),
                 record_live=False).start()
    yield st
    st.close()


@pytest.fixture(scope="module")
def browser(playwright_instance, station):
    args = CHROMIUM_ARGS + [f"--isolate-origins=http://127.0.0.1:{station.viser_port}"]
    b = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
    yield b
    b.close()


def _page(browser, station, view: bool):
    """A 1280x720 page; without ``view`` the 3-D view's server is not reached: its software WebGL
    took 0.8 of a core while a dance streamed (tests that do not look at the view leave it out)."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 720})
    if not view:
        ctx.route(f"http://127.0.0.1:{station.viser_port}/**", lambda route: route.abort())
    pg = ctx.new_page()
    # screenshots wait for a compositor frame, which the software-rendered 3-D view can starve for
    # over 30 s (Playwright's default) while the other worker runs four live hubs (CI, 2 cores)
    pg.set_default_timeout(WAIT_MS * 2)
    pg.errors = []
    pg.on("console", lambda m: pg.errors.append(m.text) if m.type == "error" else None)
    pg.on("pageerror", lambda e: pg.errors.append(str(e)))
    return pg


@pytest.fixture
def page(browser, station):
    pg = _page(browser, station, view=False)
    yield pg
    pg.context.close()


@pytest.fixture
def view_page(browser, station):
    """A page with the 3-D view (the result's cloud and ellipsoid are screenshotted)."""
    pg = _page(browser, station, view=True)
    yield pg
    pg.context.close()


@pytest.fixture(scope="module")
def shots(artifacts):
    d = artifacts / "calibration"
    d.mkdir(exist_ok=True)
    return d


@pytest.fixture
def api(station):
    with httpx.Client(base_url=station.url, timeout=10) as c:
        c.post("/api/calibration/reset")
        yield c


def connect(api) -> int:
    port = free_udp_port()
    assert api.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}).status_code == 200
    return port


def wizard(api) -> dict:
    return api.get("/api/calibration").json()


def wait_api(api, cond, timeout_s=60.0, step_s=0.1) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        w = wizard(api)
        if cond(w):
            return w
        time.sleep(step_s)
    raise AssertionError(f"timed out; wizard: state {w['state']} step {w['step']} {w['instruction']}")


def open_page(page, station):
    page.goto(station.url + "/calibrate.html")
    shown(page, "#status:not(:has-text('connecting'))", 10_000)


def in_view(page, selector) -> bool:
    """The element lies inside the 1280x720 viewport (the page re-renders it on every push, so
    it is measured in one script call)."""
    box = page.evaluate("(s) => { const e = document.querySelector(s); if (!e) return null;"
                        " const r = e.getBoundingClientRect(); return [r.top, r.bottom, r.height]; }", selector)
    return box is not None and box[2] > 0 and box[0] >= 0 and box[1] <= 720


def sent_after(msgs, t_rel_s) -> int:
    """Index of the first message at or after ``t_rel_s`` of the stream."""
    t0 = msgs[0][0]
    return next(i for i, (u, _) in enumerate(msgs) if u - t0 >= t_rel_s)


# ------------------------------------------------------------------ defect 1
def test_steps_fill_only_with_their_own_axis(station, page, api, shots):
    """Wobbling about Y and Z leaves step X empty; held still the page says so; a turn about X fills it."""
    wobble = [("body", a, d, 50.0) for a in (1, 2) for d in (40.0, -80.0, 40.0)] * 2
    moves = [("still", 2.0)] + wobble + [("still", 12.0), ("body", 0, 370.0, 35.0), ("still", 3.0)]
    hist = attitude_from_moves(moves, 25.0)
    msgs = pack_stream(hist, make_hardware(three_compasses()))
    t_wobble_end = 2.0 + sum(abs(m[2]) / m[3] for m in wobble)
    port = connect(api)
    open_page(page, station)
    press(page, "#start")
    fv = FakeVehicle(msgs, port, speed=3.0)
    # held still (heartbeats go on, the last attitude stays the station's) from 10 s after the wobble
    # (the hint needs 2 s of stillness as the station receives it: 6 s of the stream at x3) until
    # the page has shown the hint, instead of a minute of stillness waited out
    fv.hold_before = sent_after(msgs, t_wobble_end + 10.0)
    with fv:
        while fv.sent < sent_after(msgs, t_wobble_end + 0.3):
            time.sleep(0.05)
        w = wizard(api)
        assert w["step"] == "x" and w["progress_deg"]["x"] < 5.0, w["progress_deg"]
        assert w["progress_deg"]["y"] == 0.0 and w["progress_deg"]["z"] == 0.0
        w = wait_api(api, lambda w: w["hint"] is not None)
        assert w["hint"].startswith("No motion") and w["step"] == "x" and w["progress_deg"]["x"] < 5.0
        shown(page, "#hint:has-text('No motion')", WAIT_MS)
        page.screenshot(path=str(shots / "01_steps_still_after_wobble.png"))
        assert wizard(api)["step"] == "x"
        fv.release()                                 # the turn about X
        shown(page, "#steps li[data-step='y'].current", WAIT_MS)
        assert "full turn" in page.locator("#steps li[data-step='x'] .deg").inner_text()
        page.screenshot(path=str(shots / "02_steps_x_done.png"))
    assert wizard(api)["progress_deg"]["x"] >= 345.0
    assert page.errors == []


# ------------------------------------------------------------------ defect 2
def test_link_drop_pauses_and_resumes_the_step(station, page, api, shots):
    # the still stretch spans the drop, the banner and the return on a loaded machine; the second Y
    # turn is long enough to finish the step whatever part of it falls in the gap
    moves = [("still", 2.0), ("body", 0, 370.0, 35.0), ("still", 1.0), ("body", 1, 200.0, 35.0), ("still", 4.0),
             ("body", 1, 400.0, 35.0), ("still", 3.0)]
    msgs = pack_stream(attitude_from_moves(moves, 25.0), make_hardware(three_compasses()))
    t_still = 2.0 + 370 / 35 + 1.0 + 200 / 35
    port = connect(api)
    open_page(page, station)
    # started while its link connects, the wizard waits for that vehicle: no step is current yet
    page.wait_for_function("last !== null")
    assert page.evaluate("""(() => { renderSteps({...last.wizard, state: 'running', step: 'x', waiting_for: 'udpin:x'});
      const n = document.querySelectorAll('#steps li.current').length; renderSteps(last.wizard); return n; })()""") == 0
    press(page, "#start")
    fv = FakeVehicle(msgs, port, speed=SPEED)
    fv.hold_before = sent_after(msgs, t_still + 0.5)   # held still over the drop, until the banner says it resumes
    with fv:
        while fv.sent < fv.hold_before:
            time.sleep(0.05)
        fv.set_link(False)
        shown(page, "#banner:has-text('Link lost during step Y')", WAIT_MS)
        assert "paused" in page.locator("#instruction").inner_text()
        assert "paused" in page.locator("#steps li[data-step='y']").get_attribute("class")
        y_before = wizard(api)["progress_deg"]["y"]
        assert 150.0 < y_before < 345.0
        page.screenshot(path=str(shots / "03_link_lost_paused.png"))
        fv.set_link(True)
        shown(page, "#banner:has-text('resumes')", WAIT_MS)
        assert wizard(api)["progress_deg"]["y"] >= y_before - 2.0       # resumed, not restarted
        page.screenshot(path=str(shots / "04_link_back_resumed.png"))
        fv.release()                                                    # the rest of the Y turn
        shown(page, "#steps li[data-step='z'].current", WAIT_MS)
    events = [e["text"] for e in api.get("/api/state").json()["events"]]
    assert any("paused: link lost during step Y" in t for t in events)
    assert page.errors == []


# ------------------------------------------------------------------ the full guided flow
def test_three_compasses_orientation_write_reboot_and_heading_check(station, view_page, api, shots, browser):
    """Compasses mounted at YAW_90 and ROLL_180 (COMPASS_ORIENT still 0): a clean dance gives no
    field warning, three passing compasses with their orientation, written and confirmed; reboot
    (confirmed), then the heading check at a known bearing and the deviation card."""
    page = view_page
    hw = make_hardware(three_compasses((ROTATION_YAW_90, ROTATION_ROLL_180, 0)))
    msgs = pack_stream(guided_dance_attitude(), hw)
    after = pack_stream(hold_attitude(135.0, 120.0, rate_hz=25.0), hw, start_unix=msgs[-1][0] + 60, boot_offset_s=4.0)
    port = connect(api)
    open_page(page, station)
    press(page, "#start")
    warnings: set[str] = set()
    with FakeVehicle(msgs, port, speed=SPEED, after_reboot=after, reboot_silence_s=4.0) as fv:
        # step X done (a loaded machine may already be past step Y when the page is polled, or, at
        # load 20, at the result, when the steps are no longer shown)
        assert wait_until(lambda: page.locator("#steps li[data-step='x'].done").first.is_visible()
                          or page.locator("#result-card:not([hidden])").first.is_visible(), WAIT_MS / 1000, 0.1)
        page.screenshot(path=str(shots / "05_guided_step_y.png"))
        w = wait_api(api, lambda w: warnings.update(w["warnings"]) or (w["step"] == "tumble" and w["next_pose"])
                     or w["state"] != "running")
        if w["state"] == "running":            # (a loaded machine may have passed the tumble already)
            assert w["instruction"].startswith("Cover the rest of the sphere: " + w["next_pose"]["text"])
            shown(page, "#instruction:has-text('Cover the rest of the sphere')", WAIT_MS)
            page.screenshot(path=str(shots / "06_guided_tumble_next_pose.png"))
        w = wait_api(api, lambda w: warnings.update(w["warnings"]) or w["state"] == "result")
        assert not [x for x in warnings if "WMM" in x or "isturbance" in x], warnings
        shown(page, "#result-card:not([hidden])", WAIT_MS)
        page.wait_for_timeout(800)          # the 3-D view draws the cloud and ellipsoid
        page.screenshot(path=str(shots / "07_guided_result.png"))
        comps = {c["index"]: c["result"] for c in w["compasses"]}
        assert all(comps[k]["pass"] for k in range(3))
        assert [comps[k]["orientation"]["detected_name"] for k in range(3)] == ["YAW_90", "ROLL_180", "NONE"]
        assert w["consistency"]["status"] == "ok"
        assert page.locator("#compass-table").inner_text().count("pass") == 3

        set_checked(page, "#compass-table input[data-compass='2']", False)      # leave compass 3 out ...
        wait_api(api, lambda w: "COMPASS_OFS3_X" not in w["result"]["ardupilot_params"])
        shown(page, "#compass-table tr.left-out", WAIT_MS)
        page.screenshot(path=str(shots / "07b_compass_3_left_out.png"))
        set_checked(page, "#compass-table input[data-compass='2']", True)        # ... and back in
        wait_api(api, lambda w: "COMPASS_OFS3_X" in w["result"]["ardupilot_params"])

        press(page, "#accept")
        shown(page, "#param-write .good", WAIT_MS)
        page.screenshot(path=str(shots / "08_written.png"))
        assert in_view(page, "#param-write .good")             # success line without scrolling
        assert "Reboot" in page.locator("#instruction").inner_text()
        params = wizard(api)["result"]["ardupilot_params"]
        assert params["COMPASS_ORIENT"] == 2 and params["COMPASS_ORIENT2"] == 8
        for name, value in params.items():
            assert abs(fv.params[name] - value) <= 1e-4 * max(1.0, abs(value)), name
        station_page = browser.new_page()
        station_page.goto(station.url + "/index.html")
        shown(station_page, "#v-cal:has-text('autopilot-corrected')", 10_000)   # the vehicle corrects it now
        station_page.close()

        press(page, "#reboot")
        shown(page, "#reboot-confirm:not([hidden])", 5000)
        page.screenshot(path=str(shots / "09_reboot_confirm.png"))
        press(page, "#reboot-yes")
        shown(page, "#instruction:has-text('Rebooting')", WAIT_MS)
        page.screenshot(path=str(shots / "10_rebooting.png"))
        shown(page, "#instruction:has-text('is back')", WAIT_MS)
        assert fv.reboots == 1
        set_value(page, "#hc-bearing", "135")
        press(page, "#hc-measure")
        shown(page, "#hc-result .good", WAIT_MS)
        page.wait_for_timeout(300)
        page.screenshot(path=str(shots / "11_heading_check.png"))
        check = wizard(api)["heading_check"]["result"]
        assert abs(check["error_deg"]) < 2.0, check
        dev = wizard(api)["deviation"]
        assert dev["max_before_deg"] > 10.0 and dev["max_after_deg"] < 2.0
        page.locator("#deviation-card").scroll_into_view_if_needed()
        page.screenshot(path=str(shots / "12_deviation_card.png"))
    assert page.errors == []


# ------------------------------------------------------------------ onboard calibration
def test_onboard_calibrator_beside_ours(station, page, api, shots):
    hw = make_hardware(three_compasses())
    dance = hold_attitude(30.0, 4.0, rate_hz=25.0, wobble_deg=0.0).then(guided_dance_attitude(tilts=TILTS + MORE_TILTS))
    msgs = pack_stream(dance, hw)
    port = connect(api)
    open_page(page, station)
    set_checked(page, "#modes input[value='onboard']", True)
    fv = FakeVehicle(msgs, port, speed=SPEED)
    fv.hold_before = sent_after(msgs, 3.0)         # held still until the vehicle's calibrator has started
    with fv:
        while api.get("/api/state").json()["source"]["link"] != "up":      # the command needs the link
            time.sleep(0.05)
        press(page, "#start")
        shown(page, "#onboard-card:not([hidden])", WAIT_MS)
        assert wait_until(lambda: any(c[0] == 42424 for c in fv.commands), WAIT_MS / 1000)   # DO_START_MAG_CAL
        fv.release()
        wait_api(api, lambda w: w["onboard"]["compasses"] and w["onboard"]["compasses"][0].get("completion_pct", 0) > 40)
        page.wait_for_timeout(500)
        page.screenshot(path=str(shots / "13_onboard_running.png"))
        w = wait_api(api, lambda w: w["state"] == "result", timeout_s=120)
        shown(page, "#ob-accept:not([disabled])", WAIT_MS)
        page.screenshot(path=str(shots / "14_onboard_reported.png"))
        ours = {c["index"]: (c["result"] or {}).get("status") for c in w["compasses"]}
        why = ([((c2["result"] or {}).get("message"), (c2["result"] or {}).get("reasons")) for c2 in w["compasses"]],
               w["samples"], w["coverage"])
        # our fit of a compass once ended 'error' here under load: Start had landed while the link
        # was switching over, and the wizard un-applied the previous vehicle's COMPASS_DIA2
        assert all(s == "ok" for s in ours.values()) and len(ours) == 3, (ours, why)
        for c in w["onboard"]["compasses"]:
            assert c["report"] and c["report"]["success"], c
            assert c["compare"]["max_offset_difference_mG"] < 5.0, (c["compare"], why)
            assert len(c["sections"]) > 40                      # the completion mask arrived
        report0 = w["onboard"]["compasses"][0]["report"]
        press(page, "#ob-accept")
        shown(page, "#param-write .good", WAIT_MS)
        page.screenshot(path=str(shots / "15_onboard_accepted.png"))
        np.testing.assert_allclose([fv.params[f"COMPASS_OFS_{a}"] for a in "XYZ"], report0["ofs_mG"], atol=0.1)
        np.testing.assert_allclose(report0["ofs_mG"], -hw.compasses[0].offsets_mG, atol=3.0)
    assert any(c[0] == 42424 for c in fv.commands) and any(c[0] == 42425 for c in fv.commands)
    assert page.errors == []


# ------------------------------------------------------------------ large vehicle
def test_large_vehicle_fixed_yaw_with_gps_course_and_entered_heading(station, page, api, shots):
    """Walk the vehicle straight (GPS course), calibrate with that course, check against the WMM;
    then again with the heading entered by hand."""
    hw = make_hardware(three_compasses())
    hist = (hold_attitude(75.0, 16.0, rate_hz=25.0).then(walk_attitude(75.0, 24.0, rate_hz=25.0))
            .then(hold_attitude(75.0, 160.0, rate_hz=25.0)))
    msgs = pack_stream(hist, hw)
    port = connect(api)
    open_page(page, station)
    set_checked(page, "#modes input[value='fixed_yaw']", True)
    press(page, "#start")
    shown(page, "#fixed-card:not([hidden])", 20_000)   # 5 s ran out at load 11 (two suites at once)
    fv = FakeVehicle(msgs, port, speed=3.0)
    fv.hold_before = sent_after(msgs, 15.0)         # standing at the start of the line until the walk starts
    with fv:
        shown(page, "#status:has-text('link up')", WAIT_MS)
        while fv.sent < fv.hold_before:
            time.sleep(0.05)
        press(page, "#fy-walk")
        shown(page, "#fy-walk-text:has-text('walking')", WAIT_MS)
        fv.release()
        wait_api(api, lambda w: w["heading_check"]["distance_m"] > 12.0)
        page.screenshot(path=str(shots / "16_large_vehicle_walking.png"))
        press(page, "#fy-walk-stop")
        shown(page, "#fy-walk-text:has-text('GPS course')", WAIT_MS)
        course = wizard(api)["heading_check"]["result"]["reference_deg"]
        assert course == pytest.approx(75.0, abs=1.0)
        while fv.sent < sent_after(msgs, 41.0):     # standing still at the end of the walk
            time.sleep(0.05)
        press(page, "#fy-gps")
        w = wait_api(api, lambda w: w["fixed_yaw"] and w["fixed_yaw"]["state"] == "done")
        shown(page, "#fy-table:has-text('Check against the WMM')", WAIT_MS)
        page.screenshot(path=str(shots / "17_large_vehicle_gps_course.png"))
        fy = w["fixed_yaw"]
        assert fy["check"]["ok"] and abs(fy["check"]["heading_error_deg"]) < 2.0
        assert abs(fy["check"]["strength_mG"] - fy["check"]["wmm_strength_mG"]) < 15.0
        np.testing.assert_allclose(fy["vehicle_ofs_mG"]["0"], fy["ours_ofs_mG"]["0"], atol=5.0)
        set_value(page, "#fy-yaw", "75")
        press(page, "#fy-send")
        w = wait_api(api, lambda w: w["fixed_yaw"]["source"] == "entered" and w["fixed_yaw"]["state"] == "done")
        assert abs(w["fixed_yaw"]["check"]["heading_error_deg"]) < 2.0
        assert "calibration in use: the vehicle's" in page.locator("#status").inner_text()
        page.screenshot(path=str(shots / "18_large_vehicle_entered.png"))
    assert page.errors == []


# ------------------------------------------------------------------ write failures and PX4
def test_write_failures_shown_then_px4_write(station, page, api, shots):
    """No echo, then a wrong echo, each named on the page; the same result written to a PX4 vehicle."""
    hw = make_hardware(three_compasses())
    msgs = pack_stream(guided_dance_attitude(rate_deg_s=35.0, rate_hz=12.5), hw)
    hold = pack_stream(hold_attitude(10.0, 200.0, rate_hz=10.0), hw)
    port = connect(api)
    open_page(page, station)
    press(page, "#start")
    with FakeVehicle(msgs, port, speed=8.0, param_mode="ignore") as fv:
        wait_api(api, lambda w: w["state"] == "result", timeout_s=90)
        press(page, "#accept")
        shown(page, "#param-write .error", WAIT_MS)
        assert "no answer from the vehicle" in page.locator("#param-write").inner_text()
        page.screenshot(path=str(shots / "19_write_failed_no_echo.png"))
        assert in_view(page, "#param-write .error")
        assert fv.params["COMPASS_OFS_X"] == 0.0
    port = connect(api)
    with FakeVehicle(hold, port, speed=1.0, param_mode="corrupt") as fv:
        shown(page, "#status:has-text('link up')", WAIT_MS)
        press(page, "#accept")                      # "Retry the write"
        shown(page, "#param-write li:has-text('kept')", WAIT_MS)
        assert "other values" in page.locator("#param-write").inner_text()
        page.screenshot(path=str(shots / "20_write_failed_wrong_value.png"))
    port = connect(api)
    with FakeVehicle(hold, port, speed=1.0, autopilot="px4") as fv:
        shown(page, "#status:has-text('px4')", WAIT_MS)
        wait_api(api, lambda w: (w["result"] or {}).get("status") == "ok", timeout_s=30)   # kept for this link
        press(page, "#accept")
        shown(page, "#param-write .good", WAIT_MS)
        page.screenshot(path=str(shots / "21_px4_written.png"))
        px4 = wizard(api)["result"]["px4_params"]
        assert {f"CAL_MAG{k}_XOFF" for k in range(3)} <= set(px4)
        for name, value in px4.items():
            assert abs(fv.params[name] - value) <= 1e-5 * max(1.0, abs(value)), name
        for k, c in enumerate(hw.compasses):
            np.testing.assert_allclose([fv.params[f"CAL_MAG{k}_{a}OFF"] for a in "XYZ"], c.offsets_mG / 1000, atol=0.003)
    assert page.errors == []
