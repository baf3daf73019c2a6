"""The calibration wizard against known truth, without a network: streams of the fake vehicle's
sensors (groundstation.sim.vehicle_streams) decoded as the live link does and fed to the wizard."""
from __future__ import annotations

import math

import numpy as np
import pytest

from groundstation.io.decode import MavlinkDecoder
from groundstation.io.magcal import mask_from_sections, section_centres, section_of, sections_from_mask
from groundstation.samples import AttitudeSample, MagSample
from groundstation.sim.fake_autopilot import OnboardCalibrator, default_params
from groundstation.sim.fake_vehicle import compress_time
from groundstation.sim.vehicle_streams import (FakeCompass, ROTATION_ROLL_180, ROTATION_YAW_90, attitude_from_moves,
                                               guided_dance_attitude, make_hardware, pack_stream,
                                               three_compasses, walk_attitude)
from groundstation.station.wizard import CalibrationWizard, WizardSettings
from groundstation.station.wizard.aftercheck import HeadingCheck
from groundstation.station.wizard.coverage import field_unit_ned, next_pose

PARAMS = default_params("ardupilot", 3)


def feed(w: CalibrationWizard, messages, speed: float = 1.0, until=None, on_step=None) -> None:
    """Decode as the live link does (time compressed by ``speed``) and feed the wizard."""
    dec = MavlinkDecoder()
    t0 = messages[0][0]
    for unix, msg in messages:
        for s in dec.decode(compress_time(msg, speed), (unix - t0) / speed):
            w.on_sample(s)
        if on_step is not None:
            on_step(unix - t0)
        if until is not None and until(unix - t0):
            return


def dance_result(messages) -> CalibrationWizard:
    """A guided wizard fed ``messages`` and finished (ArduPilot, three compasses' default
    parameters) as soon as it is ready: in state "result"."""
    w = CalibrationWizard()
    w.start()

    def step(_t):
        if w.state == "running" and w.ready():
            w.finish("ardupilot", default_params("ardupilot", 3))

    feed(w, messages, until=lambda t: w.state == "result", on_step=step)
    assert w.state == "result"
    return w


@pytest.fixture(scope="module")
def dance_three_mounted():
    """The guided dance of a vehicle whose compasses 1 and 2 are mounted at YAW_90 and ROLL_180
    while COMPASS_ORIENT/ORIENT2 still say 0; collected and fitted once for the module."""
    hw = make_hardware(three_compasses((ROTATION_YAW_90, ROTATION_ROLL_180, 0)))
    msgs = pack_stream(guided_dance_attitude(), hw)
    w = CalibrationWizard()
    w.start()
    warnings: set[str] = set()

    def step(_t):
        if w.state == "running":
            warnings.update(w.live_warnings())
            if w.ready():
                w.finish("ardupilot", PARAMS)

    feed(w, msgs, until=lambda t: w.state == "result", on_step=step)
    return w, hw, warnings


# ------------------------------------------------------------------ defect 1: steps measure their own axis
def _moves_stream(moves, rate_hz=25.0, seed=0):
    hw = make_hardware(three_compasses())
    return pack_stream(attitude_from_moves(moves, rate_hz), hw, seed=seed)


def test_wobbling_about_other_axes_does_not_fill_step_x():
    wobble = [("still", 2.0)] + [("body", a, d, 60.0) for a in (1, 2) for d in (40.0, -80.0, 40.0)] * 3
    w = CalibrationWizard()
    w.start()
    feed(w, _moves_stream(wobble + [("still", 2.0)]))
    assert w.step == "x"
    assert w.progress.progress_deg[0] < 5.0                         # the old |ω| integral gave ~1400°
    assert w.progress.progress_deg[1] == 0.0 and w.progress.progress_deg[2] == 0.0   # not their steps yet


def test_held_still_does_not_creep_and_says_no_motion():
    w = CalibrationWizard()
    w.start()
    feed(w, _moves_stream([("still", 60.0)]))
    assert w.progress.progress_deg[0] < 0.5          # the gyro-noise integral crept 3 -> 14 deg in a minute
    assert w.hint() is not None and w.hint().startswith("No motion")


