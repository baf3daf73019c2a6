"""ArduPilot-realistic simulator (groundstation.sim.ardupilot): what it writes is what ArduPilot writes."""
from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from estimators.compass_corrections import corrections_from_param_changes, unapply_ardupilot_corrections
from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot, truth_path
from groundstation.sim.ardupilot_flight import FlightPlan
from groundstation.io.logs import read_log


@pytest.fixture(scope="module")
def sim():
    return simulate_ardupilot(ArduSimConfig(seed=4, imu_rate_hz=1.5, dropout_compass=2, dropout_after_s=150.0))


def test_tlog_streams_corrected_fields_at_telemetry_rate(sim, tmp_path):
    from pymavlink import mavutil
    path = sim.write_tlog(tmp_path / "a.tlog")
    truth = json.loads(truth_path(path).read_text())
    assert truth["format"] == "tlog" and len(truth["compasses"]) == 3 and truth["calibration_applied_s"] > 0
    conn = mavutil.mavlink_connection(str(path))
    counts = Counter()
    while (m := conn.recv_msg()) is not None:
        counts[m.get_type()] += 1
    conn.close()
    dur = sim.flight.t_s[-1]
    for name in ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        assert 1.3 < counts[name] / dur < 1.55                 # 1.5 Hz less 2 % dropped packets
    assert counts["MAG_CAL_PROGRESS"] >= 3 * 30 and counts["MAG_CAL_REPORT"] == 3
    assert counts["SENSOR_OFFSETS"] > 0 and counts["SYS_STATUS"] > 0 and counts["VFR_HUD"] > 0
    log = read_log(path)
    comp = {c.compass: c for c in log.compasses}
    assert comp[2].field[:, 0].max() < 151.0                   # compass 2 dropped out: zeros are not a field
    # Rebuilding raw with the corrections in force gives the simulated raw (rounding to 1 mG, arrival jitter).
    for k in range(3):
        t, corrected = comp[k].field[:, 0], comp[k].field[:, 1:4]
        corr = corrections_from_param_changes(t, log.param_history, k)
        cur = np.interp(t, log.battery[:, 0], log.battery[:, 1])
        raw = unapply_ardupilot_corrections(corrected, corr, current_A=cur).raw_mG
        idx = np.searchsorted(sim.flight.t_s, t - 0.16) + 1       # the grid sample sent just before arrival
        ok = np.isfinite(raw).all(1)
        errs = [np.min(np.abs(raw[ok] - sim.compasses[k].raw_rot_mG[np.clip(idx[ok] + j, 0, len(sim.flight.t_s) - 1)]).max(1))
                for j in range(-1, 2)]
        assert np.median(np.min(errs, axis=0)) < 3.0


def test_offsets_change_mid_log_with_the_onboard_calibration(sim):
    for rec in sim.compasses:
        c = rec.corrections
        before, after = c.offsets_mG[0], c.offsets_mG[-1]
        assert np.max(np.abs(before - after)) > 5.0
        ideal = np.asarray(rec.truth["ideal"]["COMPASS_OFS"])
        assert np.max(np.abs(after - ideal)) < 5.0 < np.max(np.abs(before - ideal))   # stale, then calibrated
        assert 0 < rec.report["fitness_mG"] < 10


@pytest.mark.parametrize("layout", ["timems", "timeus_split", "timeus_instance"])
def test_dataflash_layouts_read_back_with_pymavlink(sim, tmp_path, layout):
    path = sim.write_bin(tmp_path / f"b_{layout}.bin", layout)
    assert json.loads(truth_path(path).read_text())["format"] == f"bin/{layout}"
    log = read_log(path)
    comp = {c.compass: c for c in log.compasses}
    assert sorted(comp) == [0, 1, 2]
    t0, m0 = comp[0].field[:, 0], comp[0].field[:, 1:4]
    assert t0[-1] - t0[0] == pytest.approx(sim.flight.t_s[-1], abs=0.2)       # TimeMS or TimeUS clock both work
    assert log.duration_s == pytest.approx(sim.flight.t_s[-1], abs=0.2)
    np.testing.assert_allclose(m0, np.rint(sim.compasses[0].corrected_mG), atol=1.0)
    np.testing.assert_allclose(comp[0].motor_offset_mG, np.rint(sim.compasses[0].motor_offset_mG), atol=1.0)
    assert len(comp[2].field) < len(t0)                                          # the drop-out
    assert log.battery[:, 1].max() == pytest.approx(sim.flight.current_A.max(), abs=0.02)
    names = {n for _, n, _ in log.param_history}
    assert {"COMPASS_OFS3_X", "COMPASS_DIA2_Y", "COMPASS_MOTCT", "AHRS_EKF_TYPE"} <= names


def test_independent_yaw_and_no_dance():
    s = simulate_ardupilot(ArduSimConfig(seed=5, yaw_source="independent", plan=FlightPlan(dance=False)))
    assert s.cal_applied_s is None and all(not r.report for r in s.compasses)
    err = np.degrees(np.angle(np.exp(1j * (s.attitude[:, 2] - s.flight.yaw_rad))))
    assert np.std(err) < 0.5
    dep = simulate_ardupilot(ArduSimConfig(seed=5, plan=FlightPlan(dance=False)))
    err = np.degrees(np.angle(np.exp(1j * (dep.attitude[:, 2] - dep.flight.yaw_rad))))
    assert np.std(err) > 1.0                                   # the EKF-like yaw inherits the stale offsets


def test_command_line_writes_both_logs_with_their_truth(tmp_path):
    from groundstation.sim.ardupilot import main
    assert main(["--seed", "6", "--out", str(tmp_path / "f.tlog"), "--bin", "timems", "--no-dance"]) == 0
    assert json.loads((tmp_path / "f.truth.json").read_text())["format"] == "tlog"
    assert json.loads((tmp_path / "f-timems.truth.json").read_text())["format"] == "bin/timems"
    assert (tmp_path / "f-timems.bin").stat().st_size > 100_000
