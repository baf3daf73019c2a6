"""The station against ArduPilot's own firmware (SITL ArduCopter 4.7, ../shared/sitl, stock stream rates).

Scenarios, each printed as one table: ours vs the truth vs ArduPilot's own result.
1. streams   -- a stock Copter (every MAVn_* rate 0): what the station asked for, what arrived.
2. wizard    -- the guided wizard on the calibration rig (its 18-pose tour) with three compasses of
               known SIM_MAGn_OFS/DIA/ODI: our offsets and soft iron vs the truth vs the vehicle's own
               calibrator on the same rig (scenario 3); accept, read back, reboot, live data again.
3. onboard   -- the vehicle's calibrator through the station (start, progress per compass, reports,
               accept, read back); a forced failure (COMPASS_CAL_FIT tiny) and a cancel.
4. logs      -- calibrate / analyze / info on the firmware's own .BIN and on the station's session
               .tlog of the wizard run: the same offsets, the same alarms, one report per compass.
5. flights   -- (--flights) 2-minute GUIDED flights at real time: clean, with SIM_MAG_MOT, low over a
               SIM_MAG_ALY anomaly, with SIM_GPS1_ENABLE 0 for 60 s: alarms on the .BIN vs on the .tlog.
   population (--population N) clean flights drawn from wide priors (population_flight: sites by
               inclination -60..75 deg, routes, headings, speeds, SIM_MAG_MOT with COMPASS_MOT partly
               set, wind, GPS outages), one table of their combined alarms on the .BIN and the .tlog;
               --keep DIR keeps the logs, --analyse-kept DIR analyses them again without flying.
7. fixed_yaw -- large-vehicle mode: the rig held at a known yaw, the station sends
               MAV_CMD_FIXED_MAG_CAL_YAW; the firmware's offsets and ours vs SIM_MAGn_OFS.
6. trust     -- the rig spun about 8 axes with the guided wizard live: our calibration of the session
               .tlog vs SIM_MAGn_OFS/DIA/ODI, the wizard's cautions (none on a perfect rig), then our
               values written and the field the firmware reports with them applied vs the WMM (1 %).
Ports 14613-14619 (-I 12..16).  Bounded by `timeout` per SITL run.

Run:  nice -n 10 .venv/bin/python benchmarks/sitl.py [--speedup 8] [--only streams,wizard,onboard,logs,fixed_yaw,trust]
          [--flights clean,motor,anomaly,gps_off] [--population N --population-seed S] [--instance 20..29]
          [--keep DIR] [--analyse-kept DIR]
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "sitl"))

from harness import (COPTER_LAND, HOME, MAV_CMD_NAV_TAKEOFF, MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, MISSING,  # noqa: E402
                     RIG_TRUTH, SITL_BINARY, Sitl, Watch, arm, boot_offset_s, command, goto, rig_spin, rig_stop, rig_tour,
                     rig_hold, set_mode, set_params, station_for, station_link, truth_params, uncalibrated_params,
                     wait_for)

RIG_PARAMS = {**truth_params(), **uncalibrated_params(), **{f"SERVO{n}_FUNCTION": 0 for n in (5, 6, 7, 8)}}


def fmt(v, nd: int = 2) -> str:
    if v is None:
        return "—"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(fmt(x, nd) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def table(title: str, header: tuple, rows: list) -> None:
    rows = [tuple(fmt(c) for c in r) for r in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    print(f"\n## {title}\n")
    print("| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |")


def connect(sitl: Sitl, rec: Path):
    session = station_for(sitl, rec, timeout_s=60)
    link = station_link(session)
    wait_for(lambda: not link.streams_snapshot()["missing"], 40)
    time.sleep(1.0)
    return session, link


@contextlib.contextmanager
def sitl_run(out: dict, prefix: str, *sitl_args, **sitl_options):
    """A SITL run (harness.Sitl) and a station session following it: yields (sitl, session, link);
    closes the session and stops the SITL (by its PID), keeping its folder and the recordings for
    the log scenarios (listed in out["_dirs"], removed at the end)."""
    rec = Path(tempfile.mkdtemp(prefix=prefix))
    out.setdefault("_dirs", []).append(rec)
    sitl = Sitl(*sitl_args, **sitl_options).start()
    try:
        session, link = connect(sitl, rec)
        try:
            yield sitl, session, link
        finally:
            session.close()
    finally:
        sitl.stop(keep=True)
        out["_dirs"].append(sitl.run_dir)


def sfx(k: int) -> str:
    return "" if k == 0 else str(k + 1)


def params_of(p: dict, k: int, key: str) -> list:
    return [p.get(f"COMPASS_{key}{sfx(k)}_{a}") for a in "XYZ"]


# ---------------------------------------------------------------------------------- scenarios
def run_onboard(speedup: float, out: dict) -> None:
    """The vehicle's own calibrator: success run (accept, read back), a forced failure, a cancel."""
    with sitl_run(out, "sitl-bench-onboard-", 13, 14614,
                  model="calibration", speedup=speedup, extra=RIG_PARAMS, limit_s=400) as (sitl, session, link):
        out["streams"] = session.snapshot()["vehicles"]["streams"]
        rig_tour(session)
        t0 = time.monotonic()
        session.wizard_start("onboard")
        seen_pct: dict[int, set] = {}

        def reported():
            ob = session.calibration.snapshot()["onboard"]
            for c in ob["compasses"]:
                seen_pct.setdefault(c["index"], set()).add(c.get("completion_pct"))
            return ob if ob["state"] in ("reported", "failed") else None
        ob = wait_for(reported, 180, 0.2)
        out["onboard_s"] = time.monotonic() - t0
        out["onboard"] = ob
        out["progress_steps"] = {k: len(v) for k, v in seen_pct.items()}
        if ob and ob["state"] == "reported":
            session.calibration.accept("vehicle")
            wait_for(lambda: (session.calibration.snapshot()["param_write"] or {}).get("state") == "written", 30)
            reports = {c["index"]: c["report"] for c in ob["compasses"]}

            def read_back():
                got = {k: params_of(session.params, k, "OFS") for k in reports}
                return got if all(None not in v and np.allclose(v, reports[k]["ofs_mG"], atol=0.05)
                                  for k, v in got.items()) else None
            out["onboard_read_back"] = wait_for(read_back, 30)
        # a forced failure: a fit tolerance no fit meets
        session.wizard_reset()
        out["fail_set"] = set_params(session, {"COMPASS_CAL_FIT": 0.001})
        session.wizard_start("onboard")
        out["fail"] = wait_for(lambda: (lambda ob: ob if (ob or {}).get("state") in ("reported", "failed") else None)(
            session.calibration.snapshot()["onboard"]), 180, 0.3)
        # a cancel while running
        session.wizard_reset()
        set_params(session, {"COMPASS_CAL_FIT": 16.0})
        session.wizard_start("onboard")
        wait_for(lambda: (session.calibration.snapshot()["onboard"] or {}).get("state") == "running", 30, 0.2)
        try:
            session.calibration.cancel_onboard()
        except Exception as err:      # noqa: BLE001 (it was never seen running: reported in the table)
            out["cancel_error"] = str(err)
        out["cancel"] = wait_for(lambda: (lambda ob: ob if ob and ob["state"] not in ("running", "starting") else None)(
            session.calibration.snapshot()["onboard"]), 20, 0.2)
        out["onboard_tlog"] = session.sources.recording_path
    out["onboard_bin"] = max(sitl.bin_logs(), key=lambda p: p.stat().st_size, default=None)


def run_wizard(speedup: float, out: dict) -> None:
    """The guided wizard on the rig; accept, read back, reboot; the logs kept for scenario 4."""
    with sitl_run(out, "sitl-bench-wizard-", 12, 14613,
                  model="calibration", speedup=speedup, extra=RIG_PARAMS, limit_s=400) as (sitl, session, link):
        session.wizard_start("guided")
        rig_tour(session)
        t0 = time.monotonic()
        done = wait_for(lambda: session.calibration.snapshot()["state"] not in ("running",), 200 / speedup + 30, 0.3)
        if not done:
            try:
                session.wizard_finish_now()
            except Exception as err:  # noqa: BLE001 (it finished by itself meanwhile)
                out["finish_error"] = str(err)
            time.sleep(2)
        out["wizard_s"] = time.monotonic() - t0
        snap = session.calibration.snapshot()
        out["wizard"] = snap["result"]
        out["wizard_compasses"] = len(snap["compasses"])
        if snap["result"] and snap["result"].get("status") == "ok":
            session.wizard_accept()
            wait_for(lambda: (session.calibration.snapshot()["param_write"] or {}).get("state") in
                     ("written", "failed"), 60, 0.3)
            out["write"] = session.calibration.snapshot()["param_write"]
            ours = snap["result"]["ardupilot_params"]
            session.vehicle.request_params(link)

            def read_back():
                names = [n for n in ours if n.startswith(("COMPASS_OFS", "COMPASS_DIA", "COMPASS_ODI"))]
                bad = [n for n in names if session.params.get(n) is None or
                       abs(session.params[n] - ours[n]) > 1e-3 * max(1, abs(ours[n]))]
                return {"checked": len(names), "different": bad} if not bad else None
            out["wizard_read_back"] = wait_for(read_back, 30) or {"checked": 0, "different": ["(timeout)"]}
        # the reboot: once the data flows, from the command to live data again (a restart seen)
        wait_for(lambda: session.snapshot()["vehicle"]["no_data"] is None and
                 link.streams.arriving("ATTITUDE", time.time()), 30, 0.1)
        restarts = lambda: sum("restarted" in e["text"] for e in session.snapshot()["events"])  # noqa: E731
        before = restarts()
        t0 = time.monotonic()
        session.calibration.reboot(True)          # the page's reboot button (POST /api/calibration/reboot)
        out["reboot_resume_s"] = resumed_after(session, link, restarts, before, t0)
        time.sleep(2)
        out["after_reboot_params"] = {k: params_of(session.params, k, "OFS") for k in range(3)}
        # the heading check after the reboot: the rig held level at a known true heading (the rig's
        # AHRS_EKF_TYPE 10 is the simulation's own attitude, so ATTITUDE.yaw is the truth too)
        out["heading_check"] = heading_check_at(session, link, HEADING_CHECK_YAW_DEG, speedup)
        out["tlog"] = session.sources.recording_path
        out["wizard_events"] = [f"{e['t_s']:.1f} {e['text']}" for e in session.snapshot()["events"]]
    out["bin"] = max(sitl.bin_logs(), key=lambda p: p.stat().st_size, default=None)   # before the reboot