def test_a_turn_about_x_fills_x_then_y_is_current():
    w = CalibrationWizard()
    w.start()
    feed(w, _moves_stream([("still", 1.0), ("body", 0, 370.0, 45.0), ("still", 3.0)]))
    assert w.step == "y"
    assert 345.0 <= w.progress.progress_deg[0] <= 372.0
    assert w.hint() is not None                      # still again at the end


def test_pitching_over_through_90_deg_adds_nothing_to_x():
    """Near pitch ±90° ATTITUDE's roll and yaw are arbitrary: the gyro is used there."""
    w = CalibrationWizard()
    w.start()
    w.progress.set_axis(0)
    feed(w, _moves_stream([("still", 1.0), ("body", 1, 360.0, 45.0), ("still", 1.0)]))
    assert w.progress.net_deg[0] == pytest.approx(0.0, abs=2.0)


# ------------------------------------------------------------------ defect 2: link drops
def _started_on_y(progress_y: float) -> CalibrationWizard:
    w = CalibrationWizard()
    w.start()
    w.step_index = 1
    w.progress.set_axis(1)
    w.progress.net_deg[1] = progress_y
    w._last_t = 20.0
    return w


def test_short_drop_pauses_then_resumes_the_step():
    w = _started_on_y(200.0)
    text = w.on_link(False, 23.0)
    assert w.paused and "paused" in text and "Link lost during step Y" in w.banner["text"]
    assert "paused" in w.snapshot()["instruction"]
    w.on_sample(AttitudeSample(25.0, 0.0, 0.3, 0.0))       # ignored while paused
    assert w.att.n == 0
    text = w.on_link(True, 26.0)
    assert not w.paused and "resumes" in text and w.progress.net_deg[1] == 200.0


def test_long_drop_restarts_the_step():
    w = _started_on_y(200.0)
    w.on_link(False, 23.0)
    text = w.on_link(True, 60.0)
    assert "restarts" in text and w.progress.net_deg[1] == 0.0 and w.step == "y"


# ------------------------------------------------------------------ defect 3: no field warning on a clean run
def test_clean_run_never_warns_about_the_field(dance_three_mounted):
    w, _, warnings = dance_three_mounted
    assert w.state == "result"
    assert not [x for x in warnings if "WMM" in x or "disturbance" in x.lower()], warnings


def test_wrong_scale_gives_the_field_hypothesis_only_once_the_fit_is_trusted():
    hw = make_hardware((FakeCompass(0, np.eye(3) * 0.62, np.array([80.0, -40.0, 30.0]), 1.5),))
    w = CalibrationWizard()
    w.start()
    seen = []
    feed(w, pack_stream(guided_dance_attitude(), hw),
         on_step=lambda t: seen.append((t, w.tracks[0].trusted() if 0 in w.tracks else False, w.live_warnings())))
    first = next(t for t, _, warn in seen if any("WMM" in x for x in warn))
    assert all(trusted for t, trusted, warn in seen if any("WMM" in x for x in warn))
    assert first > 20.0                      # not on the first few hundred samples
    text = next(x for _, _, warn in seen for x in warn if "WMM" in x)
    assert "weaker" in text and "Possibly" in text


# ------------------------------------------------------------------ every compass, orientation, quality
def test_three_compasses_fitted_with_their_orientation(dance_three_mounted):
    w, hw, _ = dance_three_mounted
    r = w.results
    assert set(r) == {0, 1, 2} and all(r[k]["status"] == "ok" and r[k]["pass"] for k in r)
    assert r[0]["orientation"]["detected"] == ROTATION_YAW_90 and r[0]["orientation"]["status"] == "rotation_found"
    assert r[1]["orientation"]["detected"] == ROTATION_ROLL_180
    assert r[2]["orientation"]["status"] == "confirmed"
    p = w.result["ardupilot_params"]
    assert p["COMPASS_ORIENT"] == 2 and p["COMPASS_ORIENT2"] == 8 and p["COMPASS_ORIENT3"] == 0
    for k, c in enumerate(hw.compasses):     # hard iron in the body frame of the right orientation
        from groundstation.io.params import rotation_enum_matrix
        b_body = rotation_enum_matrix(c.mount_rotation) @ c.offsets_mG
        n = "" if k == 0 else str(k + 1)
        ofs = [p[f"COMPASS_OFS{n}_{a}"] for a in "XYZ"]
        np.testing.assert_allclose(ofs, -b_body, atol=3.0)
    assert w.consistency["status"] == "ok" and all(x["angle_deg"] < 2.0 for x in w.consistency["pairs"])
    assert w.result["status"] == "ok" and w.result["compasses_included"] == [0, 1, 2]


