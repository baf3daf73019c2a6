"""The pages as a new user meets them (issue 31): the station page (heading plot, the 3-D view of a
replayed dance and of a flight, the recordings table, the preset line), the wizard driven by the
demo's replayed dance, and the wizard against a fake vehicle with three compasses (heading check
far off, mode choice after a run, Reset asking, labels, one primary action, the Compasses card).

Headless Debian chromium at 1280x720 (and 1920x1080 where the layout is the question); replays
run at high speed.  Screenshots go to tests/artifacts/pages/ (gitignored)."""
from __future__ import annotations

import math
import shutil
import subprocess
import time
from types import SimpleNamespace

import httpx
import numpy as np
import pytest

from browser_checks import (ROOT, dismiss_webgl_notice, label_boxes, launch_browser, overlaps, project,
                            set_value, view_pixels_until, wait_js)
from conftest import free_tcp_port, free_udp_port, wait_until

UPLOAD_NAME = "upload-20260101-101010-a_very_long_field_log_name_from_the_trial.tlog"
SIZES = ((1280, 720), (1920, 1080))


# ------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def station(tmp_path_factory):
    from groundstation.station.app import Station
    d = tmp_path_factory.mktemp("pages") / "recordings"
    d.mkdir()
    shutil.copy(ROOT / "recordings" / "demo.tlog", d / "demo.tlog")
    shutil.copy(ROOT / "recordings" / "mission-clean.tlog", d / "mission-clean.tlog")   # the longest bundled name
    shutil.copy(ROOT / "recordings" / "mission-fast.tlog", d / UPLOAD_NAME)
    st = Station(port=0, viser_port=free_tcp_port(), recordings_dir=d, record_live=False).start()
    yield st
    st.close()


@pytest.fixture(scope="module")
def browser(playwright_instance, station):
    b = launch_browser(playwright_instance, station.viser_port)
    yield b
    b.close()


@pytest.fixture
def new_page(browser, station):
    contexts = []

    def make(width: int = 1280, height: int = 720, view: bool = False):
        ctx = browser.new_context(viewport={"width": width, "height": height})
        if not view:       # software WebGL costs a core: only the tests that look at the view load it
            ctx.route(f"http://127.0.0.1:{station.viser_port}/**", lambda route: route.abort())
        contexts.append(ctx)
        page = ctx.new_page()
        page.errors = []
        page.on("pageerror", lambda e: page.errors.append(str(e)))
        page.set_default_timeout(45_000)
        return page

    yield make
    for ctx in contexts:
        ctx.close()


@pytest.fixture(scope="module")
def shots(artifacts):
    d = artifacts / "pages"
    d.mkdir(exist_ok=True)
    return d


@pytest.fixture
def http(station):
    with httpx.Client(base_url=station.url, timeout=30) as c:
        c.post("/api/calibration/reset")
        yield c
        c.post("/api/calibration/reset")


def ok(r: httpx.Response):
    assert r.status_code < 400, (r.request.url, r.status_code, r.text)
    return r.json() if r.content else None


def open_page(page, station, path: str, view: bool = False) -> None:
    page.goto(station.url + path)
    wait_js(page, "!document.getElementById('status').textContent.includes('connecting')")
    if view:
        wait_js(page, "document.getElementById('viewer').getAttribute('src')")
        src = page.locator("#viewer").get_attribute("src").split("/?")[0].rstrip("/")
        for _ in range(240):          # Playwright learns of the frame only while it is called
            if any(f.url.startswith(src) for f in page.frames):
                break
            page.wait_for_timeout(250)
        dismiss_webgl_notice(page)


def replay_demo(http, speed: float, seek: float | None = None, paused: bool = False) -> None:
    ok(http.post("/api/replay/start", json={"recording": "demo.tlog", "speed": speed}))
    assert wait_until(lambda: not ok(http.get("/api/state"))["analysing"], 90)
    if paused:
        ok(http.post("/api/replay/pause", json={"paused": True}))
    if seek is not None:
        ok(http.post("/api/replay/seek", json={"t_s": seek}))


