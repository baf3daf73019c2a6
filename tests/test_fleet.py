"""Fleet review pieces without a cluster: the per-log row against a simulated flight's truth, the
SQLite history, the airframe mapping, the fleet findings on synthetic histories, the per-log
timeout, and the station's read-only fleet router.  (tests/test_fleet_cluster.py runs `review`
through real Dask clusters.)"""
from __future__ import annotations

import json
import sqlite3
import threading
import time
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from groundstation.io import fleet_db
from groundstation.jobs.airframes import load_airframes, resolve_airframe
from groundstation.jobs.compass_history import DriftSettings, analyse_fleet, record_calibration, refresh_alerts
from groundstation.jobs.fleet import discover_logs, run_job_with_timeout
from groundstation.jobs.review_row import ATTITUDE_ALARMS, ATTITUDE_RESIDUALS, ROW_VERSION, alarm_fields, review_log
from groundstation.sim.fleet import FleetSettings, Site, plan_fleet, write_flight
from groundstation.sim.fleet_score import score_review
from groundstation.station.routers import fleet as fleet_router

from conftest import SHARED_DATA, needs_shared

DAY = 86400.0


# ------------------------------------------------------------------------------ the per-log row
@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Three flights (random bearings) of one drifting vehicle at an anomaly-free site."""
    settings = FleetSettings(vehicles=1, flights=4, drift_vehicles=1, payload_vehicles=0, flight_s=(75.0, 85.0),
                             interference_fraction=0.0, sites=(Site("base", 30.26, 120.12),), seed=5)
    plans, truth = plan_fleet(settings)
    out = tmp_path_factory.mktemp("flights")
    entries = [write_flight(p, out) for p in plans[1:]]
    return [(out / e["file"], e) for e in entries]


@pytest.fixture(scope="module")
def one_flight(flights):
    return flights[-1]


def test_review_row_recovers_offset_change_and_motor_field(flights):
    errors, motor_errors, changes = [], [], []
    for path, truth in flights:
        (r,) = review_log(path)
        assert r["status"] == "ok" and r["fit_status"] == "ok" and r["fit_model"] == "yaw_free", r
        true_change = np.array(truth["offsets_change_mG"])
        fit_change = np.array([r[f"ofs_change_{a}_mG"] for a in "xyz"])
        errors.append(np.linalg.norm(fit_change - true_change))
        changes.append(fit_change)
        motor = np.array([r[f"motor_{a}_mG_per_A"] for a in "xyz"])
        motor_errors.append(np.linalg.norm(motor - truth["motor_mG_per_A"]) / np.linalg.norm(truth["motor_mG_per_A"]))
    planted = np.array(flights[-1][1]["offsets_change_mG"]) - flights[0][1]["offsets_change_mG"]
    assert np.linalg.norm(planted) > 30.0                                   # the drift between first and last
    assert np.linalg.norm((changes[-1] - changes[0]) - planted) < 0.5 * np.linalg.norm(planted)
    assert np.median(errors) < 20.0, errors
    assert max(motor_errors) < 0.35, motor_errors


def test_review_row_is_the_calibrate_jobs_fit(one_flight):
    """One way to fit: the row's offsets and motor field are jobs.calibrate's for that compass, against the
    same reference field (the WMM with its inclination refined from the flight)."""
    from groundstation.io.logs import read_log
    from groundstation.jobs.calibrate.compass import calibrate_compass
    from groundstation.jobs.calibrate.context import log_context
    from groundstation.jobs.calibrate.reference import refine_reference
    from groundstation.jobs.compass_raw import compass_fields
    from groundstation.jobs.review_row import REVIEW_CALIBRATE

    path, _ = one_flight
    (r,) = review_log(path)
    log = read_log(path)
    (cf,) = compass_fields(log)
    ctx = refine_reference(log, [cf], log_context(log), REVIEW_CALIBRATE)
    result, _ = calibrate_compass(log, cf, ctx, REVIEW_CALIBRATE)
    refined = ctx.field_refinement
    if refined["flight_estimate_mG"] is not None:
        assert r["field_inclination_deg"] == refined["inclination_deg"]
        assert r["field_inclination_sd_deg"] == refined["inclination_sd_deg"] < 0.3
    else:
        assert r["field_inclination_deg"] is None
    assert [r[f"fit_ofs_{a}_mG"] for a in "xyz"] == pytest.approx(result["inflight"]["offsets_mG"], abs=0.01)
    assert [r[f"motor_{a}_mG_per_A"] for a in "xyz"] == pytest.approx(result["motor"]["motor_mG_per_unit"], abs=0.001)
    assert r["interference_pct"] == result["motor"]["interference_pct"] and r["motor_status"] == "ok"
    assert [r[f"cal_ofs_{a}_mG"] for a in "xyz"] == pytest.approx(cf.offsets_in_force_mG[-1], abs=0.01)


def test_review_row_fields(one_flight):
    path, truth = one_flight
    (r,) = review_log(path)
    assert r["identity"] == f"serial:{truth['serial']}" and r["autopilot"] == "ardupilot" and r["sysid"] == 1
    assert np.allclose([r[f"cal_ofs_{a}_mG"] for a in "xyz"], truth["calibration_offsets_mG"], atol=0.01)
    assert r["cal_state"] == "ok" and r["alarm_count"] == 0 and r["compasses"] == 1
    assert abs(r["duration_s"] - truth["duration_s"]) < 0.1 and r["mag_rate_hz"] == pytest.approx(50.0, abs=0.5)
    assert r["date"].startswith("2026-01-0") and abs(r["lat_deg"] - 30.26) < 0.01
    assert abs(r["strength_resid_mG"]) < 60 and r["wmm_strength_mG"] == pytest.approx(489, abs=3)
    assert len(r["log_hash"]) == 64 and r["review_s"] > 0 and r["row_version"] == ROW_VERSION
    assert r["fit_model"] == "yaw_free" and r["compass_source"] and r["fit_heading_coverage"] > 0.9
    # which attitude each part used: alarms on the causal AHRS, residuals on the autopilot's ATTITUDE
    assert r["attitude_source"] == f"{ATTITUDE_ALARMS}; {ATTITUDE_RESIDUALS}"


def test_review_row_for_bad_files_is_an_error_row_not_an_exception(tmp_path):
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    for path, text in ((empty, "empty"), (garbage, "no readable messages")):
        (r,) = review_log(path)
        assert r["status"] == "error" and text in r["error"], r
        assert len(r["log_hash"]) == 64
    (r,) = review_log(tmp_path / "missing.tlog")
    assert r["status"] == "error" and "missing.tlog" in r["error"]


def test_review_row_skips_known_hash(one_flight):
    path, _ = one_flight
    (first,) = review_log(path)
    (again,) = review_log(path, skip_hashes={first["log_hash"]})
    assert again == {"log_hash": first["log_hash"], "path": str(path), "status": "skipped"}


def test_every_combined_alarm_is_kept_and_an_event_after_an_earlier_alarm_is_found():
    """An earlier alarm of the flight (37.8 s) must not hide the interference event's own (54.5 s):
    the row keeps every combined alarm, the scorer looks at all of them (AF-07/flight-039 of the
    20 × 50 fleet was missed when only the first alarm was kept)."""
    report = {"first_alarm_s": 37.76, "alarms": [
        {"kind": "path_deviation", "start_s": 34.72, "end_s": 37.9},
        {"kind": "combined", "start_s": 37.76, "end_s": 39.9, "evidence": ["path_deviation"]},
        {"kind": "combined", "start_s": 54.54, "end_s": None, "evidence": ["heading_difference", "field_anomaly"]}]}
    fields = alarm_fields(report)
    assert fields["alarm_count"] == 2 and fields["first_alarm_s"] == 37.76
    assert json.loads(fields["alarm_intervals_s"]) == [[37.76, 39.9, "path_deviation"],
                                                       [54.54, None, "heading_difference+field_anomaly"]]
    row = dict(fleet_db.empty_row(), path="/fleet/AF-07/flight-039.tlog", status="ok", **fields)
    truth = {"vehicles": [], "sites": [], "corrupt": [], "flights": [
        {"file": "AF-07/flight-039.tlog", "site": "river", "interference": {"onset_s": 52.58, "end_s": 68.58}}]}
    found = score_review(truth, [row], [])["interference"]
    assert (found["found"], found["median_delay_s"]) == (1, pytest.approx(1.96))
    first_only = dict(row, alarm_intervals_s=None)                 # a row of the older job: first alarm only
    assert score_review(truth, [first_only], [])["interference"]["missed"] == ["AF-07/flight-039.tlog"]


def test_rows_of_an_older_job_version_are_reviewed_again(tmp_path):
    with closing(fleet_db.connect(tmp_path / "h.sqlite")) as con:
        fleet_db.upsert_rows(con, [dict(fleet_db.empty_row(), log_hash=h, compass=0, status="ok", path=h, row_version=v)
                                   for h, v in (("old", ROW_VERSION - 1), ("new", ROW_VERSION), ("none", None))])
        assert set(fleet_db.known_hashes(con, only_ok=True)) == {"old", "new", "none"}
        assert set(fleet_db.known_hashes(con, only_ok=True, min_row_version=ROW_VERSION)) == {"new"}


@needs_shared("px4-pyulog/sample.ulg")
def test_review_row_on_real_logs():
    (r,) = review_log(SHARED_DATA / "px4-pyulog" / "sample.ulg")          # attitude, no magnetometer
    assert r["status"] == "no_mag" and r["autopilot"] == "px4" and r["sysid"] == 1
    rows = review_log(SHARED_DATA / "dronekit" / "flight_replay_flight.tlog")     # RAW_IMU and SCALED_IMU2
    assert [r["compass"] for r in rows] == [0, 1] and {r["compasses"] for r in rows} == {2}
    assert len({r["log_hash"] for r in rows}) == 1 and len({r["device_id"] for r in rows}) == 2
    # in-flight WMM fit: compass 1 (unused by the vehicle) is an answer with its 1σ, not recommended
    assert all(r["fit_status"] in ("ok", "weak") and r["fit_ofs_x_mG"] is not None for r in rows)
    assert rows[0]["fit_status"] == "ok"
    r = rows[0]
    assert r["status"] == "ok" and r["autopilot"] == "ardupilot" and r["motor_status"] == "ok"
    assert r["corrupt_packets"] > 1000 and "corrupt" in r["warnings"]       # the radio link's damage, counted
    assert r["identity_source"] == "folder" and r["identity"] == "folder:dronekit"
    assert r["mag_rate_hz"] < 5.0 and r["max_gap_s"] > 1.0


def test_discover_logs_recursive_and_sorted(tmp_path):
    for name in ("a/x.tlog", "a/b/y.BIN", "c.ulg", "d.csv", "e.txt", ".hidden/z.tlog"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"1")
    found = [p.relative_to(tmp_path).as_posix() for p in discover_logs([tmp_path, tmp_path / "c.ulg"])]
    assert found == ["a/b/y.BIN", "a/x.tlog", "c.ulg", "d.csv"]
    with pytest.raises(FileNotFoundError):
        discover_logs([tmp_path / "nope"])


# ------------------------------------------------------------------------------ per-log timeout
def _hangs(path, *args):
    while True:            # a reader stuck in a pure-Python loop
        time.sleep(0.001)


def test_job_past_its_timeout_gives_a_timeout_row_and_stops():
    before = threading.active_count()
    t0 = time.perf_counter()
    (r,) = run_job_with_timeout(_hangs, "/logs/hung.tlog", 0.3)
    assert time.perf_counter() - t0 < 3.0
    assert r["status"] == "timeout" and "0.3 s" in r["error"] and r["file_name"] == "hung.tlog"
    time.sleep(0.1)
    assert threading.active_count() == before          # the job's thread was interrupted, not left running


# ------------------------------------------------------------------------------ history + mapping
def _row(airframe: str, k: int, ofs, motor=(1.0, 0.5, -1.5), lat=30.26, lon=120.12, strength=0.0, **extra) -> dict:
    r = fleet_db.empty_row()
    r.update(log_hash=f"{airframe}-{k:03d}-{lat}", compass=0, path=f"/fleet/{airframe}/flight-{k:03d}.tlog",
             file_name=f"flight-{k:03d}.tlog", status="ok", airframe=airframe, identity=f"folder:{airframe}",
             start_unix_s=1.77e9 + k * DAY, date=f"day {k}", duration_s=80.0, lat_deg=lat, lon_deg=lon,
             fit_status="ok", strength_resid_mG=strength, inclination_resid_deg=strength / 20.0,
             current_max_A=25.0, wmm_strength_mG=490.0, alarm_count=0, **extra)
    for a, v in zip("xyz", ofs):
        r[f"fit_ofs_{a}_mG"] = float(v)
        r[f"fit_ofs_sd_{a}_mG"] = 0.5
        r[f"cal_ofs_{a}_mG"] = 0.0
    for a, v in zip("xyz", motor):
        r[f"motor_{a}_mG_per_A"] = float(v)
    r["interference_pct"] = float(np.linalg.norm(motor)) * 25.0 / 490.0 * 100.0
    return r


def _synthetic_fleet(seed: int = 1, flights: int = 40) -> list[dict]:
    """Six airframes, 4 mG flight-to-flight scatter: AF-1 drifts 50 mG, AF-2 gets a payload at
    flight 20, everyone visits a site 20 km away whose local field adds (0, 0, 40) mG."""
    rng = np.random.default_rng(seed)
    rows = []
    for a in range(6):
        base = rng.uniform(-150, 150, 3)
        drift = np.array([30.0, -40.0, 0.0]) / (flights - 1) if a == 1 else np.zeros(3)
        for k in range(flights):
            anomaly = k % 4 == 3
            ofs = base + drift * k + rng.normal(0, 4.0, 3) + (np.array([0, 0, 40.0]) if anomaly else 0.0)
            motor = np.array([1.0, 0.5, -1.5]) + (np.array([1.5, 1.5, 0.5]) if a == 2 and k >= 20 else 0.0)
            rows.append(_row(f"AF-{a}", k, ofs, motor + rng.normal(0, 0.05, 3), lat=30.44 if anomaly else 30.26,
                             strength=(40.0 if anomaly else 0.0) + rng.normal(0, 3.0)))
    return rows


def test_findings_on_a_synthetic_history():
    f = analyse_fleet(_synthetic_fleet())
    kinds = {(a["kind"], a["airframe"]) for a in f.alerts}
    assert ("offset_drift", "AF-1") in kinds
    assert not [k for k in kinds if k[0] == "offset_drift" and k[1] != "AF-1"], kinds
    payload = [a for a in f.alerts if a["kind"] == "payload_change"]
    assert [a["airframe"] for a in payload] == ["AF-2"]
    assert payload[0]["log_hash"].startswith("AF-2-02")                         # flight 20 ± 1
    anomaly = [a for a in f.alerts if a["kind"] == "anomaly_site"]
    assert len(anomaly) == 1 and abs(anomaly[0]["lat_deg"] - 30.44) < 0.01 and abs(anomaly[0]["value"] - 40) < 5
    assert len(f.sites) == 2


def test_no_false_drift_alerts_on_steady_noise():
    """The statistical threshold: 100 steady airframes × 40 flights of 4 mG scatter, no alert."""
    rng = np.random.default_rng(7)
    rows = [_row(f"S{a}", k, rng.normal(0, 4.0, 3)) for a in range(100) for k in range(40)]
    f = analyse_fleet(rows, settings=DriftSettings(floor_mG=0.0))      # the sigma test alone
    assert not [a for a in f.alerts if a["kind"] in ("offset_drift", "payload_change")]


def test_a_calibration_starts_a_new_segment_and_changes_are_alerted(tmp_path):
    db = tmp_path / "fleet.sqlite"
    rows = [_row("AF-9", k, (10.0 + (40.0 if k >= 12 else 0.0), 0.0, 0.0)) for k in range(24)]
    with closing(fleet_db.connect(db)) as con:
        fleet_db.upsert_rows(con, rows)
        assert [a["kind"] for a in refresh_alerts(con).alerts] == ["offset_drift"]
    t_cal = rows[12]["start_unix_s"] - 3600.0         # a calibration just before the offsets moved
    first = record_calibration(db, "AF-9", {"offsets_mG": [10.0, 0.0, 0.0], "matrix": np.eye(3).tolist(),
                                            "residual_rms_mG": 2.0}, unix_s=t_cal - 5 * DAY)
    second = record_calibration(db, "AF-9", {"offsets_mG": [50.0, 0.0, 0.0], "matrix": np.eye(3).tolist(),
                                             "residual_rms_mG": 2.0, "expected_field_mG": 489.0}, unix_s=t_cal)
    assert first["id"] == 1 and second["id"] == 2
    kinds = sorted(a["kind"] for a in second["alerts"])
    assert kinds == ["calibration_change"], second["alerts"]      # the drift is explained by the calibration
    with closing(fleet_db.connect(db, read_only=True)) as con:
        cals = fleet_db.calibration_rows(con, "AF-9")
        assert [c["ofs_x_mG"] for c in cals] == [10.0, 50.0] and cals[1]["wmm_strength_mG"] == 489.0
        with pytest.raises(sqlite3.OperationalError):
            con.execute("DELETE FROM calibrations")
    with pytest.raises(ValueError):
        record_calibration(db, "AF-9", {"status": "insufficient_coverage", "offsets_mG": None})


def test_history_is_readable_while_written(tmp_path):
    db = tmp_path / "fleet.sqlite"
    with pytest.raises(FileNotFoundError):
        fleet_db.connect(db, read_only=True)
    writer = fleet_db.connect(db)
    fleet_db.upsert_rows(writer, [_row("A", 0, (1, 2, 3))])
    reader = fleet_db.connect(db, read_only=True)
    writer.execute("BEGIN")
    writer.execute("UPDATE flights SET airframe = 'B'")
    assert [r["airframe"] for r in fleet_db.flight_rows(reader)] == ["A"]     # WAL: the reader is not blocked
    writer.commit()
    assert [r["airframe"] for r in fleet_db.flight_rows(reader)] == ["B"]
    failed = dict(_row("A", 1, (0, 0, 0)), log_hash="error:/fleet/A/flight-001.tlog", status="error")
    fleet_db.upsert_rows(writer, [failed])
    fleet_db.upsert_rows(writer, [_row("A", 1, (0, 0, 0))])                   # reviewed fine later
    assert sorted(r["status"] for r in fleet_db.flight_rows(reader)) == ["ok", "ok"]
    writer.close(), reader.close()


def test_airframe_mapping_json_and_csv(tmp_path):
    js = tmp_path / "m.json"
    js.write_text(json.dumps({"airframes": [
        {"match": {"serial": 7100}, "airframe": "hexa-1", "payload": "camera"},
        {"match": {"serial": "7100"}, "airframe": "hexa-1", "payload": "lidar", "from_date": "2026-02-01"},
        {"match": {"path": "*/spare/*"}, "airframe": "spare"}]}))
    entries = load_airframes(js)
    row = {"serial": "7100", "start_unix_s": 1.7696e9, "path": "/x/flight.tlog", "identity": "serial:7100"}
    assert resolve_airframe(row, entries) == ("hexa-1", "camera")              # 2026-01-28
    assert resolve_airframe(dict(row, start_unix_s=1.7702e9), entries) == ("hexa-1", "lidar")
    assert resolve_airframe({"path": "/logs/spare/a.bin", "identity": "folder:spare"}, entries) == ("spare", None)
    assert resolve_airframe({"serial": "1", "identity": "serial:1"}, entries) == ("serial:1", None)
    csv = tmp_path / "m.csv"
    csv.write_text("key,airframe,payload,from_date\nsysid:3,quad-3,,\nfolder:AF-07,AF-07,lidar,\n")
    entries = load_airframes(csv)
    assert resolve_airframe({"sysid": 3, "identity": "sysid:3"}, entries) == ("quad-3", None)
    assert resolve_airframe({"path": "/f/AF-07/x.tlog", "identity": "?"}, entries) == ("AF-07", "lidar")
    csv.write_text("key,airframe\nserial7100,x\n")
    with pytest.raises(ValueError, match="line 2"):
        load_airframes(csv)
    js.write_text(json.dumps({"airframes": [{"match": {"colour": "red"}, "airframe": "x"}]}))
    with pytest.raises(ValueError, match="unknown match key"):
        load_airframes(js)


def test_vehicle_identity_order_and_the_station_helper(tmp_path):
    from groundstation.jobs.airframes import airframe_for_vehicle, identity_key
    from groundstation.jobs.review_row import vehicle_identity
    from groundstation.samples import FlightLog, StatusSample

    log = FlightLog("x", params={"SYSID_THISMAV": 1.0, "BRD_SERIAL_NUM": 0.0})
    log.status.append(StatusSample(1.0, "statustext", "CubeOrange 00360024 3039510c 30393437"))
    ident = vehicle_identity(log, Path("/logs/hexa/a.tlog"))
    assert ident["identity"] == "uid:00360024 3039510C 30393437" and ident["identity_source"] == "board_uid"
    assert identity_key({"MAV_SYS_ID": 7.0})["identity"] == "sysid:7"
    assert identity_key({"SYSID_THISMAV": 1.0}, folder="hexa")["identity"] == "folder:hexa"   # default sysid 1
    assert identity_key({"BRD_SERIAL_NUM": 7100.0, "SYSID_THISMAV": 4.0})["identity"] == "serial:7100"
    (tmp_path / "m.json").write_text(json.dumps({"airframes": [{"match": {"sysid": 4}, "airframe": "quad-4"}]}))
    entries = load_airframes(tmp_path / "m.json")
    assert airframe_for_vehicle({"SYSID_THISMAV": 4.0}, entries) == "quad-4"
    assert airframe_for_vehicle({"SYSID_THISMAV": 5.0}, entries) == "sysid:5"



# ------------------------------------------------------------------------------ station router
@pytest.fixture
def fleet_app(tmp_path):
    db = tmp_path / "fleet.sqlite"
    app = FastAPI()
    app.include_router(fleet_router.router)
    app.state.fleet_db_path = db
    return TestClient(app), db


def test_fleet_router_reads_the_history(fleet_app):
    client, db = fleet_app
    res = client.get("/api/fleet/summary")
    assert res.status_code == 404 and "run `magstation review`" in res.json()["detail"]
    with closing(fleet_db.connect(db)) as con:
        fleet_db.upsert_rows(con, _synthetic_fleet(flights=24))
        refresh_alerts(con)
    s = client.get("/api/fleet/summary").json()
    assert s["flights"] == 6 * 24 and len(s["airframes"]) == 6 and len(s["sites"]) == 2
    assert {"offset_drift", "payload_change", "anomaly_site"} <= {a["kind"] for a in s["alerts"]}
    h = client.get("/api/fleet/airframes/AF-1").json()
    assert len(h["flights"]) == 24 and h["flights"][0]["start_unix_s"] < h["flights"][-1]["start_unix_s"]
    assert client.get("/api/fleet/airframes/nope").status_code == 404
    worst = client.get("/api/fleet/flights", params={"limit": 5}).json()
    assert len(worst) == 5 and all(w["site"] for w in worst)
    assert client.get("/api/fleet/flights", params={"limit": 0}).status_code == 422
    assert client.post("/api/fleet/summary").status_code == 405                 # read-only


def test_station_app_serves_the_fleet_page_and_router(tmp_path, monkeypatch):
    """The fleet router is in the station's ROUTERS (behind require_operator); its history is the
    recordings folder's fleet.sqlite unless $MAGSTATION_FLEET_DB names another."""
    from groundstation.station.app import ROUTERS, create_app
    from groundstation.station.hub.session import Session

    assert fleet_router in ROUTERS
    monkeypatch.delenv("MAGSTATION_FLEET_DB", raising=False)
    session = Session(tmp_path, record_live=False)
    try:
        client = TestClient(create_app(session), base_url="http://127.0.0.1")
        missing = client.get("/api/fleet/summary")
        assert missing.status_code == 404 and fleet_db.DB_NAME in missing.json()["detail"]
        with closing(fleet_db.connect(tmp_path / fleet_db.DB_NAME)) as con:
            fleet_db.upsert_rows(con, [dict(fleet_db.empty_row(), log_hash="b" * 64, compass=0, status="ok",
                                            airframe="AF-09", start_unix_s=1.0)])
        assert [a["airframe"] for a in client.get("/api/fleet/summary").json()["airframes"]] == ["AF-09"]
        cross = client.get("/api/fleet/summary", headers={"Sec-Fetch-Site": "cross-site"})
        assert cross.status_code == 403                                       # never answered to another site
        monkeypatch.setenv("MAGSTATION_FLEET_DB", str(tmp_path / "none.sqlite"))
        assert client.get("/api/fleet/summary").status_code == 404          # path from the environment
        page = client.get("/fleet.html")
        assert page.status_code == 200 and "fleet.js" in page.text
    finally:
        session.close()