def resumed_after(session, link, restarts, before: int, t0: float) -> float | None:
    """Seconds from ``t0`` (the reboot command) until the station has seen the restart, shows no
    "no attitude data" and ATTITUDE arrives again (None after 30 s).  At 8x the vehicle is silent
    for well under a second of wall time, so the stale state may never be polled: the restart event
    is the sign the reboot happened."""
    back = wait_for(lambda: restarts() > before and session.snapshot()["vehicle"]["no_data"] is None
                    and link.streams.arriving("ATTITUDE", time.time()) and time.monotonic(), 30, 0.05)
    return back - t0 if back else None


HEADING_CHECK_YAW_DEG = 45.0     # output 8 at PWM 1625 exactly: -180 + 360 * 625 / 1000


def heading_check_at(session, link, yaw_deg: float, speedup: float) -> dict:
    """Hold the rig level at ``yaw_deg`` true, let it settle, run the station's heading check
    ("bearing", the page's Check heading) against it; returns its result with the vehicle's
    ATTITUDE yaw (the simulation's truth on the rig) beside it."""
    yaws: list[float] = []

    def hook(_conn, msg) -> None:
        if msg.get_type() == "ATTITUDE" and msg.get_srcSystem() == 1:
            yaws.append(float(np.degrees(msg.yaw)) % 360.0)
    link.mav.message_hooks.append(hook)
    try:
        rig_hold(session, 0.0, 0.0, np.radians(yaw_deg))
        # settled: the simulation's yaw at the hold for a second of samples (a loaded machine runs
        # the SITL slower than its speedup, so no fixed wait)
        wait_for(lambda: len(yaws) > 20 and all(abs((y - yaw_deg + 180.0) % 360.0 - 180.0) < 0.05
                                                for y in yaws[-20:]), 60, 0.2)
        time.sleep(1.0)
        yaws.clear()
        session.calibration.heading_check("bearing", yaw_deg)
        hc = wait_for(lambda: (lambda h: h if h and h.get("state") == "done" else None)(
            session.calibration.snapshot().get("heading_check")), 30, 0.2)
    finally:
        link.mav.message_hooks.remove(hook)
    r = dict((hc or {}).get("result") or {})
    r["attitude_yaw_deg"] = float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(yaws)))))) % 360.0 if yaws else None
    return r


def run_fixed_yaw(speedup: float, out: dict) -> None:
    """Large-vehicle mode: the rig held level at a known yaw, the station sends
    MAV_CMD_FIXED_MAG_CAL_YAW with it (the page's Large vehicle, entered heading); the firmware sets
    every compass's offsets from the WMM field; these, ours from the same samples, vs SIM_MAGn_OFS.
    The method assumes no soft iron: the truth here is offsets only (DIA 1, ODI 0)."""
    truth = {n: {"OFS": t["OFS"], "DIA": (1.0, 1.0, 1.0), "ODI": (0.0, 0.0, 0.0)} for n, t in RIG_TRUTH.items()}
    extra = {**truth_params(truth), **uncalibrated_params(), **{f"SERVO{n}_FUNCTION": 0 for n in (5, 6, 7, 8)}}
    with sitl_run(out, "sitl-bench-fixedyaw-", 16, 14617,
                  model="calibration", speedup=speedup, extra=extra, limit_s=300) as (sitl, session, link):
        settled: list[float] = []

        def hook(_conn, msg) -> None:
            if msg.get_type() == "ATTITUDE" and msg.get_srcSystem() == 1:
                settled.append(abs((float(np.degrees(msg.yaw)) - FIXED_YAW_DEG + 180.0) % 360.0 - 180.0))
        link.mav.message_hooks.append(hook)
        rig_hold(session, 0.0, 0.0, np.radians(FIXED_YAW_DEG))
        wait_for(lambda: len(settled) > 20 and max(settled[-20:]) < 0.05, 60, 0.2)
        link.mav.message_hooks.remove(hook)
        session.wizard_start("fixed_yaw")
        time.sleep(3.0)                                   # the wizard's latest samples of each compass
        sent = session.calibration.fixed_yaw(FIXED_YAW_DEG, "entered")
        done = wait_for(lambda: (lambda f: f if f and f.get("state") in ("done", "refused") else None)(
            session.calibration.snapshot().get("fixed_yaw")), 40, 0.2)
        session.vehicle.request_params(link)
        time.sleep(3.0)

        def vehicle_ofs():
            got = {k: params_of(session.params, k, "OFS") for k in range(3)}
            return got if all(None not in v and max(abs(a - 0.001) for a in v) > 1 for v in got.values()) else None
        out["fixed_yaw"] = {"sent": sent, "done": done, "vehicle_ofs": wait_for(vehicle_ofs, 20, 0.3),
                            "truth": {k: truth[k + 1]["OFS"] for k in range(3)},
                            "heading_check": heading_check_after_fixed_yaw(session, link, speedup)}


FIXED_YAW_DEG = 45.0


def heading_check_after_fixed_yaw(session, link, speedup: float) -> dict:
    """The heading at a second known yaw (135 deg, PWM 1875) with the vehicle's new offsets."""
    return heading_check_at(session, link, 135.0, speedup)


def run_logs(out: dict) -> None:
    """calibrate / analyze / info on the firmware's .BIN and on the station's session .tlog."""
    from groundstation.io.logs import read_log
    from groundstation.jobs.analyze import analyze_log
    from groundstation.jobs.calibrate import calibrate_compasses
    from groundstation.jobs.log_summary import compass_lines, distinct_reports

    for kind, path in (("onboard_bin", out.get("onboard_bin")), ("onboard_tlog", out.get("onboard_tlog"))):
        if path is not None:
            log = read_log(path)
            out[f"{kind}_reports"] = (len(distinct_reports(log.mag_cal)), sum(e.kind == "report" for e in log.mag_cal),
                                      sum(e.kind == "start" for e in log.mag_cal))
    for kind, path in (("bin", out.get("bin")), ("tlog", out.get("tlog"))):
        if path is None:
            continue
        log = read_log(path)
        res = {r["compass"]: r for r in calibrate_compasses(log)}
        summary, _ = analyze_log(log)
        out[f"{kind}_cal"] = res
        out[f"{kind}_cal_status"] = {k: (r["status"], (r.get("message") or "")[:120]) for k, r in res.items()}
        out[f"{kind}_alarms"] = summary.get("alarms", [])
        out[f"{kind}_info"] = compass_lines(log)
        out[f"{kind}_reports"] = (len(distinct_reports(log.mag_cal)), sum(e.kind == "report" for e in log.mag_cal),
                                  sum(e.kind == "start" for e in log.mag_cal))
        out[f"{kind}_sources"] = {c.compass: c.source for c in log.compass_tables()}


MOTOR_TRUTH_mG_PER_A = (3.0, -2.0, 4.0)
MOTOR = {f"SIM_MAG_MOT_{a}": v for a, v in zip("XYZ", MOTOR_TRUTH_mG_PER_A)}
SQUARE = ((80, 0), (80, 80), (0, 80), (0, 0))                 # north, east m from home
SURVEY = ((200, 0), (200, 40), (0, 40), (0, 80), (200, 80), (0, 0))
STOP_GO = ((40, 0), (40, 40), (80, 40), (80, 80), (0, 80), (0, 0))
WIND = {"SIM_WIND_SPD": 7.0, "SIM_WIND_DIR": 60.0, "SIM_WIND_TURB": 2.0}