def test_fitness_levels_and_leaving_a_compass_out(dance_three_mounted):
    w, _, _ = dance_three_mounted
    fit1 = w.results[1]["fitness_mG"]            # compass 2: 3 mG noise
    assert 2.0 < fit1 < 4.0 and w.results[1]["fitness_threshold_mG"] == 32.0   # twice COMPASS_CAL_FIT after the first
    from dataclasses import replace
    w.settings = replace(w.settings, fitness_level="very_strict")
    w.rebuild_result("ardupilot")
    assert w.results[1]["fitness_threshold_mG"] == 8.0 and w.results[1]["pass"]
    w.settings = replace(w.settings, fitness_level="default")
    w.tracks[2].included = False
    w.rebuild_result("ardupilot")
    assert "COMPASS_OFS3_X" not in w.result["ardupilot_params"] and "COMPASS_OFS2_X" in w.result["ardupilot_params"]
    w.tracks[2].included = True
    w.rebuild_result("ardupilot")


def test_failing_fitness_is_explained_in_words():
    hw = make_hardware((FakeCompass(0, np.eye(3), np.array([50.0, 20.0, -30.0]), 14.0),))
    w = CalibrationWizard(WizardSettings(fitness_level="strict"))
    w.start()
    feed(w, pack_stream(guided_dance_attitude(), hw), until=lambda t: w.ready())
    w.finish("ardupilot", PARAMS)
    r = w.results[0]
    assert r["status"] == "ok" and not r["pass"] and w.result["status"] == "failed"
    assert any("above the 8 mG threshold" in x for x in r["reasons"])
    assert r["heading_error_deg"] > 1.0


def test_deviation_card_before_and_after(dance_three_mounted):
    card = dance_three_mounted[0].deviation
    assert card is not None and len(card["heading_deg"]) >= 10
    assert card["max_before_deg"] > 10.0 and card["max_after_deg"] < 2.0


def test_deviation_card_at_x4_read_in_bursts(dance_three_mounted):
    """The fake vehicle at x4 (``compress_time``: every boot time / 4, RAW_IMU's time_usec too)
    and a loaded station reading the link in bursts (gaps 0.1 s on average): on one boot clock
    the card is the one of the calm x1 run.  With RAW_IMU's time_usec left at x1 the station's
    one clock saw two, re-anchored at every ATTITUDE, and the wizard gave no card."""
    hw = make_hardware(three_compasses((ROTATION_YAW_90, ROTATION_ROLL_180, 0)))
    msgs = pack_stream(guided_dance_attitude(), hw)
    raw = [m for _, m in msgs if m.get_type() == "RAW_IMU"][5]
    assert compress_time(raw, 4.0).time_usec == raw.time_usec // 4
    rng = np.random.default_rng(1)
    w, dec = CalibrationWizard(), MavlinkDecoder()
    w.start()
    t0, read_at = msgs[0][0], 0.0
    for unix, msg in msgs:
        sent = (unix - t0) / 4.0
        if sent > read_at:                              # the next burst read
            read_at = sent + float(rng.exponential(0.1))
        for s in dec.decode(compress_time(msg, 4.0), read_at):
            w.on_sample(s)
        if w.state == "running" and w.ready():
            w.finish("ardupilot", PARAMS)
        if w.state == "result":
            break
    calm = dance_three_mounted[0].deviation
    assert w.deviation is not None
    assert w.deviation["max_after_deg"] < 2.0
    assert w.deviation["max_after_deg"] == pytest.approx(calm["max_after_deg"], abs=0.1)
    assert w.deviation["max_before_deg"] == pytest.approx(calm["max_before_deg"], abs=0.5)