def test_cli_errors_are_one_line(tmp_path, capsys):
    from groundstation.cli import main

    (tmp_path / "empty").mkdir()
    bad_map = tmp_path / "m.csv"
    bad_map.write_text("key,airframe\nnokey,x\n")
    log = tmp_path / "a.tlog"
    log.write_bytes(b"1")
    cases = [(["review", str(tmp_path / "empty")], "no .tlog/.bin/.ulg/.csv logs"),
             (["review", str(tmp_path / "missing")], "no such file or folder"),
             (["review", str(log), "--scheduler", "nohost"], "expected tcp://HOST:PORT"),
             (["review", str(log), "--airframes", str(bad_map)], "must look like serial:7100"),
             (["review", str(log), "--workers", "0"], "at least 1"),
             (["simulate", "fleet", "--vehicles", "0", "--out", str(tmp_path / "f")], "at least 1 vehicle")]
    for argv, text in cases:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and text in err and "Traceback" not in err, (argv, err)


# ------------------------------------------------------------------ the station records what it writes
def _wait_until(read, done, timeout_s: float):
    """``read()`` polled until ``done`` holds of it or the time is up; the last value read."""
    deadline = time.monotonic() + timeout_s
    value = read()
    while not done(value) and time.monotonic() < deadline:
        time.sleep(0.05)
        value = read()
    return value