@dataclass(frozen=True)
class SitlFlight:
    """One GUIDED flight: extra defaults (SIM truth, speed, wind), the legs' altitude [m], what the
    truth is, the site (--home lat, lon, alt m, yaw deg), the legs (north, east m from home), and
    what is done in flight: GPS away for ``gps_off_s`` (60 s) from the second leg, or the anomaly (SIM_MAG_ALY, 150,
    -100, 200 mG at the ground, 1/8 at SIM_MAG_ALY_HGT 5 m) switched on by a parameter once
    airborne at 4 m ("inflight": it appears in time), or switched on at 25 m, where it is 1/216 of
    that (1.2 mG), and flown onto in a descent to 2 m and the climb back ("descent": it rises and
    falls with the place flown).  The SITL anomaly depends on the height alone, so one set before
    take-off is under the vehicle from the start: the detector learns it on the ground and alarms
    at the climb out of it, for the whole flight (measured: "rising with time" at take-off).
    ``expect``: "none" (a clean flight: no alarm), "motor" (learnt, no alarm) or "anomaly".  A leg is
    (north, east) at ``alt_m`` and the speed WPNAV_SPEED says, or (north, east, alt m, speed m/s)
    (MAV_CMD_DO_CHANGE_SPEED before it; the population's, ``population_flight``)."""
    extra: dict
    alt_m: float
    truth: str
    home: tuple = HOME
    legs: tuple = SQUARE
    gps_off: bool = False
    anomaly: str | None = None
    expect: str = "none"
    gps_off_s: float = 60.0                       # the outage's length when ``gps_off``
    motor_truth: tuple | None = MOTOR_TRUTH_mG_PER_A   # the field per ampere left after COMPASS_MOT (expect "motor")
    site: str = ""                                # the population's: "lat, lon (inclination)" for the table


ANOMALY = {"SIM_MAG_ALY_HGT": 5.0, "SIM_MAG_ALY_X": 150.0, "SIM_MAG_ALY_Y": -100.0, "SIM_MAG_ALY_Z": 200.0}
TROMSO, SOUTH, EQUATOR = (69.65, 18.96, 20.0, 0.0), (-45.87, 170.5, 50.0, 0.0), (0.5, 32.6, 1150.0, 0.0)
FLIGHTS = {
    "clean": SitlFlight({}, 15.0, "no alarm"),
    "motor": SitlFlight(MOTOR, 15.0, f"motor field {list(MOTOR_TRUTH_mG_PER_A)} mG/A (SIM_MAG_MOT)", expect="motor"),
    "anomaly": SitlFlight({}, 4.0, "anomaly [150, -100, 200] mG at the ground, 1/8 at 5 m, from takeoff + 5 s: "
                          "alarms low", anomaly="inflight", expect="anomaly"),
    "anomaly_descent": SitlFlight({"WPNAV_SPEED": 300}, 25.0,
                                  "anomaly on at 25 m (1.2 mG); descend to 2 m onto it and climb back over "
                                  "25 m: alarms fixed in place", anomaly="descent", expect="anomaly"),
    "gps_off": SitlFlight({}, 15.0, "no alarm (GPS away 60 s from the second leg)", gps_off=True),
    # clean flights nobody tuned for: sites, routes, speeds, wind, a motor field with varying current
    "clean_tromso": SitlFlight({}, 20.0, "no alarm (Tromso, inclination 78 deg)", home=TROMSO),
    "clean_south": SitlFlight({"WPNAV_SPEED": 1000}, 25.0, "no alarm (New Zealand, inclination -71 deg, 10 m/s)",
                              home=SOUTH),
    "clean_equator": SitlFlight({}, 15.0, "no alarm (Uganda, inclination -20 deg)", home=EQUATOR, legs=STOP_GO),
    "clean_survey_fast": SitlFlight({"WPNAV_SPEED": 1200}, 30.0, "no alarm (200 m survey legs at 12 m/s)",
                                    legs=SURVEY),
    "clean_slow": SitlFlight({"WPNAV_SPEED": 250}, 10.0, "no alarm (stop-and-go at 2.5 m/s)", legs=STOP_GO[:4]),
    "clean_wind": SitlFlight(WIND, 15.0, "no alarm (wind 7 m/s, turbulence 2)"),
    "motor_wind": SitlFlight({**MOTOR, **WIND, "WPNAV_SPEED": 1000}, 20.0,
                             "motor field with current varying in wind and 10 m/s legs: no alarm", legs=STOP_GO,
                             expect="motor"),
    "motor_tromso": SitlFlight({**MOTOR, "WPNAV_SPEED": 800}, 15.0, "motor field at Tromso: no alarm",
                               home=TROMSO, legs=SURVEY[:4], expect="motor"),
    "gps_off_wind": SitlFlight(WIND, 15.0, "no alarm (GPS away 60 s, wind 7 m/s)", home=SOUTH, gps_off=True),
    "gps_off_motor": SitlFlight({**MOTOR, "WPNAV_SPEED": 800}, 20.0, "no alarm (GPS away 60 s, motor field)",
                                home=TROMSO, legs=STOP_GO, gps_off=True, expect="motor"),
}


MAV_CMD_DO_CHANGE_SPEED = 178
FLIGHT_INSTANCES = (*range(10, 15), *range(20, 30))   # 10..14 (UDP 14601 + I) or, beside the suite, 20..29


def flight_port(instance: int) -> int:
    """The station's UDP port for the flights' SITL -I ``instance``: 14601 + I for 10..14, and
    14620 + I for 20..29 (harness.BENCH_PORTS, outside the suite's 14610-14639)."""
    return 14601 + instance if instance < 20 else 14620 + instance


def population_flight(seed: int, k: int) -> tuple[str, SitlFlight]:
    """Clean flight ``k`` of population ``seed``, drawn from wide priors nobody tuned for:
    - site: an inclination drawn uniformly in -60..75 deg, then a random place (|lat| <= 72) whose
      WMM inclination is within 4 deg of it; home altitude 0-600 m; initial heading 0-360 deg;
    - route: 3-5 legs to random points 30-120 m from home (scaled so the legs take about 80-140 s),
      each at its own height (10-40 m) and speed (3-12 m/s), then home; WP_YAW_BEHAVIOR 0, 1 or 2
      (fixed heading, nose to the next point, or nose to it except RTL): headings of every kind;
    - motor field (70 %): SIM_MAG_MOT of 0.5-6 mG/A in a random body direction, COMPASS_MOT
      set to -(0-100 %) of it (0 in a third of them: not compensated), COMPASS_MOTCT 2 (current);
    - wind (50 %): 0-8 m/s from anywhere, turbulence 0-2;
    - a GPS outage (35 %): SIM_GPS1_ENABLE 0 for 20-45 s from the second leg.
    Every draw from numpy's default_rng((seed, k)).  No disturbance: every flight is "no alarm"
    ("motor": the residual field per ampere learnt, no alarm).  Returns (name, flight)."""
    import warnings

    from estimators.geomag import earth_field
    warnings.filterwarnings("ignore", message=".*blackout zone.*")   # the WMM's caution near the poles
    rng = np.random.default_rng((seed, k))
    target = rng.uniform(-60.0, 75.0)
    for _ in range(5000):
        lat, lon = float(rng.uniform(-72.0, 72.0)), float(rng.uniform(-180.0, 180.0))
        inc = earth_field(lat, lon, 0.0, 2026.9).inclination_deg
        if abs(inc - target) <= 4.0:
            break
    home = (round(lat, 4), round(lon, 4), float(round(rng.uniform(0, 600))), float(round(rng.uniform(0, 360))))
    n = int(rng.integers(3, 6))
    bearings = np.sort(rng.uniform(0, 2 * np.pi, n)) + rng.uniform(0, 2 * np.pi)
    pts = [(r * np.cos(b), r * np.sin(b)) for b, r in zip(bearings, rng.uniform(30, 120, n))]
    alts = rng.uniform(10, 40, n + 1)
    speeds = rng.uniform(3, 12, n + 1)
    path = np.vstack([(0.0, 0.0), *pts, (0.0, 0.0)])
    leg_s = float(np.sum(np.hypot(*np.diff(path, axis=0).T) / speeds))
    scale = float(np.clip(rng.uniform(80, 140) / leg_s, 0.5, 2.0))
    legs = tuple((round(float(x * scale), 1), round(float(y * scale), 1), round(float(a), 1), round(float(v), 1))
                 for (x, y), a, v in zip([*pts, (0.0, 0.0)], alts, speeds))
    extra: dict = {"WP_YAW_BEHAVIOR": int(rng.choice([0, 1, 2]))}
    motor, what = None, []
    if rng.uniform() < 0.7:
        d = rng.normal(size=3)
        mot = d / np.linalg.norm(d) * rng.uniform(0.5, 6.0)
        comp = 0.0 if rng.uniform() < 1 / 3 else float(rng.uniform(0.0, 1.0))
        extra.update({f"SIM_MAG_MOT_{a}": round(float(v), 2) for a, v in zip("XYZ", mot)})
        extra.update({f"COMPASS_MOT{sfx}_{a}": round(float(-comp * v), 2) for sfx in ("", "2", "3")
                      for a, v in zip("XYZ", mot)})
        extra["COMPASS_MOTCT"] = 2
        motor = tuple(round(float(extra[f"SIM_MAG_MOT_{a}"] + extra[f"COMPASS_MOT_{a}"]), 2) for a in "XYZ")
        what.append(f"SIM_MAG_MOT {np.linalg.norm(mot):.1f} mG/A, {100 * comp:.0f} % compensated")
    if rng.uniform() < 0.5:
        extra.update({"SIM_WIND_SPD": round(float(rng.uniform(0, 8)), 1),
                      "SIM_WIND_DIR": round(float(rng.uniform(0, 360))),
                      "SIM_WIND_TURB": round(float(rng.uniform(0, 2)), 1)})
        what.append(f"wind {extra['SIM_WIND_SPD']:g} m/s")
    gps_off_s = float(round(rng.uniform(20, 45))) if rng.uniform() < 0.35 else 0.0
    if gps_off_s:
        what.append(f"GPS off {gps_off_s:.0f} s")
    site = f"{home[0]:.1f}, {home[1]:.1f} (inc {earth_field(home[0], home[1], 0.0, 2026.9).inclination_deg:.0f})"
    truth = f"no alarm ({site}; {n + 1} legs; yaw {extra['WP_YAW_BEHAVIOR']}; {'; '.join(what) or 'plain'})"
    return f"pop{seed}_{k}", SitlFlight(extra, float(round(alts[0], 1)), truth, home=home, legs=legs,
                                        gps_off=bool(gps_off_s), gps_off_s=gps_off_s or 60.0,
                                        expect="motor" if motor else "none", motor_truth=motor, site=site)