# ------------------------------------------------------------------------------ station page
def test_heading_plot_does_not_jump_to_a_0_360_axis(station, new_page, http, shots):
    """At 190 s of the demo the GPS course turns through north (350° beside headings of 30°):
    the headings are unwrapped, so the axis spans their own range (well under 180°), its labels
    read mod 360, and no value is drawn twice across the wrap."""
    page = new_page()
    replay_demo(http, 1.0, seek=190.0, paused=True)
    open_page(page, station, "/index.html")
    wait_js(page, "document.getElementById('plot-heading').dataset.yrange && "
                  "document.getElementById('replay-time').textContent.startsWith('190.0')")
    time.sleep(1.0)          # the plots redraw every 0.5 s
    lo, hi = map(float, page.locator("#plot-heading").get_attribute("data-yrange").split())
    assert hi - lo < 180, (lo, hi)
    labels = page.locator("#plot-heading").get_attribute("data-yticks").split()
    assert all(0 <= float(x) < 360 for x in labels), labels
    # the course crossing 360 -> 0 stays beside the 30° headings instead of jumping to the far edge
    out = page.evaluate("""unwrapHeadings([{y: [30, 31, 32, null]}, {y: [355, 359, 2, 6]}]).map(s => s.y)""")
    assert out == [[30, 31, 32, None], [-5, -1, 2, 6]], out
    page.screenshot(path=str(shots / "station_heading_190s.png"))
    assert page.errors == []


def test_recordings_table_and_preset_line_fit(station, new_page, http, shots):
    """At both sizes every column of the recordings table fits (the 'mag' heading too), an upload
    reads by its own name (the stored name in its tooltip) and the preset line's four inputs sit
    on one row."""
    for w, h in SIZES:
        page = new_page(w, h)
        open_page(page, station, "/index.html")
        wait_js(page, "document.querySelectorAll('#recordings tr[data-name]').length >= 2")
        fit = page.evaluate("""() => {
          const box = document.querySelector('.recordings'), t = document.getElementById('recordings');
          const cut = [...t.querySelectorAll('th')].filter(c => c.scrollWidth > c.clientWidth).map(c => c.textContent);
          const cutCells = [...t.querySelectorAll('tr[data-name] td')].filter(c => c.cellIndex > 0 && c.scrollWidth > c.clientWidth)
            .map(c => c.textContent);
          const names = [...t.querySelectorAll('tr[data-name]:not([data-name^="upload-"]) td:first-child')].map(c => c.textContent);
          const cutNames = [...t.querySelectorAll('tr[data-name]:not([data-name^="upload-"]) td:first-child')]
            .filter(c => c.scrollWidth > c.clientWidth).map(c => c.textContent);
          const tops = ['a-lat', 'a-lon', 'b-lat', 'b-lon'].map(id => document.getElementById(id).getBoundingClientRect().top);
          const up = t.querySelector('tr[data-name^="upload-"]');
          const choice = document.getElementById('cal-choice').getBoundingClientRect().right,
                card = document.getElementById('cal-card').getBoundingClientRect().right;
          return {overflow: t.scrollWidth - box.clientWidth, cut, cutCells, names, cutNames, tops, choice, card,
                  upload: up.cells[0].textContent, title: up.title};
        }""")
        assert fit["overflow"] <= 0, fit
        assert fit["cut"] == [] and fit["cutCells"] == [] and fit["cutNames"] == [], fit   # the bundled names whole
        assert max(fit["tops"]) - min(fit["tops"]) < 1, fit
        assert fit["choice"] <= fit["card"], fit                  # the calibration chooser stays in its card
        assert fit["upload"].startswith("↑ a_very_long_field_log"), fit
        assert UPLOAD_NAME in fit["title"], fit
        page.screenshot(path=str(shots / f"station_source_{w}.png"), clip={"x": 0, "y": 0, "width": 460, "height": h})