def test_a_calibration_written_to_the_vehicle_enters_its_airframe_history(tmp_path, monkeypatch):
    """The wizard's result written to an ArduPilot fake vehicle (PARAM_SET confirmed by echo) is
    appended to the compass history in the recordings folder, under the airframe name the review
    gave that board serial, with every compass's offsets, matrix, fitness, WMM field and place."""
    from conftest import free_udp_port
    from groundstation.sim.fake_autopilot import default_params
    from groundstation.sim.fake_vehicle import FakeVehicle
    from groundstation.sim.vehicle_streams import guided_dance_attitude, make_hardware, pack_stream, three_compasses
    from groundstation.station.hub.session import Session

    monkeypatch.delenv("MAGSTATION_FLEET_DB", raising=False)
    db = tmp_path / fleet_db.DB_NAME
    with closing(fleet_db.connect(db)) as con:           # the review saw this board as AF-07
        fleet_db.upsert_rows(con, [dict(fleet_db.empty_row(), log_hash="a" * 64, compass=0, status="ok",
                                        identity="serial:4242", airframe="AF-07", start_unix_s=1.0)])
    hw = make_hardware(three_compasses())
    params = default_params("ardupilot", 3) | {"BRD_SERIAL_NUM": 4242.0}
    session = Session(tmp_path, record_live=False)
    port = free_udp_port()
    session.connect(f"udpin:127.0.0.1:{port}")
    session.wizard_start()
    fv = FakeVehicle(pack_stream(guided_dance_attitude(rate_hz=12.5), hw), port, speed=8.0, params=params).start()
    try:
        w = _wait_until(lambda: session.snapshot()["wizard"], lambda w: w["state"] == "result", 90.0)
        assert w["state"] == "result" and w["result"]["status"] == "ok", w["result"]
        assert session.wizard_accept()["state"] == "checking"      # re-reads the parameters, then writes
        _wait_until(lambda: list(session.events), lambda ev: any("fleet history" in e["text"] for e in ev), 30.0)
        pw = session.snapshot()["wizard"]["param_write"]
        events = [e["text"] for e in session.events]
    finally:
        fv.stop()
        session.close()
    assert pw["state"] == "written", pw
    assert any("calibration added to the fleet history of AF-07" in t for t in events), events
    with closing(fleet_db.connect(db, read_only=True)) as con:
        cals = fleet_db.calibration_rows(con, airframe="AF-07")
    assert [c["compass"] for c in cals] == [0, 1, 2] and all(c["written_to_vehicle"] == 1 for c in cals)
    for c, truth in zip(cals, hw.compasses):
        np.testing.assert_allclose([c[f"ofs_{a}_mG"] for a in "xyz"], truth.offsets_mG, atol=3.0)
        assert np.asarray(c["matrix"]).shape == (3, 3) and 0 < c["fitness_mG"] < 10
        assert 200 < c["wmm_strength_mG"] < 700 and -90 < c["wmm_inclination_deg"] < 90
        assert c["lat_deg"] is not None and c["source"] == "station"