def _offset(home: tuple, dn: float, de: float) -> tuple[float, float]:
    return home[0] + dn / 111320.0, home[1] + de / (111320.0 * np.cos(np.radians(home[0])))


def run_flight(name: str, out: dict, instance: int | None = 14, flight: SitlFlight | None = None,
               speedup: float = 1.0) -> None:
    """A GUIDED flight at real time (the .tlog's arrival times are wall clock, the .BIN's the
    simulation's: a speedup would squeeze one against the other): takeoff, the scenario's legs,
    land.  Session .tlog and .BIN analysed alike.  ``flight``: FLIGHTS[name] unless given (the
    population's).  SITL instance ``instance`` and its UDP port (``flight_port``; None: the harness
    claims a free pair).  ``speedup`` other than 1 is for the smoke test only (the mechanics, not
    the .tlog's timing)."""
    f = flight or FLIGHTS[name]
    alt = f.alt_m
    res: dict = {"flight": f}
    with sitl_run(out, f"sitl-bench-{name}-", instance, None if instance is None else flight_port(instance),
                  model="quad", speedup=speedup, extra=f.extra,
                  limit_s=600, home=f.home) as (sitl, session, link):
        watch = Watch(link)
        res["armed"] = arm(session, watch)
        command(session, MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt)
        wait_for(lambda: watch.position and watch.position[2] > alt - 1.5, 60)
        if f.anomaly in ("inflight", "descent"):
            time.sleep(5)
            res["anomaly_set_failed"] = set_params(session, ANOMALY)

        def fly_to(dn: float, de: float, a: float, timeout_s: float = 90.0) -> None:
            lat, lon = _offset(f.home, dn, de)
            goto(session, lat, lon, a)
            wait_for(lambda: watch.position and np.hypot((watch.position[0] - lat) * 111320.0,
                                                         (watch.position[1] - lon) * 111320.0 *
                                                         np.cos(np.radians(lat))) < 3
                     and abs(watch.position[2] - a) < 1.5, timeout_s)

        def gps_back() -> None:
            if "gps_off_unix" in res and "gps_on_unix" not in res and time.time() - res["gps_off_unix"] > f.gps_off_s:
                set_params(session, {"SIM_GPS1_ENABLE": 1})
                res["gps_on_unix"] = time.time()
        for i, leg in enumerate(f.legs):
            dn, de = leg[:2]
            a = leg[2] if len(leg) > 2 else alt
            if len(leg) > 3:
                command(session, MAV_CMD_DO_CHANGE_SPEED, 1, leg[3], -1)
            if f.gps_off and i == 1:
                set_params(session, {"SIM_GPS1_ENABLE": 0})
                res["gps_off_unix"] = time.time()
            if f.anomaly == "descent" and i == 1:     # down onto the anomaly and up again, 25 m of track
                fly_to(dn / 2, de / 2, 2.0)
                fly_to(dn / 2 + 25.0, de / 2, alt)
            fly_to(dn, de, a)
            gps_back()
        if f.gps_off and "gps_off_unix" in res:
            wait_for(lambda: time.time() - res["gps_off_unix"] > f.gps_off_s, f.gps_off_s + 10)
            gps_back()
        set_mode(session, COPTER_LAND)
        wait_for(lambda: not watch.armed, 120)
        time.sleep(2)
        # the station's live view: its alarms with their explanation, as the page shows them
        res["live_alarms"] = [(a.get("evidence_text") or "combined", a["start_s"], a.get("explanation_text") or "")
                              for a in session.alarm_list()]
        res["live_sys_status"] = next((m["state"] for m in link.streams_snapshot()["messages"]
                                       if m["name"] == "SYS_STATUS"), None)     # battery current
        if name == "clean":           # a reboot at real time, landed: command to live data again
            restarts = lambda: sum("restarted" in e["text"] for e in session.snapshot()["events"])  # noqa: E731
            before, t0 = restarts(), time.monotonic()
            command(session, MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
            res["stale_seen"] = bool(wait_for(lambda: session.snapshot()["vehicle"]["no_data"], 10, 0.05))
            res["reboot_resume_s"] = resumed_after(session, link, restarts, before, t0)
        res["tlog"] = session.sources.recording_path
        res["events"] = [e["text"] for e in session.snapshot()["events"] if "vehicle:" in e["text"]]
        res["prearm"] = sorted({t for t in res["events"] if "PreArm" in t})[:3]
    res["bin"] = max(sitl.bin_logs(), key=lambda p: p.stat().st_size, default=None)
    if out.get("_keep"):                  # the flight's two logs kept for analysing again
        keep = Path(out["_keep"])
        keep.mkdir(parents=True, exist_ok=True)
        for kind in ("bin", "tlog"):
            if res.get(kind) is not None:
                shutil.copy(res[kind], keep / f"{name}.{'BIN' if kind == 'bin' else 'tlog'}")
    analyse_flight_logs(res)
    out.setdefault("flights", {})[name] = res


def analyse_kept(folder: Path, name: str, out: dict) -> None:
    """``analyse_flight_logs`` on a flight kept by --keep (folder/NAME.BIN, NAME.tlog), its flight
    from its name (FLIGHTS, or popSEED_K: ``population_flight``); no live view, no armed flag."""
    if name.startswith("pop"):
        seed, k = (int(v) for v in name[3:].split("_"))
        flight = population_flight(seed, k)[1]
    else:
        flight = FLIGHTS[name]
    res: dict = {"flight": flight, "armed": "kept"}
    for kind, ext in (("bin", "BIN"), ("tlog", "tlog")):
        if (folder / f"{name}.{ext}").is_file():
            res[kind] = folder / f"{name}.{ext}"
    analyse_flight_logs(res)
    out.setdefault("flights", {})[name] = res


def analyse_flight_logs(res: dict) -> None:
    """analyze on the flight's .BIN and session .tlog (res["bin"], res["tlog"]): alarms on the boot
    clock and on each log's UNIX clock, explanations, motor field, the detector's inputs."""
    from groundstation.io.logs import read_log
    from groundstation.jobs.analyze import analyze_log

    for kind in ("bin", "tlog"):
        if res.get(kind) is None:
            continue
        log = read_log(res[kind])
        summary, _ = analyze_log(log)
        boot = boot_offset_s(res[kind], log)      # the vehicle's boot clock: one time base for both logs
        res[f"{kind}_alarms"] = [(a["kind"], round(boot + a["start_s"], 2)) for a in summary.get("alarms", [])]
        res[f"{kind}_unix_alarms"] = [(a["kind"], round((log.start_unix_s or 0.0) + a["start_s"], 2))
                                      for a in summary.get("alarms", [])]
        res[f"{kind}_explained"] = [(a["kind"], round(boot + a["start_s"], 2), a.get("explanation_text") or "")
                                    for a in summary.get("alarms", []) if a.get("explanation_text")]
        res[f"{kind}_combined"] = [(round(boot + a["start_s"], 1), None if a.get("end_s") is None else
                                    round(boot + a["end_s"], 1), a.get("explanation_text") or "")
                                   for a in summary.get("alarms", []) if a["kind"] == "combined"]
        res[f"{kind}_motor"] = summary.get("motor_field") or {}
        res[f"{kind}_duration"] = log.duration_s
        res[f"{kind}_inputs"] = flight_inputs(log, diagnose=bool(summary.get("alarms")))
    if res.get("tlog") is not None:
        res["tlog_late"] = raw_imu_late_s(res["tlog"])


def raw_imu_late_s(tlog: Path) -> dict:
    """How late the session .tlog's RAW_IMU arrived against the vehicle's clock: per packet its
    arrival minus its time_usec (ArduPilot's boot clock), less the smallest such value up to then
    (the reader's boot-clock anchor, groundstation.io.boot_clock.BootClock).  The reader times RAW_IMU,
    ATTITUDE and the other boot-clocked messages on that clock; SYS_STATUS (the current), VFR_HUD
    and GPS_RAW_INT have no boot time and stay on arrival, so this is how far those stand from the
    compass in the .tlog: it grows for good when the SITL falls behind the wall clock (a loaded
    machine).  {median, p95, max} [s]."""
    from pymavlink import mavutil

    late = []
    conn = mavutil.mavlink_connection(str(tlog))
    try:
        while (m := conn.recv_match(type="RAW_IMU")) is not None:
            if m.get_srcSystem() == 1 and m.time_usec < 1e14:
                late.append(m._timestamp - m.time_usec * 1e-6)
    finally:
        conn.close()
    if not late:
        return {}
    d = np.asarray(late) - np.minimum.accumulate(late)
    return {"median": float(np.median(d)), "p95": float(np.percentile(d, 95)), "max": float(d.max())}


def flight_inputs(log, diagnose: bool = True) -> dict:
    """What the detector is given on a flight log, for the leg-start alarms of clean flights: the
    IMU, compass and attitude rates, the largest tilt the autopilot reports, the largest difference
    between our AHRS's roll/pitch and the autopilot's (which the field tests use only within
    jobs.inputs.TILT_AGREE_DEG of ours), and the alarms analyze gives when the autopilot's tilt is
    taken everywhere (a diagnosis: the limit patched for one call, then restored; only when
    ``diagnose``, i.e. the log alarms: a second analyze of the log)."""
    import groundstation.jobs.inputs as inputs
    from groundstation.jobs.analyze import analyze_log

    def rate(a) -> float | None:
        a = np.asarray(a, dtype=float)
        return float((len(a) - 1) / (a[-1, 0] - a[0, 0])) if len(a) > 2 else None
    x = inputs.detection_inputs(log)
    ch, att = x["chain"], np.asarray(x["att_held"], dtype=float)
    with np.errstate(invalid="ignore"):
        d_tilt = np.degrees(np.maximum(np.abs(np.angle(np.exp(1j * (ch.roll_rad - att[:, 0])))),
                                       np.abs(ch.pitch_rad - att[:, 1])))
        tilt_ap = np.degrees(np.hypot(att[:, 0], att[:, 1]))
    kept, with_ap = inputs.TILT_AGREE_DEG, []
    try:
        inputs.TILT_AGREE_DEG = 90.0
        if diagnose:
            with_ap = analyze_log(log)[0].get("alarms", [])
    finally:
        inputs.TILT_AGREE_DEG = kept
    return {"imu_hz": rate(log.imu), "mag_hz": rate(log.mag), "attitude_hz": rate(log.attitude),
            "max_tilt_deg": float(np.nanmax(tilt_ap)), "max_tilt_diff_deg": float(np.nanmax(d_tilt)),
            "over_limit_s": float(np.sum(d_tilt > kept) / max(rate(log.imu) or 1.0, 1e-9)),
            "alarms_with_autopilot_tilt": [(a["kind"], a["start_s"]) for a in with_ap]}


def alarm_match(a: list, b: list, tol_s: float = 0.5) -> tuple[int, int, float | None]:
    """(alarms of a with an alarm of the same kind in b within tol_s, alarms of a, the largest
    such difference) for two lists of (kind, start on one clock)."""
    diffs = []
    for kind, t in a:
        near = [abs(t - u) for k, u in b if k == kind]
        if near and min(near) <= tol_s:
            diffs.append(min(near))
    return len(diffs), len(a), (max(diffs) if diffs else None)


# Rig spins of the trust scenario: axis (outputs 6/7/8 - 1500) and simulated seconds at 36 deg/s.
TRUST_SPINS = [(100, 0, 0), (0, 100, 0), (0, 0, 100), (100, 100, 0), (100, 0, 100), (0, 100, 100),
               (100, -100, 100), (-100, 100, 100)]
TRUST_SPIN_S, TRUST_RATE_RAD_S = 11.0, np.radians(36.0)
MAG_MESSAGES = {"RAW_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}


def run_trust(speedup: float, out: dict) -> None:
    """Spin the rig about 8 axes with the guided wizard live; calibrate the session .tlog (ours vs
    the truth); write our values, spin again and keep |B| the firmware reports per compass."""
    from estimators.geomag import decimal_year_from_unix, earth_field
    from groundstation.io.logs import read_log
    from groundstation.jobs.calibrate import calibrate_compasses

    field: dict[int, list] = {0: [], 1: [], 2: []}
    keep = {"on": False}

    def hook(_conn, msg) -> None:
        k = MAG_MESSAGES.get(msg.get_type())
        if keep["on"] and k is not None and msg.get_srcSystem() == 1:
            field[k].append(float(np.linalg.norm([msg.xmag, msg.ymag, msg.zmag])))
    with sitl_run(out, "sitl-bench-trust-", 15, 14616,
                  model="calibration", speedup=speedup, extra=RIG_PARAMS, limit_s=400) as (sitl, session, link):
        t0 = time.monotonic()
        session.wizard_start("guided")
        for axis in TRUST_SPINS:
            rig_spin(session, axis, TRUST_RATE_RAD_S)
            time.sleep(TRUST_SPIN_S / speedup)
        rig_stop(session)
        time.sleep(1.0)
        if session.calibration.snapshot()["state"] == "running":     # else finished by itself (coverage)
            session.wizard_finish_now()
        wait_for(lambda: session.calibration.snapshot()["state"] != "running", 30, 0.3)
        out["trust_s"] = time.monotonic() - t0
        wiz = session.calibration.wizard
        out["trust_wizard"] = {k: dict(r) for k, r in (wiz.results or {}).items()}
        out["trust_consistency"] = dict(wiz.consistency or {})
        results = calibrate_compasses(read_log(str(session.sources.recording_path)))
        out["trust_cal"] = {r.get("compass"): r for r in results}
        ours = {n: v for r in results if r.get("status") == "ok"
                for n, v in (r.get("ardupilot_params") or {}).items()
                if n.startswith(("COMPASS_OFS", "COMPASS_DIA", "COMPASS_ODI", "COMPASS_SCALE"))}
        out["trust_write_failed"] = set_params(session, ours) if ours else ["(nothing to write)"]
        link.mav.message_hooks.append(hook)
        rig_spin(session, (100, 100, 100), TRUST_RATE_RAD_S)
        time.sleep(1.0 / speedup + 0.5)
        keep["on"] = True
        time.sleep(12.0 / speedup + 1.0)
        keep["on"] = False
        rig_stop(session)
        out["trust_field_mG"] = {k: float(np.median(v)) if v else None for k, v in field.items()}
        out["trust_wmm_mG"] = float(earth_field(HOME[0], HOME[1], HOME[2],
                                                decimal_year_from_unix(time.time())).field_strength_mG)


def trust_verdict(out: dict) -> list[tuple]:
    """Rows (what, ours, truth, error, pass) of the trust scenario; the checks of the former
    tests/sitl/trust_rig_test.py: offsets within 2 mG, soft iron within 0.01, no misalignment, the
    corrected field within 1 % of the WMM, the wizard without cautions."""
    from groundstation.io.params import ardupilot_matrix

    rows = []
    wmm = out.get("trust_wmm_mG")
    for k in range(3):
        r = out.get("trust_cal", {}).get(k) or {}
        ap = r.get("ardupilot_params") or {}
        t = RIG_TRUTH[k + 1]
        ofs = params_of(ap, k, "OFS")
        err = max(abs(a - b) for a, b in zip(ofs, t["OFS"])) if None not in ofs else None
        rows.append((f"compass {k + 1} offsets mG", ofs, t["OFS"], err, err is not None and err <= 2.0))
        truth = {f"COMPASS_{key}{sfx(k)}_{a}": v for key in ("DIA", "ODI") for a, v in zip("XYZ", t[key])}
        m_err = None if None in params_of(ap, k, "DIA") + params_of(ap, k, "ODI") else \
            float(np.max(np.abs(ardupilot_matrix(ap, k)[1] - ardupilot_matrix(truth, k)[1])))
        rows.append((f"compass {k + 1} soft iron DIA/ODI (max)", r.get("status"), "ok", fmt(m_err, 4),
                     m_err is not None and m_err <= 0.01))
        rows.append((f"compass {k + 1} misalignment deg", r.get("misalignment_deg"), None, None,
                     r.get("misalignment_deg") is None))
        f = (out.get("trust_field_mG") or {}).get(k)
        rel = abs(f / wmm - 1.0) if f and wmm else None
        rows.append((f"compass {k + 1} firmware |B| mG (error %)", f, wmm, None if rel is None else fmt(100 * rel, 3),
                     rel is not None and rel < 0.01))
        w = (out.get("trust_wizard") or {}).get(k) or {}
        rows.append((f"compass {k + 1} wizard: status, cautions, misalignment",
                     f"{w.get('status')}, {w.get('cautions')}, {w.get('misalignment_deg')}", "ok, [], None", None,
                     w.get("status") == "ok" and w.get("cautions") == [] and w.get("misalignment_deg") is None))
    rows.append(("written, confirmed", out.get("trust_write_failed"), [], None, out.get("trust_write_failed") == []))
    rows.append(("wizard consistency", (out.get("trust_consistency") or {}).get("status"), "ok", None,
                 (out.get("trust_consistency") or {}).get("status") == "ok"))
    return rows


def _alarm_text(alarms: list, t0: float) -> str:
    kinds: dict[str, list] = {}
    for kind, unix in alarms:
        kinds.setdefault(kind, []).append(f"{unix - t0:.1f}")
    return "; ".join(f"{k} at {', '.join(v[:4])}{' …' if len(v) > 4 else ''}" for k, v in kinds.items()) or "none"


# ---------------------------------------------------------------------------------- tables
def print_tables(out: dict) -> None:
    st = out.get("streams")
    if st:
        rows = [(m["name"], m["state"], m["rate_hz"], m["acked"], m["why"][:60]) for m in st["messages"]]
        table("1. streams on a stock ArduCopter (the station asks; truth: every consumed stream arrives)",
              ("message", "state", "rate Hz (sim x speedup)", "SET_MESSAGE_INTERVAL", "why"), rows)
    w, ob = out.get("wizard"), out.get("onboard")
    reports = {c["index"]: c["report"] for c in (ob or {}).get("compasses", [])}
    if w:
        ours = w.get("ardupilot_params") or {}
        rows = []
        for k in range(3):
            truth = RIG_TRUTH[k + 1]
            rep = reports.get(k, {})
            for key, rk in (("OFS", "ofs_mG"), ("DIA", "diag"), ("ODI", "offdiag")):
                o = params_of(ours, k, key)
                err = max(abs(a - b) for a, b in zip(o, truth[key])) if None not in o else None
                rep_v = rep.get(rk)
                rep_err = max(abs(a - b) for a, b in zip(rep_v, truth[key])) if rep_v else None
                nd = 2 if key == "OFS" else 4
                rows.append((f"compass {k + 1} {key}", fmt(o, nd), fmt(truth[key], nd), fmt(rep_v, nd), fmt(err, nd),
                             fmt(rep_err, nd)))
        table(f"2. guided wizard on the rig ({out.get('wizard_compasses')} compasses, {out.get('wizard_s', 0):.0f} s wall)"
              " vs the truth vs ArduPilot's onboard calibrator",
              ("", "ours", "truth (SIM_MAGn_*)", "ArduPilot report", "ours - truth (max)", "ArduPilot - truth"), rows)
        rb = out.get("wizard_read_back") or {}
        table("2b. accept, read back, reboot", ("", "ours", "target"),
              [("parameters written", (out.get("write") or {}).get("state"), "written"),
               ("read back equal", f"{rb.get('checked', 0) - len(rb.get('different', []))}/{rb.get('checked', 0)}",
                "all"),
               ("live data after the reboot command [s]", out.get("reboot_resume_s"), "<= 5"),
               ("compass 1 offsets after the reboot", out.get("after_reboot_params", {}).get(0), truth_row(0)),
               ("heading check after the reboot: compass vs bearing [deg]",
                f"{fmt((out.get('heading_check') or {}).get('heading_deg'))} vs "
                f"{fmt((out.get('heading_check') or {}).get('reference_deg'))} (ATTITUDE yaw "
                f"{fmt((out.get('heading_check') or {}).get('attitude_yaw_deg'), 3)})", HEADING_CHECK_YAW_DEG),
               ("heading check error [deg]", (out.get("heading_check") or {}).get("error_deg"), "within 0.5")])
    if ob:
        rows = [(f"compass {c['index'] + 1}", c["report"]["success"], c["report"]["fitness_mG"], c["report"]["ofs_mG"],
                 RIG_TRUTH[c["index"] + 1]["OFS"], out.get("progress_steps", {}).get(c["index"]))
                for c in ob["compasses"]]
        rb = out.get("onboard_read_back")
        rows.append(("accepted, read back", "yes" if rb else "no", None, None, None, None))
        fail, cancel = out.get("fail") or {}, out.get("cancel") or {}
        rows.append(("COMPASS_CAL_FIT 0.001", fail.get("state"), None, [c.get("status_text") for c in
                     fail.get("compasses", [])], "failed", None))
        rows.append(("cancel while running", cancel.get("state") or out.get("cancel_error"), None, None, "cancelled",
                     None))
        table(f"3. the vehicle's calibrator through the station ({out.get('onboard_s', 0):.0f} s wall)",
              ("", "success / state", "fitness mG", "ArduPilot's offsets", "truth", "progress values seen"), rows)
    fy = out.get("fixed_yaw")
    if fy:
        done = fy.get("done") or {}
        rows = []
        for k in range(3):
            truth, veh = fy["truth"][k], (fy.get("vehicle_ofs") or {}).get(k)
            ours = (done.get("ours_ofs_mG") or {}).get(str(k))
            err = lambda v: None if v is None else max(abs(a - b) for a, b in zip(v, truth))  # noqa: E731
            rows.append((f"compass {k + 1} offsets mG", ours, veh, truth, err(ours), err(veh)))
        chk = done.get("check") or {}
        rows.append(("check at the entered yaw: heading error deg, |B| vs WMM mG",
                     f"{fmt(chk.get('heading_error_deg'))}, {fmt(chk.get('strength_mG'), 1)} vs "
                     f"{fmt(chk.get('wmm_strength_mG'), 1)}", done.get("state"), "0, WMM", None, None))
        hc = fy.get("heading_check") or {}
        rows.append(("heading check at 135 deg afterwards", hc.get("heading_deg"), hc.get("attitude_yaw_deg"), 135.0,
                     hc.get("error_deg"), None))
        table(f"7. large-vehicle mode: MAV_CMD_FIXED_MAG_CAL_YAW {FIXED_YAW_DEG:g} deg from the station, rig level "
              "(truth: offsets only)", ("", "ours (same samples)", "ArduPilot (read back)", "truth (SIM_MAGn_OFS)",
                                        "ours - truth (max)", "ArduPilot - truth (max)"), rows)
    if out.get("tlog_cal") or out.get("bin_cal"):
        rows = []
        for k in range(3):
            b = out.get("bin_cal", {}).get(k, {})
            t = out.get("tlog_cal", {}).get(k, {})
            ob_ = params_of(b.get("ardupilot_params") or {}, k, "OFS")
            ot = params_of(t.get("ardupilot_params") or {}, k, "OFS")
            diff = max(abs(x - y) for x, y in zip(ob_, ot)) if None not in ob_ + ot else None
            rows.append((f"compass {k + 1} offsets", ob_, ot, RIG_TRUTH[k + 1]["OFS"], reports.get(k, {}).get("ofs_mG"),
                         diff))
        rows.append(("sources", out.get("bin_sources"), out.get("tlog_sources"), None, None, None))
        rows.append(("alarms (kind@start s)", [f"{a.get('kind')}@{a.get('start_s')}" for a in out.get("bin_alarms", [])],
                     [f"{a.get('kind')}@{a.get('start_s')}" for a in out.get("tlog_alarms", [])], "none", None, None))
        rows.append(("onboard run: reports distinct / MAG_CAL_REPORT messages / start commands",
                     out.get("onboard_bin_reports"), out.get("onboard_tlog_reports"), "[6, -, 3]: success + forced failure, 3 compasses each; the cancel none",
                     None, None))
        table("4. calibrate / analyze / info on the firmware's .BIN vs the station's session .tlog (wizard run)",
              ("", ".BIN", "session .tlog", "truth", "ArduPilot report", ".BIN - .tlog (max) mG"), rows)


def print_flights(out: dict) -> None:
    flights = out.get("flights") or {}
    if not flights:
        return
    rows, match_rows, input_rows, explain_rows = [], [], [], []
    for name, r in flights.items():
        bm, tm = r.get("bin_motor", {}), r.get("tlog_motor", {})
        armed = r.get("armed") if r.get("armed") else f"no: {'; '.join(r.get('prearm') or [])}"
        ba, ta = r.get("bin_alarms", []), r.get("tlog_alarms", [])
        rows.append((name, armed, _alarm_text(ba, 0.0), _alarm_text(ta, 0.0), r["flight"].truth,
                     f"{bm.get('status')} {fmt(bm.get('mG_per_A'))} / {tm.get('status')} {fmt(tm.get('mG_per_A'))}"))
        mb, nb, db = alarm_match(ba, ta)
        mt, nt, dt = alarm_match(ta, ba)
        bu, tu = r.get("bin_unix_alarms", []), r.get("tlog_unix_alarms", [])
        unix_d = [u - v for (k, u), (k2, v) in zip(tu, bu) if k == k2][:3]
        match_rows.append((name, f"{mb}/{nb}", f"{mt}/{nt}", fmt(max(filter(None, (db, dt)), default=None)),
                           fmt(unix_d), "same kinds, start within 0.5 s"))
        for kind in ("bin", "tlog"):
            i = r.get(f"{kind}_inputs") or {}
            input_rows.append((f"{name} {'.BIN' if kind == 'bin' else '.tlog'}", fmt(i.get("imu_hz"), 1),
                               fmt(i.get("mag_hz"), 1), fmt(i.get("attitude_hz"), 1), fmt(i.get("max_tilt_deg"), 1),
                               fmt(i.get("max_tilt_diff_deg"), 1), fmt(i.get("over_limit_s"), 1),
                               _alarm_text(i.get("alarms_with_autopilot_tilt", []), 0.0)))
        for src, alarms in (("analyze .BIN", r.get("bin_explained", [])), ("analyze .tlog", r.get("tlog_explained", [])),
                            ("live view", [(k, t, e) for k, t, e in r.get("live_alarms", [])])):
            kinds = sorted({e.split(";")[0].replace("likely ", "").split(" at ")[0] for _, _, e in alarms if e})
            explain_rows.append((name, src, len(alarms), ", ".join(kinds) or "—"))
    table("5. flights at real time (alarm starts in s of the vehicle's boot clock, both logs)",
          ("flight", "armed", "alarms on the .BIN", "alarms on the session .tlog", "truth",
           "motor field mG/A .BIN / .tlog"), rows)
    table("5a. the same alarms on both logs? (boot clock; UNIX clocks: .tlog - .BIN of paired alarms)",
          ("flight", ".BIN alarms matched", ".tlog alarms matched", "largest matched difference s",
           "UNIX-clock difference s (first 3)", "target"), match_rows)
    table("5c. the detector's inputs (our AHRS vs the autopilot's tilt; alarms with the autopilot's tilt taken "
          "everywhere)", ("log", "IMU Hz", "compass Hz", "attitude Hz", "autopilot max tilt deg",
                          "max |ours - autopilot| roll/pitch deg", "s over TILT_AGREE_DEG",
                          "alarms with the autopilot's tilt"), input_rows)
    table("5d. explanations (motor flight: SIM_MAG_MOT with battery current arriving)",
          ("flight", "where", "alarms explained", "kinds"), explain_rows)
    clean = flights.get("clean")
    if clean and "reboot_resume_s" in clean:
        table("5b. reboot at real time after the clean flight (landed)", ("", "ours", "target"),
              [("'no attitude data' shown meanwhile", clean.get("stale_seen"), True),
               ("live data after the reboot command [s]", clean.get("reboot_resume_s"), "<= 5")])


def print_population(out: dict) -> None:
    """One row per population flight (``--population``): its draw, the combined alarms on the .BIN
    and on the session .tlog (start-end s of the boot clock, explanation), the single-test alarms
    besides, the motor field learnt against what COMPASS_MOT leaves, the .tlog's IMU rate."""
    rows = []
    for name, r in (out.get("flights") or {}).items():
        f = r["flight"]
        if not name.startswith("pop"):
            continue
        mot = [f.extra.get(f"SIM_MAG_MOT_{a}", 0.0) for a in "XYZ"]
        motor = (f"{np.linalg.norm(mot):.1f} -> {np.linalg.norm(f.motor_truth):.1f}" if f.motor_truth else "0")
        learnt = " / ".join(fmt(np.linalg.norm(m["mG_per_A"]), 1) if (m := r.get(f"{k}_motor") or {}).get("mG_per_A")
                            else (m.get("status") or "—") for k in ("bin", "tlog"))

        def comb(kind: str) -> str:
            c = r.get(f"{kind}_combined")
            if c is None:
                return "—"
            return str(len(c)) + "".join(f"; {a:.1f}-{fmt(b, 1)} s {e[:60]}" for a, b, e in c[:2])
        singles = "/".join(str(len([a for a in r.get(f"{k}_alarms", []) if a[0] != "combined"])) for k in ("bin", "tlog"))
        wind = f.extra.get("SIM_WIND_SPD")
        rows.append((name, f.site, f"{len(f.legs)} legs, yaw {f.extra.get('WP_YAW_BEHAVIOR')}", motor,
                     f"{f.gps_off_s:.0f} s" if f.gps_off else "—", f"{wind:g}" if wind is not None else "—",
                     "kept" if r.get("armed") == "kept" else "yes" if r.get("armed") else "no",
                     comb("bin"), comb("tlog"), singles, learnt,
                     fmt((r.get("tlog_inputs") or {}).get("imu_hz"), 1),
                     f"{fmt((r.get('tlog_late') or {}).get('median'))} / {fmt((r.get('tlog_late') or {}).get('max'))}"))
    if rows:
        table("5p. population of clean flights (combined alarms: count; start-end s of the boot clock, explanation)",
              ("flight", "site lat, lon (inclination deg)", "route", "motor field mG/A (SIM_MAG_MOT -> left)",
               "GPS outage", "wind m/s", "armed", "combined .BIN", "combined .tlog", "single-test .BIN/.tlog",
               "motor learnt mG/A .BIN / .tlog", ".tlog IMU Hz", ".tlog RAW_IMU late s median / max"), rows)


def _max_err(vals: list, truths: list) -> float | None:
    pairs = [(v, t) for v, t in zip(vals, truths) if v is not None and None not in v]
    return max((abs(a - b) for v, t in pairs for a, b in zip(v, t)), default=None) if len(pairs) == len(truths) else None


def summary_rows(out: dict) -> list[tuple]:
    """One row per scenario: ours, the truth, ArduPilot's own result, the target, met."""
    rows = []
    st = out.get("streams")
    if st:
        consumed = [m for m in st["messages"] if m["state"] not in ("not asked", "not available")]
        bad = [m["name"] for m in consumed if m["state"] not in ("arriving", "on demand")]
        rows.append(("1 streams (stock Copter)", f"{len(consumed) - len(bad)}/{len(consumed)} arriving or on demand",
                     "all consumed", "MAVn_* rates 0: HEARTBEAT only", "every consumed stream", not bad))
    w = out.get("wizard")
    if w:
        ap = w.get("ardupilot_params") or {}
        reports = {c["index"]: c["report"] for c in (out.get("onboard") or {}).get("compasses", [])}
        e_ofs = _max_err([params_of(ap, k, "OFS") for k in range(3)], [RIG_TRUTH[k + 1]["OFS"] for k in range(3)])
        e_m = _max_err([params_of(ap, k, "DIA") + params_of(ap, k, "ODI") for k in range(3)],
                       [RIG_TRUTH[k + 1]["DIA"] + RIG_TRUTH[k + 1]["ODI"] for k in range(3)])
        r_ofs = _max_err([reports.get(k, {}).get("ofs_mG") for k in range(3)], [RIG_TRUTH[k + 1]["OFS"] for k in range(3)])
        r_m = _max_err([(reports.get(k, {}).get("diag") or [None]) + (reports.get(k, {}).get("offdiag") or [None])
                        for k in range(3)], [RIG_TRUTH[k + 1]["DIA"] + RIG_TRUTH[k + 1]["ODI"] for k in range(3)])
        rows.append(("2 wizard: offsets / DIA,ODI (max error)",
                     f"{out.get('wizard_compasses')} compasses, {fmt(e_ofs)} mG / {fmt(e_m, 4)}", "SIM_MAGn_OFS/DIA/ODI",
                     f"{fmt(r_ofs)} mG / {fmt(r_m, 4)} (scaled to its WMM)", "3 compasses, 2 mG / 0.01",
                     out.get("wizard_compasses") == 3 and e_ofs is not None and e_ofs <= 2 and e_m is not None and e_m <= 0.01))
        hc = out.get("heading_check") or {}
        rows.append(("2 wizard: heading check after the reboot", f"{fmt(hc.get('error_deg'))} deg",
                     f"{HEADING_CHECK_YAW_DEG:g} deg (ATTITUDE {fmt(hc.get('attitude_yaw_deg'), 3)})", "—", "0.5 deg",
                     hc.get("error_deg") is not None and abs(hc["error_deg"]) <= 0.5))
        rows.append(("2 wizard: live data after the reboot (8x)", f"{fmt(out.get('reboot_resume_s'))} s", "—", "—",
                     "5 s", out.get("reboot_resume_s") is not None and out["reboot_resume_s"] <= 5))
    ob = out.get("onboard")
    if ob:
        n_ok = sum(bool(c["report"]["success"]) for c in ob["compasses"])
        rows.append(("3 onboard: reports, accepted, read back", f"{n_ok}/3 shown, read back "
                     f"{'equal' if out.get('onboard_read_back') else 'no'}", "3", f"{n_ok} reports", "all, equal",
                     n_ok == 3 and bool(out.get("onboard_read_back"))))
    if out.get("tlog_cal") and out.get("bin_cal"):
        d = _max_err([params_of(out["bin_cal"].get(k, {}).get("ardupilot_params") or {}, k, "OFS") for k in range(3)],
                     [params_of(out["tlog_cal"].get(k, {}).get("ardupilot_params") or {}, k, "OFS") for k in range(3)])
        rows.append(("4 logs: calibrate .BIN vs .tlog", f"{fmt(d)} mG apart", "same", "—", "1 mG", d is not None and d <= 1))
    fy = out.get("fixed_yaw")
    if fy:
        truths = [fy["truth"][k] for k in range(3)]
        e_ours = _max_err([((fy.get("done") or {}).get("ours_ofs_mG") or {}).get(str(k)) for k in range(3)], truths)
        e_ap = _max_err([(fy.get("vehicle_ofs") or {}).get(k) for k in range(3)], truths)
        hc = fy.get("heading_check") or {}
        rows.append(("7 large vehicle: offsets (max error), heading after", f"{fmt(e_ours)} mG, {fmt(hc.get('error_deg'))} deg",
                     "SIM_MAGn_OFS, 135 deg", f"{fmt(e_ap, 3)} mG", "vehicle 2 mG, 0.5 deg",
                     e_ap is not None and e_ap <= 2 and hc.get("error_deg") is not None and abs(hc["error_deg"]) <= 0.5))
    if "trust_cal" in out:
        tr = trust_verdict(out)
        rows.append(("6 trust (rig spun, real time)", f"{sum(r[4] for r in tr)}/{len(tr)} checks", "SIM truth, WMM",
                     "firmware |B| with ours applied", "all", all(r[4] for r in tr)))
    for name, r in (out.get("flights") or {}).items():
        ba, ta = r.get("bin_alarms", []), r.get("tlog_alarms", [])
        mb, nb, _ = alarm_match(ba, ta)
        mt, nt, _ = alarm_match(ta, ba)
        same = mb == nb and mt == nt
        f = r["flight"]
        if f.expect == "none":
            rows.append((f"5 flight {name}", f"alarms .BIN {nb}, .tlog {nt}", "no alarm", "—", "no alarm; same on both",
                         nb == 0 and nt == 0))
        elif f.expect == "motor":
            m = r.get("bin_motor") or {}
            e = _max_err([m.get("mG_per_A")], [f.motor_truth])
            explained = r.get("bin_explained", []) + r.get("tlog_explained", []) + r.get("live_alarms", [])
            moving = all("moving with current" in x for _, _, x in explained)
            # within 10 %, or 0.1 mG/A of a field COMPASS_MOT nearly removed (the population's)
            learnt = e is not None and e <= max(0.1 * float(np.linalg.norm(f.motor_truth)), 0.1)
            said = "no alarm" if not (nb or nt) else ("every alarm 'moving with current'" if moving
                                                        else "an alarm not explained 'moving with current'")
            rows.append((f"5 flight {name}", f"{fmt(m.get('mG_per_A'))} mG/A ({fmt(e)} off); {said}",
                         f"{list(f.motor_truth)} mG/A", "—",
                         "learnt within 10 % (or 0.1 mG/A); no alarm, or each explained moving with current; "
                         "same on both",
                         learnt and moving and same))
        else:
            kinds = sorted({e.split(";")[0].replace("likely ", "").split(" at ")[0]
                            for _, _, e in r.get("bin_explained", []) + r.get("tlog_explained", []) if e})
            rows.append((f"5 flight {name}", f"alarms .BIN {nb}, .tlog {nt}, matched {mb}/{nb}, {mt}/{nt}; "
                         f"{', '.join(kinds) or 'unexplained'}", f.truth[:40], "—",
                         "alarms, same kinds, start within 0.5 s; fixed in place", same and nb > 0 and
                         "fixed in place" in kinds))
    return rows


def print_notes(out: dict) -> None:
    """What a reader needs when a row misses its target."""
    w = out.get("write") or {}
    if w.get("state") not in (None, "written"):
        print(f"\nwrite: {w.get('state')}: {w.get('message')}; failures {w.get('failures') or w.get('failed')}")
    for kind in ("bin", "tlog"):
        for k, (status, msg) in (out.get(f"{kind}_cal_status") or {}).items():
            if status != "ok":
                print(f"{kind} compass {k + 1}: {status}: {msg}")
    if "wizard" in out and (out.get("reboot_resume_s") is None or out["reboot_resume_s"] > 5):
        print("events of the wizard run (last 15):\n  " + "\n  ".join(out.get("wizard_events", [])[-15:]))


def truth_row(k: int):
    return RIG_TRUTH[k + 1]["OFS"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speedup", type=float, default=8.0)
    ap.add_argument("--only", default="streams,wizard,onboard,logs,fixed_yaw,trust")
    ap.add_argument("--trust-speedup", type=float, default=1.0,
                    help="the trust scenario's speedup (at 8x the wizard finds a 0.55 deg misalignment of every "
                         "compass that real time does not: the station stamps packets at wall time)")
    ap.add_argument("--flights", default="clean,motor,anomaly,gps_off", help="comma-separated of "
                    + ",".join(FLIGHTS) + " (2-4 min each at real time, ~3.5 min with boot and landing); '' for none")
    ap.add_argument("--instance", type=int, default=14, choices=FLIGHT_INSTANCES,
                    help="the flights' SITL instance -I (10..14: UDP port 14601 + it; 20..29, beside the test suite: "
                         "14620 + it): one per process run in parallel")
    ap.add_argument("--population", type=int, default=0, metavar="N",
                    help="also fly N clean flights drawn from wide priors (population_flight: sites, routes, "
                         "headings, speeds, SIM_MAG_MOT with COMPASS_MOT partly set, wind, GPS outages), "
                         "~4 min each at real time, one after the other")
    ap.add_argument("--population-seed", type=int, default=0)
    ap.add_argument("--analyse-kept", metavar="DIR", help="fly nothing: analyse again the flights kept in DIR by "
                    "--keep (NAME.BIN, NAME.tlog; NAME a flight of --flights or popSEED_K) and print their tables")
    ap.add_argument("--population-from", type=int, default=0, metavar="K", help="start at flight K of the population")
    ap.add_argument("--keep", metavar="DIR", help="copy each flight's .BIN and session .tlog here (NAME.BIN, NAME.tlog)")
    args = ap.parse_args()
    if SITL_BINARY is None:
        print(f"skipped: {MISSING}")
        return 0
    only = set(args.only.split(","))
    out: dict = {"_keep": args.keep}
    print(f"# benchmarks/sitl.py --speedup {args.speedup:g}  ({datetime.datetime.utcnow():%Y-%m-%d %H:%M} UTC)")
    runs = []
    if only & {"streams", "onboard", "wizard"}:
        runs.append(("onboard", lambda: run_onboard(args.speedup, out)))
    if only & {"wizard", "logs"}:
        runs.append(("wizard", lambda: run_wizard(args.speedup, out)))
    if "logs" in only:
        runs.append(("logs", lambda: run_logs(out)))
    if "fixed_yaw" in only:
        runs.append(("fixed_yaw", lambda: run_fixed_yaw(args.speedup, out)))
    if "trust" in only:
        runs.append(("trust", lambda: run_trust(args.trust_speedup, out)))
    for name in filter(None, args.flights.split(",")):
        if name not in FLIGHTS:
            print(f"unknown flight {name!r}: one of {', '.join(FLIGHTS)}")
            return 2
        runs.append((f"flight {name}", lambda name=name: run_flight(name, out, args.instance)))
    for k in range(args.population_from, args.population_from + args.population):
        name, flight = population_flight(args.population_seed, k)
        runs.append((f"flight {name}", lambda name=name, flight=flight: run_flight(name, out, args.instance, flight)))
    if args.analyse_kept:
        runs = [(f"flight {name}", lambda name=name: analyse_kept(Path(args.analyse_kept), name, out))
                for name in sorted({p.stem for p in Path(args.analyse_kept).glob("*.BIN")},
                                   key=lambda n: (n.startswith("pop"), n.split("_")[0], int(n.split("_")[-1])
                                                  if n.startswith("pop") else 0, n))]
    for what, run in runs:            # one scenario failing does not lose the others' figures
        try:
            run()
        except Exception as err:      # noqa: BLE001 (reported, the run goes on)
            print(f"{what}: failed: {type(err).__name__}: {err}"[:300])
        r = (out.get("flights") or {}).get(what.removeprefix("flight "))
        if what.startswith("flight ") and r is not None:   # as it goes: a long run cut short keeps its figures
            print(f"{what} ({datetime.datetime.utcnow():%H:%M} UTC): {r['flight'].truth}; armed {r.get('armed')}; "
                  f"combined .BIN {r.get('bin_combined')}, .tlog {r.get('tlog_combined')}; all .BIN "
                  f"{r.get('bin_alarms')}, .tlog {r.get('tlog_alarms')}; motor .BIN "
                  f"{(r.get('bin_motor') or {}).get('mG_per_A')} .tlog {(r.get('tlog_motor') or {}).get('mG_per_A')} "
                  f"(truth {r['flight'].motor_truth if r['flight'].expect == 'motor' else None})", flush=True)
    print_tables(out)
    if "trust_cal" in out:
        rows = trust_verdict(out)
        table(f"6. trust: the rig spun about 8 axes at {args.trust_speedup:g}x ({out.get('trust_s', 0):.0f} s wall): "
              "ours vs the truth, "
              "the firmware's corrected field vs the WMM", ("", "ours", "truth", "error", "pass"), rows)
        failed = [r[0] for r in rows if not r[4]]
        print(f"\ntrust: {len(rows) - len(failed)}/{len(rows)} pass" + (f"; failed: {failed}" if failed else ""))
    print_flights(out)
    print_population(out)
    rows = summary_rows(out)
    table("summary: per scenario, ours vs the truth vs ArduPilot's own result",
          ("scenario", "ours", "truth", "ArduPilot's own", "target", "met"), rows)
    print(f"\n{sum(bool(r[5]) for r in rows)}/{len(rows)} targets met")
    clean = [n for n, r in (out.get("flights") or {}).items() if r["flight"].expect in ("none", "motor")]
    if clean:
        alarmed = [n for n in clean if out["flights"][n].get("bin_alarms") or out["flights"][n].get("tlog_alarms")]
        print(f"clean SITL flights (no disturbance): {len(clean)}, with a combined alarm on the .BIN or .tlog: "
              f"{len(alarmed)} {alarmed}")
    print_notes(out)
    for d in out.get("_dirs", []):          # SITL run folders and session recordings, once analysed
        shutil.rmtree(d, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