# ------------------------------------------------------------------ coverage and next pose
def test_next_pose_comes_from_what_is_missing():
    from estimators.calibration import coverage_cells
    from groundstation.station.wizard.coverage import body_field_directions
    h = field_unit_ned(np.array([336.6, -35.8, 353.5]))
    yaw = np.radians(np.arange(0, 360, 2.0))

    def turn(pose):
        n = len(yaw)
        return coverage_cells(body_field_directions(np.full(n, math.radians(pose["roll_deg"])),
                                                    np.full(n, math.radians(pose["pitch_deg"])), yaw, h))

    covered = np.zeros(100, bool)
    seen = []
    for _ in range(4):                       # follow the advice four times
        pose = next_pose(covered, h)
        assert pose is not None and pose["fills"] > 0 and pose["text"] not in seen
        added = turn(pose) & ~covered
        assert added.sum() >= pose["fills"]      # it fills at least what it promised
        covered |= added
        seen.append(pose["text"])
    assert covered.mean() > 0.5
    assert next_pose(np.ones(100, bool), h) is None


# ------------------------------------------------------------------ heading check
def test_walk_course_and_bearing_check():
    hc = HeadingCheck("walk", None, 3.0, -6.0)
    hw = make_hardware()
    msgs = pack_stream(walk_attitude(75.0, 12.0), hw)
    dec = MavlinkDecoder()
    for unix, msg in msgs:
        for s in dec.decode(msg, unix - msgs[0][0]):
            if s.__class__.__name__ == "GpsSample":
                hc.add_fix(s.t_s, s.lat_deg, s.lon_deg)
            elif isinstance(s, MagSample):
                hc.add_heading(s.t_s, 75.0 + 1.0)
    r = hc.finish()
    assert r["ok"] and r["reference_deg"] == pytest.approx(75.0, abs=0.5) and r["error_deg"] == pytest.approx(1.0, abs=0.5)
    assert r["distance_m"] > 15.0
    short = HeadingCheck("walk", None, 3.0, None)
    short.add_fix(0.0, 30.0, 120.0)
    short.add_fix(1.0, 30.00001, 120.0)
    for i in range(10):
        short.add_heading(i * 0.1, 10.0)
    assert not short.finish()["ok"]


def test_bearing_check_in_large_vehicle_mode_is_worded_as_a_bearing_not_a_walk():
    """Large-vehicle mode before its calibration with a bearing check (the page's Check heading; found
    on ArduPilot SITL): the instruction read the walk's distance_m from a bearing result (KeyError,
    the state failing); it says the bearing check's words and then its result."""
    w = CalibrationWizard(WizardSettings())
    w.start("fixed_yaw")
    w.heading_check = HeadingCheck("bearing", 45.0, 3.0, -6.0)
    assert "bearing" in w.snapshot()["instruction"]
    for i in range(40):
        w.heading_check.add_heading(i * 0.1, 45.4)
    assert w.heading_check.result["error_deg"] == pytest.approx(0.4, abs=0.01)
    text = w.snapshot()["instruction"]
    assert "walk" not in text.lower() and "+0.4" in text


# ------------------------------------------------------------------ ArduPilot's onboard pieces (fake vehicle, wire format)
def test_geodesic_sections_and_completion_mask():
    rng = np.random.default_rng(0)
    s = section_of(rng.normal(size=(20000, 3)))
    assert s.min() == 0 and s.max() == 79 and np.all(np.bincount(s, minlength=80) > 0)
    assert list(section_of(section_centres())) == list(range(80))
    assert sections_from_mask(mask_from_sections([0, 9, 42, 79])) == [0, 9, 42, 79]


def test_fake_onboard_calibrator_reports_arduplot_convention_offsets():
    from groundstation.sim.vehicle_streams import MORE_TILTS, TILTS
    hw = make_hardware(three_compasses())
    cal = OnboardCalibrator()
    cal.start(0, 1, default_params())
    for _, m in pack_stream(guided_dance_attitude(tilts=TILTS + MORE_TILTS), hw):
        if m.get_type() == "RAW_IMU":
            cal.new_sample(0, np.array(m.raw_mag_mG))
    (report,) = cal.report_fields(default_params())
    assert report[2] == 4 and report[4] < 3.0                           # success, fitness (RMS, mG)
    np.testing.assert_allclose(report[5:8], -hw.compasses[0].offsets_mG, atol=3.0)   # OFS = −b