def test_offsets_across_flights_spread_drift_and_a_combined_answer_of_weak_flights():
    """Known truth: AF-1 drifts (+30, −40, 0) mG over 39 days with 4 mG scatter; AF-W flies 12
    weak flights (stated 1σ 20 mG, true scatter 20 mG) of a steady compass."""
    from groundstation.jobs.compass_history import offset_summaries
    rows = _synthetic_fleet()
    rng = np.random.default_rng(5)
    truth_w = np.array([60.0, -25.0, 110.0])
    for k in range(12):
        r = _row("AF-W", k, truth_w + rng.normal(0, 20.0, 3))
        r.update({f"fit_ofs_sd_{a}_mG": 20.0 for a in "xyz"}, fit_status="weak")
        rows.append(r)
    by = {s["airframe"]: s for s in offset_summaries(rows)}
    af1 = by["AF-1"]
    assert af1["flights"] == 40 and "drift" in af1["line"] and "combined" in af1["line"]
    true_slope = np.array([30.0, -40.0, 0.0]) / 39.0 * 30.0                  # mG per 30 days
    slope, slope_sd = np.array(af1["drift_mG_per_30d"]), np.array(af1["drift_sd_mG_per_30d"])
    assert np.all(np.abs(slope - true_slope) < 3 * slope_sd) and af1["drift_sigma"] > 5, af1
    # the stated 0.5 mG is far below the 4 mG (+ anomaly site) scatter: the Birge ratio widens the 1σ
    assert np.all(np.array(af1["spread_mG"]) > 4 * np.array(af1["stated_sd_mG"]))
    assert np.all(np.array(af1["combined_sd_mG"]) > 0.5 / np.sqrt(40))
    steady = by["AF-3"]
    assert steady["drift_sigma"] < 4, steady
    w = by["AF-W"]
    sd = np.array(w["combined_sd_mG"])
    assert np.all(np.abs(sd - 20.0 / np.sqrt(12)) < 3.0), sd                  # ~5.8 mG from 12 × 20 mG
    assert np.all(np.abs(np.array(w["combined_mG"]) - truth_w) < 3 * sd), (w["combined_mG"], truth_w)
    assert np.all(np.abs(np.array(w["spread_mG"]) - 20.0) < 10.0)
    from groundstation.cli_fleet import _print_offsets
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        _print_offsets(rows)
    text = buf.getvalue().splitlines()
    assert text[0].startswith("in-flight offsets across flights") and any(t.strip().startswith("AF-W: 12 flight(s)")
                                                                          for t in text)


