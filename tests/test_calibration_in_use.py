"""Relative and absolute calibrations (jobs.calibrate.frame), .param files (io.param_file), and the
held-out flow: a dance log without parameters -> calibrate -> analyze the vehicle's other flights
with it (tlog: simulated vehicles with and without onboard calibration; DataFlash: the
ArduPilot-like simulator)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from groundstation.cli import _load_calibration, main
from groundstation.io.logs import read_log
from groundstation.io.param_file import ParamFileError, apply_to_log, parse_param_text, read_param_file
from groundstation.jobs.analyze import analyze_log, calibration_for_log
from groundstation.jobs.calibrate import calibrate_compasses
from groundstation.jobs.calibrate.frame import compose, corrections_record, for_log, relative_to
from groundstation.sim.scenarios import Simulation, simulate

STRIPPED = ("PARAM_VALUE", "SENSOR_OFFSETS")      # what a held-out log without parameters lacks


def _write_stripped(sim: Simulation, path: Path) -> Path:
    msgs = [(t, m) for t, m in sim.messages if m.get_type() not in STRIPPED]
    return Simulation(sim.scenario, sim.seed, msgs, sim.truth, sim.result).write(path)


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("held_out")
    out = {}
    for onboard, tag in ((False, "raw"), (True, "onboard")):
        dance, fast = simulate("calibration", 5, onboard_calibration=onboard), simulate("mission-fast", 5,
                                                                                         onboard_calibration=onboard)
        out[f"dance-{tag}"] = _write_stripped(dance, d / f"dance-{tag}.tlog")
        out[f"fast-{tag}"] = _write_stripped(fast, d / f"fast-{tag}.tlog")
        out[f"fast-{tag}-params"] = fast.write(d / f"fast-{tag}-params.tlog")
        out[f"truth-{tag}"] = dance.truth
        out["onset_s"] = fast.truth["interference"]["onset_s"]
    out["dir"] = d
    return out


# ------------------------------------------------------------------------------ pure parts

def test_compose_is_exact_through_raw():
    rng = np.random.default_rng(0)
    b, o = rng.normal(0, 100, 3), rng.normal(0, 100, 3)
    C, N = np.eye(3) + rng.normal(0, 0.05, (3, 3)), np.eye(3) + 0.05 * np.diag(rng.normal(size=3))
    raw = rng.normal(0, 500, (50, 3))
    b2, C2 = compose(b, C, o, N)
    want = ((raw - o) @ N.T - b) @ C.T          # relative (b, C) on top of K(raw) = N (raw - o)
    np.testing.assert_allclose((raw - b2) @ C2.T, want, atol=1e-9)


def test_relative_to_of_old_and_new_objects():
    assert relative_to({"status": "ok", "offsets_mG": [0, 0, 0]}) == "raw"            # older calibrate JSON
    assert relative_to({"status": "no_parameters"}) == "unknown"
    assert relative_to({"relative_to": "corrections", "corrections_in_force": {"offsets_mG": [1, 2]}}) == "unknown"
    rec = corrections_record([1, 2, 3], np.eye(3))
    assert relative_to({"relative_to": "corrections", "corrections_in_force": rec}) == "corrections"


def test_for_log_cases():
    b, C = np.array([10.0, -5.0, 3.0]), np.diag([1.1, 0.9, 1.0])
    o, N = np.array([-40.0, 7.0, 2.0]), np.diag([1.02, 0.98, 1.0])
    rec = corrections_record(o, N)
    a = for_log(b, C, {"relative_to": "raw"}, "ok")
    assert a.exact and np.allclose(a.offsets_mG, b)
    a = for_log(b, C, {"relative_to": "raw"}, "no_parameters")
    assert not a.exact and "unknown" in a.note
    a = for_log(b, C, {"relative_to": "corrections", "corrections_in_force": rec}, "ok", [0, 0, 0], np.eye(3))
    assert a.exact and np.allclose(a.offsets_mG, compose(b, C, o, N)[0])     # its own corrections, not the log's
    a = for_log(b, C, {"relative_to": "unknown"}, "ok", o, N)
    assert not a.exact and np.allclose(a.matrix, C @ N) and "assumed the same" in a.note
    a = for_log(b, C, {"relative_to": "unknown"}, "no_parameters")
    assert np.allclose(a.offsets_mG, b) and np.allclose(a.matrix, C)


def test_param_formats_bad_lines_and_hostile_values(tmp_path):
    text = ("# Mission Planner\nCOMPASS_OFS_X,12.5\n\n"
            "COMPASS_OFS_Y  -3   # MAVProxy\n"
            "1\t1\tCOMPASS_OFS_Z\t7.25\t9\n"            # QGC export
            "COMPASS_DIA_X,nan\nCOMPASS_DIA_Y,inf\nCOMPASS_DIA_Z,3.4e38\n"
            "not a parameter\n\x1b[31mCOMPASS_ODI_X,1\n")
    pf = parse_param_text(text, "v.param")
    assert pf.values == {"COMPASS_OFS_X": 12.5, "COMPASS_OFS_Y": -3.0, "COMPASS_OFS_Z": 7.25}
    assert pf.skipped == 5 and "5 line(s)" in pf.warning()
    (tmp_path / "bin.param").write_bytes(b"\x00\x01\x02COMPASS")
    with pytest.raises(ParamFileError, match="binary"):
        read_param_file(tmp_path / "bin.param")
    (tmp_path / "none.param").write_text("hello\nworld\n")
    with pytest.raises(ParamFileError, match="no NAME,VALUE"):
        read_param_file(tmp_path / "none.param")
    assert main(["calibrate", str(tmp_path / "x.tlog"), "--params", str(tmp_path / "none.param")]) == 1


def test_log_values_win_over_the_file(logs):
    log = read_log(logs["fast-onboard-params"])
    before = dict(log.params)
    note = apply_to_log(log, {"COMPASS_OFS_X": 999.0, "COMPASS_OFS_Y": 1.0}, "x.param")
    assert log.params["COMPASS_OFS_X"] == before["COMPASS_OFS_X"] and "not used" in note


# ------------------------------------------------------------------------------ the held-out flow

@pytest.mark.parametrize("tag", ["raw", "onboard"])
def test_dance_without_parameters_calibrates_and_analyze_applies_it(logs, tag, tmp_path):
    cal_json = tmp_path / "c.json"
    assert main(["calibrate", str(logs[f"dance-{tag}"]), "--json", str(cal_json)]) == 0
    result = json.loads(cal_json.read_text())["results"][0]
    assert result["status"] == "ok" and result["relative_to"] == "unknown" and not result["ardupilot_params"]
    cal = _load_calibration(str(cal_json))                        # the CLI accepts it now
    report, _ = analyze_log(read_log(logs[f"fast-{tag}"]), calibration=cal)
    assert report["calibration_applied"] and report["calibration_relative_to"] == "unknown"
    assert "assumed the same" in report["calibration_in_use"]
    assert report["heading_test"] == "on"
    first = report["first_alarm_s"]
    assert first is not None and logs["onset_s"] < first < logs["onset_s"] + 5.0, first
    # the same flight with its parameters in the log: the relative fit goes on top of its corrections
    report2, _ = analyze_log(read_log(logs[f"fast-{tag}-params"]), calibration=cal)
    assert report2["calibration_applied"] and abs(report2["first_alarm_s"] - first) < 0.5


@pytest.mark.parametrize("how", ["params", "assume"])
def test_never_calibrated_vehicle_exports_offsets_within_5_mG(logs, tmp_path, how):
    pfile = tmp_path / "vehicle.param"
    pfile.write_text("# a never-calibrated vehicle, Mission Planner format\n"
                     + "".join(f"COMPASS_OFS_{a},0\nCOMPASS_DIA_{a},0\nCOMPASS_ODI_{a},0\n" for a in "XYZ")
                     + "COMPASS_SCALE,0\nCOMPASS_MOTCT,0\n")
    out = tmp_path / "out.param"
    opts = ["--params", str(pfile)] if how == "params" else ["--assume-uncalibrated"]
    assert main(["calibrate", str(logs["dance-raw"]), "--json", str(tmp_path / "c.json"), "--param-out", str(out),
                 *opts]) == 0
    result = json.loads((tmp_path / "c.json").read_text())["results"][0]
    assert result["relative_to"] == "raw"
    written = read_param_file(out).values
    truth = -np.array(logs["truth-raw"]["mag"]["offsets_mG"])            # COMPASS_OFS = -b
    ofs = np.array([written[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    assert np.max(np.abs(ofs - truth)) < 5.0, (ofs, truth)


def test_param_out_refuses_a_relative_fit(logs, tmp_path, capsys):
    assert main(["calibrate", str(logs["dance-raw"]), "--param-out", str(tmp_path / "o.param")]) == 1
    assert "no absolute calibration" in capsys.readouterr().err
    assert not (tmp_path / "o.param").exists()


def test_relative_fit_with_recorded_corrections_converts_exactly(logs):
    """A relative calibration that records the corrections it was fitted on, applied to a log with
    other corrections known: converted through raw, the same numbers as the absolute fit."""
    with_params = read_log(logs["fast-onboard-params"])         # corrections known: the true calibration
    absolute = calibrate_compasses(read_log(logs["dance-raw"]))[0]    # relative unknown (raw vehicle's)
    o, N = np.zeros(3), np.eye(3)                                # the raw vehicle had identity in force
    rel = dict(absolute, relative_to="corrections", corrections_in_force=corrections_record(o, N))
    applied, note = calibration_for_log(with_params, rel)
    np.testing.assert_allclose(applied["offsets_mG"], absolute["offsets_mG"], atol=1e-9)
    assert "exactly" in note


# ------------------------------------------------------------------------------ DataFlash

@pytest.fixture(scope="module")
def dataflash(tmp_path_factory):
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot

    sim = simulate_ardupilot(ArduSimConfig(seed=3, imu_rate_hz=2.0))
    return sim, sim.write_bin(tmp_path_factory.mktemp("df") / "flight.bin")


def test_dataflash_is_absolute_and_named_as_the_autopilot_corrects_it(dataflash, tmp_path, capsys):
    sim, path = dataflash
    log = read_log(path)
    r = calibrate_compasses(log)[0]
    assert r["status"] == "ok" and r["relative_to"] == "raw" and r["ardupilot_params"]
    assert r["corrections_in_force"]["params"] or r["corrections_in_force"]["offsets_mG"]
    report, _ = analyze_log(log)
    assert "autopilot-corrected" in report["calibration_in_use"]          # not "none (raw magnetometer)"
    report, _ = analyze_log(log, calibration=r)
    assert report["calibration_applied"] and report["calibration_in_use"].startswith("absolute")


def test_serve_params_fill_a_replayed_log_without_them(logs):
    """serve --params / --assume-uncalibrated: the station's replays take the values where the
    log has none (the same rule as the other commands)."""
    from groundstation.cli import _serve_params, build_parser
    from groundstation.station.hub.session import Session

    args = build_parser().parse_args(["serve", "--assume-uncalibrated"])
    settings = _serve_params(args)
    assert settings["params_label"] == "--assume-uncalibrated"
    hub = Session(logs["dir"] / "rec", record_live=False)
    hub.in_use.params_in_force = (dict(settings["params_in_force"]), settings["params_label"])
    log = read_log(logs["dance-raw"])
    assert "COMPASS_OFS_X" not in log.params
    assert "taken as in force" in hub.in_use.fill_params(log)
    r = calibrate_compasses(log)[0]
    assert r["relative_to"] == "raw"
    truth = np.array(logs["truth-raw"]["mag"]["offsets_mG"])
    assert np.max(np.abs(np.array(r["offsets_mG"]) - truth)) < 5.0


def test_accepted_wizard_result_is_the_next_replays_calibration(logs, tmp_path):
    """The wizard's Accept chooses its result for the airframe and stores it: the next replay of a
    log of that airframe without a dance starts with it (the history DB), also after a restart."""
    from groundstation.io import fleet_db
    from groundstation.station.hub.session import Session

    read = read_log

    rec = tmp_path / "recordings"
    rec.mkdir()
    flight = rec / "flight.tlog"
    flight.write_bytes(Path(logs["fast-raw"]).read_bytes())
    result = calibrate_compasses(read(logs["dance-raw"]))[0]
    hub = Session(rec, record_live=False)
    airframe = hub.in_use.airframe_of(read(flight).params, rec.name)
    with hub._lock:
        hub.in_use.airframe = airframe
        hub.in_use.accepted(result)
    deadline = time.time() + 20
    while time.time() < deadline:
        try:
            with fleet_db.connect(fleet_db.default_db_path(rec), read_only=True) as con:
                if fleet_db.get_in_use(con, airframe):
                    break
        except FileNotFoundError:
            pass
        time.sleep(0.1)
    again = Session(rec, record_live=False)                   # a restart
    choice = again.in_use.for_replay(read(flight), flight, None)
    assert choice["source"] == "wizard" and choice["calibration"]["relative_to"] == "unknown"
    assert np.allclose(choice["calibration"]["offsets_mG"], result["offsets_mG"])
    with fleet_db.connect(fleet_db.default_db_path(rec), read_only=True) as con:
        rec_ = fleet_db.calibration_in_force(con, airframe)
    assert rec_ is not None and rec_["relative_to"] == "unknown"     # in the history for `review`


def test_older_calibration_files_still_load(tmp_path):
    """An older `calibrate --json` (no relative_to) is absolute; an older no_parameters result is a
    relative fit; a file without offsets is refused in one line."""
    from groundstation.cli import CliError

    b, C = [10.0, -20.0, 5.0], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"results": [{"status": "ok", "offsets_mG": b, "matrix": C}]}))
    assert relative_to(_load_calibration(str(old))) == "raw"
    older = tmp_path / "older.json"
    older.write_text(json.dumps({"results": [{"status": "no_parameters", "offsets_mG": b, "matrix": C}]}))
    assert relative_to(_load_calibration(str(older))) == "unknown"
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"results": [{"status": "insufficient_coverage", "offsets_mG": None}]}))
    with pytest.raises(CliError, match="no calibration with status 'ok'"):
        _load_calibration(str(empty))


def test_analyze_params_make_the_log_raw_known(logs, tmp_path, capsys):
    """analyze --params: an absolute calibration on a log without parameters is applied exactly
    (the file's corrections un-applied); without --params the report says what it assumed."""
    pfile = tmp_path / "v.param"
    pfile.write_text("".join(f"COMPASS_OFS_{a} 0\n" for a in "XYZ"))          # MAVProxy format
    cal = tmp_path / "abs.json"
    assert main(["calibrate", str(logs["dance-raw"]), "--params", str(pfile), "--json", str(cal)]) == 0
    out = tmp_path / "r.json"
    assert main(["analyze", str(logs["fast-raw"]), "--calibration", str(cal), "--params", str(pfile),
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["calibration_in_use"] == "absolute calibration applied to the raw field"
    assert logs["onset_s"] < report["first_alarm_s"] < logs["onset_s"] + 5.0
    assert main(["analyze", str(logs["fast-raw"]), "--calibration", str(cal), "--json", str(out)]) == 0
    assert "right only if the vehicle was never calibrated" in json.loads(out.read_text())["calibration_in_use"]
    assert "calibration: absolute" in capsys.readouterr().out


def test_review_job_uses_the_history_at_the_log_date_or_params(logs):
    """The per-log review job: a log without a dance takes the airframe's calibration in force at
    its date (the latest before it; only later ones: the earliest, said so), else --params."""
    from groundstation.jobs.review_row import ReviewSettings, review_log

    path = logs["fast-raw"]
    bare = review_log(path)[0]
    assert bare["calibration_used"].startswith("none (autopilot-corrected")
    cal = json.dumps(calibrate_compasses(read_log(logs["dance-raw"]))[0])
    start = read_log(path).start_unix_s
    wrong = json.dumps({"status": "ok", "offsets_mG": [500.0, 0.0, 0.0], "matrix": np.eye(3).tolist()})
    history = ((bare["identity"], start - 10.0, cal), (bare["identity"], start + 10.0, wrong),
               ("someone-else", start - 5.0, wrong))
    row = review_log(path, ReviewSettings(calibrations=history))[0]
    assert row["calibration_used"].startswith("history:") and "relative (unknown corrections)" in row["calibration_used"]
    assert logs["onset_s"] < row["first_alarm_s"] < logs["onset_s"] + 5.0
    later = review_log(path, ReviewSettings(calibrations=((bare["identity"], start + 10.0, cal),)))[0]
    assert "made after this log" in later["calibration_used"]
    row = review_log(path, ReviewSettings(params=(("COMPASS_OFS_X", 0.0), ("COMPASS_OFS_Y", 0.0),
                                                  ("COMPASS_OFS_Z", 0.0)), params_label="v.param"))[0]
    assert row["calibration_used"].startswith("none, the autopilot's corrections from v.param")
    assert row["cal_state"] == "ok"                           # raw rebuilt with the file's offsets