# ------------------------------------------------------------------ PX4 over the live link (no browser)
def test_px4_vehicle_with_an_old_calibration_refitted_and_written(tmp_path):
    """A PX4 vehicle already corrects each compass with an old CAL_MAGk_* (the field it sends is
    corrected); the wizard un-applies it per slot, fits, and the write is confirmed by echo."""
    import time

    from conftest import free_udp_port
    from groundstation.sim.fake_vehicle import FakeVehicle
    from groundstation.station.hub.session import Session

    hw = make_hardware(three_compasses())
    old = default_params("px4", 3)
    old |= {"CAL_MAG0_XOFF": 0.05, "CAL_MAG0_YOFF": -0.02, "CAL_MAG1_ZOFF": -0.1, "CAL_MAG2_XSCALE": 1.05}
    msgs = pack_stream(guided_dance_attitude(rate_hz=12.5), hw)
    session = Session(tmp_path, record_live=False)
    port = free_udp_port()
    session.connect(f"udpin:127.0.0.1:{port}")
    session.wizard_start()
    fv = FakeVehicle(msgs, port, speed=8.0, autopilot="px4", params=old).start()
    try:
        deadline = time.monotonic() + 90
        while session.snapshot()["wizard"]["state"] != "result" and time.monotonic() < deadline:
            time.sleep(0.1)
        w = session.snapshot()["wizard"]
        assert w["state"] == "result" and w["result"]["status"] == "ok", w["result"]
        for k, c in enumerate(hw.compasses):
            r = w["compasses"][k]["result"]
            np.testing.assert_allclose(r["offsets_mG"], c.offsets_mG, atol=3.0)      # the sensor's own hard iron
            assert f"CAL_MAG{k}" in r["message"]                                   # it says what it un-applied
        pw = session.wizard_accept()
        assert pw["state"] == "checking" and pw["autopilot"] == "px4"     # re-reads the parameters first
        deadline = time.monotonic() + 20
        while session.snapshot()["wizard"]["param_write"]["state"] in ("checking", "writing") and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        pw = session.snapshot()["wizard"]["param_write"]
        sent = w["result"]["px4_params"]
    finally:
        fv.stop()
        session.close()
    assert pw["state"] == "written" and sorted(pw["confirmed"]) == sorted(sent)
    for name, value in sent.items():
        assert fv.params[name] == pytest.approx(value, abs=1e-6 * max(1.0, abs(value)))
    assert session.snapshot()["calibration_in_use"]          # the vehicle's, now


def test_compass_1_follows_raw_imu_even_when_scaled_imu_is_heard_first():
    """Another station has SCALED_IMU streamed at a low rate (here reading 300 mG off, so that a
    wrong choice shows in the offsets) and its first packet comes before RAW_IMU's: the wizard keeps
    the lowest source of compass 1 (RAW_IMU, instance 0), the live analysis' rule."""
    from groundstation.io.mavlink import mavlink2 as m

    hw = make_hardware(three_compasses())
    msgs, n_raw = [], 0
    for unix, msg in pack_stream(guided_dance_attitude(), hw):
        if msg.get_type() == "RAW_IMU":
            if n_raw % 5 == 0:
                msgs.append((unix - 0.001, m.MAVLink_scaled_imu_message(
                    msg.time_usec // 1000, msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro,
                    msg.xmag + 300, msg.ymag - 300, msg.zmag + 300)))
            n_raw += 1
        msgs.append((unix, msg))
    assert msgs[0][1].get_type() == "SCALED_IMU"
    w = CalibrationWizard()
    w.start()

    def step(_t):
        if w.state == "running" and w.ready():
            w.finish("ardupilot", PARAMS)

    feed(w, msgs, until=lambda t: w.state == "result", on_step=step)
    assert w.state == "result" and w.tracks[0].instance == 0
    # RAW_IMU's rate (that of SCALED_IMU2 for compass 2), not a fifth of it
    assert len(w.tracks[0].mag.view()) >= 0.95 * len(w.tracks[1].mag.view()) > 1000
    p = w.result["ardupilot_params"]
    np.testing.assert_allclose([p[f"COMPASS_OFS_{a}"] for a in "XYZ"], -hw.compasses[0].offsets_mG, atol=3.0)