def test_the_jackknifes_subsets_and_solver_give_the_numbers_of_fresh_data():
    """Issue 29 (review speed): a subset of FieldData keeps its rows of the tilt and expected field
    already computed, and the solver builds the Jacobian of an accepted trial point from that
    point's own residual terms; both give bit for bit what computing them afresh gives."""
    from dataclasses import replace as dc_replace

    from estimators import field_model as fm
    from estimators.wmm_fit import WmmFitSettings, _options, _with_jackknife

    rng = np.random.default_rng(7)
    n = 900
    t = np.arange(n) / 10.0
    roll, pitch = 0.2 * np.sin(t / 3.0), 0.15 * np.cos(t / 5.0)
    yaw = np.mod(t * 0.35, 2 * np.pi)
    H = np.array([240.0, 20.0, 430.0])
    truth = fm.nominal_params(offsets_mG=[30.0, -45.0, 12.0])
    truth[3:6] = [1.03, 0.98, 1.01]
    x = np.abs(np.sin(t / 7.0)) * 10.0
    truth[9:12] = [1.5, -0.8, 2.0]
    clean = fm.FieldData(np.zeros((n, 3)), roll, pitch, yaw, x, H)
    m = -fm.residuals(truth, clean, "vector") + rng.normal(0.0, 3.0, (n, 3))

    def fresh():
        return fm.FieldData(m.copy(), roll.copy(), pitch.copy(), yaw.copy(), x.copy(), H.copy())

    data = fresh()
    data.tilt(), data.expected_body_mG()
    keep = (np.arange(n) % 8) != 3
    sub, plain = data.subset(keep), fresh().subset(keep)
    assert "_tilt" in sub.__dict__ and "_tilt" not in plain.__dict__
    assert np.array_equal(sub.tilt(), plain.tilt()) and np.array_equal(sub.expected_body_mG(), plain.expected_body_mG())
    s = WmmFitSettings()
    p0 = fm.nominal_params()
    for model, active in (("yaw_free", np.r_[np.ones(6, bool), np.zeros(3, bool), np.ones(3, bool)]),
                          ("vector", np.ones(12, bool))):
        opts = _options(model, active, s)
        sol = fm.solve(data, p0, p0, opts)
        assert np.linalg.norm(sol.params[:3] - truth[:3]) < 5.0, model        # the fit is a real one
        again = fm.solve(fresh(), p0, p0, opts)
        assert np.array_equal(sol.params, again.params) and np.array_equal(sol.covariance, again.covariance)
        # the solver's residual and Jacobian are residuals()' at the point it stopped
        r, J = fm.residuals(sol.params, fresh(), model, True)
        r2, terms = fm._residuals_terms(sol.params, data, model)
        assert np.array_equal(r, r2) and np.array_equal(J, fm._jacobian(sol.params, data, terms))
        cov = _with_jackknife(sol.covariance, data, sol, sol.params != sol.params, p0, model,
                              dc_replace(s, jackknife_blocks=0))
        assert np.array_equal(cov, sol.covariance)                               # K = 0: no jackknife
        jk = _with_jackknife(sol.covariance, data, sol, active, p0, model, s)
        assert np.array_equal(jk, _with_jackknife(sol.covariance, fresh(), sol, active, p0, model, s))
        assert np.all(np.diag(jk) >= np.diag(sol.covariance))