def test_uploads_are_git_ignored():
    """Logs uploaded through the page land in recordings/ as upload-*: git ignores them, not the
    bundled demo files."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    ignored = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", "recordings/" + UPLOAD_NAME])
    assert ignored.returncode == 0
    for bundled in ("recordings/demo.tlog", "recordings/demo.truth.json", "recordings/mission-fast.tlog"):
        assert subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", bundled]).returncode == 1, bundled


def test_replayed_dance_shows_its_cloud_and_the_flight_a_small_vehicle(station, new_page, http, shots):
    """While the demo's calibration dance replays (wizard idle), the station's 3-D view shows the
    dance's raw field cloud (blue) and fitted ellipsoid (amber) instead of the route; once the
    flight plays, the route again, with a vehicle model small beside it (full size it hid a fifth
    of the route)."""
    page = new_page(view=True)
    open_page(page, station, "/index.html", view=True)
    replay_demo(http, 4.0, seek=2.0)
    assert wait_until(lambda: ok(http.get("/api/state"))["replay"]["t_s"] >= 16.0, 60, 0.2)     # the X turn done
    assert station.scene.activity == "calibration" and station.scene.cloud_points_shown > 200, \
        (station.scene.activity, station.scene.cloud_points_shown)
    ok(http.post("/api/replay/pause", json={"paused": True}))      # the dance stays on the screen
    assert wait_until(lambda: station.scene.activity == "calibration", 5)
    assert ok(http.get("/api/calibration"))["state"] == "idle"
    png, px = view_pixels_until(page, {"blue": 300, "amber": 300})
    (shots / "station_dance_cloud.png").write_bytes(png)
    assert px["blue"][0] >= 300 and px["amber"][0] >= 300, px
    ok(http.post("/api/replay/seek", json={"t_s": 175.0}))
    ok(http.post("/api/replay/pause", json={"paused": True}))
    assert wait_until(lambda: station.scene.activity == "flight", 30)
    png, px = view_pixels_until(page, {"violet": 150, "red": 150, "orange": 20})
    (shots / "station_flight_vehicle.png").write_bytes(png)
    route = px["violet"][0] + px["red"][0]
    assert 20 <= px["orange"][0] < 0.5 * route, px


# ------------------------------------------------------------------------------ wizard on a replayed dance
def test_replayed_dance_drives_the_wizard_step_by_step(station, new_page, http, shots):
    """Start pressed while the demo replays its tumble (50 s): the replay goes back to the start,
    so the recorded dance meets the steps in order, like a vehicle turned by hand: step 1's
    counter only grows during its X turn, each step fills and the fit ends 'ok'.  The two
    coverage measures say what they count."""
    page = new_page()
    replay_demo(http, 20.0, seek=50.0)
    open_page(page, station, "/calibrate.html")
    steps: set = set()              # every step the wizard was in, seen at each change of the hub
    hub = station.session            # (at x20 the tumble lasts about a second: polling can miss it)
    watch = lambda: steps.add(hub.calibration.wizard.step)  # noqa: E731
    hub.add_listener(watch)
    page.locator("#start").dispatch_event("click")
    assert wait_until(lambda: ok(http.get("/api/calibration"))["state"] == "running", 20)
    seen_x, rewound = [], False
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        s = ok(http.get("/api/state"))
        w = s["wizard"]
        rewound = rewound or s["replay"]["t_s"] < 30.0
        steps.add(w["step"])
        if w["step"] == "x":
            seen_x.append(w["progress_deg"]["x"])
            if len(seen_x) == 3:
                page.screenshot(path=str(shots / "wizard_replay_step_x.png"))
        if w["step"] == "tumble" and "tumble" not in steps - {w["step"]}:
            page.screenshot(path=str(shots / "wizard_replay_tumble.png"))
        if w["state"] != "running":
            break
        time.sleep(0.1)
    hub.remove_listener(watch)
    assert rewound
    assert {"x", "y", "z", "tumble"} <= steps, steps
    assert w["state"] == "result" and w["result"]["status"] == "ok", (w["state"], w["result"])
    assert all(b >= a - 3.0 for a, b in zip(seen_x, seen_x[1:])), seen_x
    assert all(w["progress_deg"][a] >= 345.0 for a in "xyz"), w["progress_deg"]
    wait_js(page, "!document.getElementById('result-card').hidden")
    steps_text = page.locator("#steps li[data-step='tumble'] .deg").inner_text()
    assert steps_text.startswith("sphere ") and "the step needs 60 %" in steps_text, steps_text
    assert "from the attitude" in page.locator("#coverage-text").inner_text()
    assert "Own coverage" in page.locator("#result-table").inner_text()
    page.screenshot(path=str(shots / "wizard_replay_result.png"))
    assert page.errors == []


def test_step_counts_only_turns_about_its_own_axis():
    """Two full turns about an axis 60° off body X (a tumble-like turn) leave step X near 0; the
    same turns about X fill it (the counter takes an increment only within 45° of its axis)."""
    from groundstation.station.wizard.progress import AxisProgress
    from groundstation.station.scene.geometry import rotation_ned

    def turn(axis):
        p = AxisProgress()
        p.set_axis(0)
        axis = np.asarray(axis, float) / np.linalg.norm(axis)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R0 = rotation_ned(0.1, 0.05, 0.3)
        for i in range(721):
            a = math.radians(i)
            R = R0 @ (np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k)
            roll, pitch, yaw = math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0]))), math.atan2(R[1, 0], R[0, 0])
            p.on_attitude(i * 0.02, roll, pitch, yaw)
        p.flush()
        return float(p.progress_deg[0])

    assert turn([math.cos(math.radians(60)), math.sin(math.radians(60)), 0.0]) < 20.0
    assert turn([1.0, 0.0, 0.0]) > 700.0


def test_vehicles_calibrator_instruction_follows_its_progress():
    """In the vehicle's-calibrator mode the instruction is the vehicle's own progress (per compass,
    from MAG_CAL_PROGRESS), never our step text, and says to hold still once it has all it needs."""
    from groundstation.station.wizard import CalibrationWizard
    from groundstation.station.wizard.onboard import OnboardCalibration

    w = CalibrationWizard()
    w.start("onboard")
    w.onboard = OnboardCalibration()
    w.onboard.on_ack(True, "accepted")

    def progress(compass, pct):
        w.onboard.on_progress(SimpleNamespace(compass_id=compass, cal_status=2, attempt=1, completion_pct=pct,
                                              completion_mask=[0] * 10))

    progress(0, 12); progress(1, 9)
    text = w.snapshot()["instruction"]
    assert text.startswith("The vehicle's calibrator: 9 % (compass 1 12 %, compass 2 9 %)"), text
    assert "roll it over about" not in text and "Cover the rest" not in text
    progress(0, 100); progress(1, 100)
    assert "hold the vehicle still" in w.snapshot()["instruction"]


def test_vehicles_calibrator_page_shows_its_progress_not_our_steps(station, new_page, http, shots):
    """In the vehicle's-calibrator mode the page shows the vehicle's progress (instruction, its card)
    and not our X/Y/Z steps, whose 'turn about X' would contradict it."""
    from groundstation.sim.fake_vehicle import FakeVehicle
    from groundstation.sim.vehicle_streams import guided_dance_attitude, make_hardware, pack_stream, three_compasses

    msgs = pack_stream(guided_dance_attitude(), make_hardware(three_compasses()))
    port = free_udp_port()
    ok(http.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}))
    page = new_page()
    open_page(page, station, "/calibrate.html")
    with FakeVehicle(msgs, port, speed=4.0):
        wait_js(page, "document.getElementById('status').textContent.includes('link up')")
        page.locator("#modes input[value='onboard']").dispatch_event("click")
        page.locator("#start").dispatch_event("click")
        wait_js(page, "document.getElementById('instruction').textContent.startsWith(\"The vehicle's calibrator: \")", 90_000)
        assert page.locator("#steps-card").is_hidden()
        assert not page.locator("#onboard-card").is_hidden()
        page.screenshot(path=str(shots / "onboard_running.png"))
    assert page.errors == []


# ------------------------------------------------------------------------------ wizard on a (fake) vehicle
def test_wizard_on_a_vehicle_reads_right(station, new_page, http, shots):
    """Three compasses on a fake vehicle, the whole guided run at 1280x720: the early live field is
    labelled preliminary, the Compasses card is in view during the dance, one primary action at a
    time, the doubled fitness limit explained, the header after our write names our calibration,
    a heading check 38.6° off reads as a failure with what to do, the mode chosen after the run
    stays chosen, Reset asks before throwing the written state away, and the 3-D labels are apart."""
    from groundstation.sim.fake_vehicle import FakeVehicle
    from groundstation.sim.vehicle_streams import (ROTATION_ROLL_180, ROTATION_YAW_90, guided_dance_attitude,
                                                   hold_attitude, make_hardware, pack_stream, three_compasses)
    from groundstation.station.scene import view

    hw = make_hardware(three_compasses((ROTATION_YAW_90, ROTATION_ROLL_180, 0)))
    msgs = pack_stream(guided_dance_attitude(), hw)
    after = pack_stream(hold_attitude(135.0, 120.0, rate_hz=25.0), hw, start_unix=msgs[-1][0] + 60, boot_offset_s=4.0)
    port = free_udp_port()
    ok(http.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}))
    page = new_page(view=True)
    open_page(page, station, "/calibrate.html", view=True)
    page.locator("#start").dispatch_event("click")
    primaries = "[...document.querySelectorAll('button.primary')].filter(b => b.offsetParent !== null && !b.disabled).length"
    with FakeVehicle(msgs, port, speed=4.0, after_reboot=after, reboot_silence_s=4.0):
        wait_js(page, "!document.getElementById('result-card').hidden || (document.querySelector('#compass-table td.muted') && "
                      "document.querySelector('#compass-table td.muted').textContent.includes('mG'))", 120_000)
        w = ok(http.get("/api/calibration"))
        if w["state"] == "running" and not w["compasses"][0]["trusted"]:
            assert "preliminary" in page.locator("#compass-table").inner_text()
            assert "preliminary field" in page.locator("#live-fit").inner_text()
        if w["state"] == "running":
            box = page.locator("#compass-card").bounding_box()
            assert box["y"] + box["height"] <= 720, box            # not cut off below the steps
            page.screenshot(path=str(shots / "vehicle_dance.png"))
        wait_js(page, "!document.getElementById('result-card').hidden", 120_000)
        w = ok(http.get("/api/calibration"))
        assert w["result"]["status"] == "ok", w["result"]
        wait_js(page, "!document.getElementById('accept').disabled")
        page.wait_for_timeout(500)
        assert page.evaluate(primaries) == 1, page.evaluate(
            "[...document.querySelectorAll('button')].filter(b => b.offsetParent !== null)"
            ".map(b => [b.id, b.className, b.disabled])")
        assert not page.locator("#start").evaluate("b => b.classList.contains('primary')")
        assert "ArduPilot doubles the limit for non-primary compasses" in page.locator("#consistency").inner_text()
        page.screenshot(path=str(shots / "vehicle_result.png"))
        # the 3-D labels, placed with this browser's camera: inside the view and apart
        cam = list(station.scene.server.get_clients().values())[-1].camera
        boxes = label_boxes(station.scene, cam, [("vehicle", view.CAL_VEHICLE_AT + [0, 0, 1.3], "bottom-center"),
                                                 ("raw field + fitted ellipsoid", view.CAL_CENTER + view.RAW_LABEL_AT,
                                                  "top-center"),
                                                 ("corrected", view.SPHERE_CENTER + [0, 0, 1.3], "bottom-center")])
        x, y = project([view.CAL_VEHICLE_AT + [0, 0.8, 1.9]], cam)[0]
        text = "grey: autopilot's attitude"
        boxes.append((text, x, y - 16, x + 7 * len(text), y))           # anchored bottom-left
        for b in boxes:
            assert b[1] >= 0 and b[3] <= cam.image_width and b[2] >= 0 and b[4] <= cam.image_height, b
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                assert not overlaps(boxes[i], boxes[j]), (boxes[i], boxes[j])
        page.locator("#accept").dispatch_event("click")
        wait_js(page, "document.querySelector('#param-write .good')", 60_000)
        wait_js(page, "document.getElementById('status').textContent.includes('calibration in use')")
        status = page.locator("#status").inner_text()
        assert "calibration in use: this station's" in status and "the vehicle's" not in status, status
        ok(http.post("/api/calibration/reboot", json={"confirm": True}))
        wait_js(page, "document.getElementById('instruction').textContent.includes('is back')", 60_000)
        set_value(page, "#hc-bearing", "173.6")                           # the vehicle points at 135°
        page.locator("#hc-measure").dispatch_event("click")
        wait_js(page, "document.querySelector('#hc-result .good, #hc-result .error')", 60_000)
        page.wait_for_timeout(300)
        text = page.locator("#instruction").inner_text()
        assert text.startswith("Heading check failed") and "redo" in text, text
        assert "in use" not in text
        assert page.locator("#instruction").evaluate("e => e.classList.contains('failed')")
        assert page.locator("#hc-result .error").count() == 1
        page.screenshot(path=str(shots / "vehicle_heading_check_far.png"))

        page.locator("#modes input[value='onboard']").dispatch_event("click")
        time.sleep(1.5)                                             # several state pushes
        assert page.locator("#modes input[value='onboard']").is_checked()
        page.locator("#reset").dispatch_event("click")
        wait_js(page, "!document.getElementById('discard-confirm').hidden")
        assert "written to the vehicle" in page.locator("#discard-text").inner_text()
        page.screenshot(path=str(shots / "vehicle_reset_asks.png"))
        time.sleep(0.5)
        assert ok(http.get("/api/calibration"))["state"] == "accepted"    # nothing thrown away yet
        page.locator("#discard-no").dispatch_event("click")
        assert ok(http.get("/api/calibration"))["reboot"] is not None
        page.locator("#reset").dispatch_event("click")
        wait_js(page, "!document.getElementById('discard-confirm').hidden")
        page.locator("#discard-yes").dispatch_event("click")
        assert wait_until(lambda: ok(http.get("/api/calibration"))["state"] == "idle", 10)

    assert page.errors == []
