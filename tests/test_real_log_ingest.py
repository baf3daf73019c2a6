"""What real autopilot logs hold, read by groundstation.io.logs: every compass and IMU, the parameter
history with times, onboard-calibration markers and commands, current and throttle, old TimeMS
DataFlash timing, MAG with an instance column, PX4 multi-instance sensor_mag with device ids.
Known truth: the ArduPilot-realistic simulator (groundstation.sim.ardupilot); real logs in ../shared/data."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import SHARED_DATA, needs_shared
from groundstation.io.logs import read_log
from groundstation.io.params import params_at
from groundstation.samples import MAG_CAL_SUCCESS
from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
from groundstation.sim.ardupilot_flight import FlightPlan



@pytest.fixture(scope="module")
def sim():
    return simulate_ardupilot(ArduSimConfig(seed=4, imu_rate_hz=1.5, dropout_compass=2, dropout_after_s=150.0,
                                            plan=FlightPlan(log_rate_hz=5.0)))


@pytest.fixture(scope="module")
def tlog(sim, tmp_path_factory):
    return read_log(sim.write_tlog(tmp_path_factory.mktemp("tlog") / "s.tlog"))


@pytest.mark.parametrize("layout", ["timems", "timeus_split", "timeus_instance"])
def test_dataflash_every_layout_every_compass_right_duration(sim, tmp_path, layout):
    log = read_log(sim.write_bin(tmp_path / f"{layout}.bin", layout))
    n = len(sim.flight.t_s)
    assert log.duration_s == pytest.approx(sim.flight.t_s[-1], abs=0.15)        # TimeMS too: not 0 s
    counts = {c.compass: len(c.field) for c in log.compasses}
    assert counts == {0: n, 1: n, 2: int(sim.compasses[2].present.sum())}      # thousands of MAG records, all read
    assert log.primary_compass == 0 and log.mag is log.compasses[0].field
    names = {c.compass: c.source for c in log.compasses}
    assert names == ({0: "MAG[0]", 1: "MAG[1]", 2: "MAG[2]"} if layout == "timeus_instance"
                     else {0: "MAG", 1: "MAG2", 2: "MAG3"})
    for k, c in enumerate(log.compasses):
        np.testing.assert_allclose(c.field[:, 1:4], np.rint(sim.compasses[k].corrected_mG[sim.compasses[k].present]),
                                   atol=1.0)
        assert c.calibration_applied is True and c.motor_offset_mG is not None
    # current: CURR in cA (2014 layout) or BAT in A; throttle: CTUN
    assert log.battery[:, 1].max() == pytest.approx(sim.flight.current_A.max(), abs=0.02)
    np.testing.assert_allclose(log.throttle[:, 1], sim.flight.throttle, atol=2e-3)
    assert log.message_counts["throttle from CTUN"] == n
    assert log.start_unix_s == pytest.approx(sim.config.start_unix_s, abs=0.2)


def test_dataflash_offsets_history_follows_the_onboard_calibration(sim, tmp_path):
    log = read_log(sim.write_bin(tmp_path / "b.bin", "timems"))
    t_apply = sim.cal_applied_s
    c1 = sim.compasses[1].corrections.offsets_mG
    before = params_at(log.param_history, t_apply - 1.0)
    after = params_at(log.param_history, t_apply + 1.0)
    for a, j in zip("XYZ", range(3)):
        assert before[f"COMPASS_OFS2_{a}"] == pytest.approx(c1[0, j], abs=1.0)
        assert after[f"COMPASS_OFS2_{a}"] == pytest.approx(c1[-1, j], abs=1.0)
    # int16 MAG OfsX.. re-reporting the float PARM value is not a change: a few entries, not thousands
    assert len([h for h in log.param_history if h[1] == "COMPASS_OFS2_X"]) <= 3


def test_tlog_compasses_imus_history_markers_and_command(sim, tlog):
    log = tlog
    assert [c.source for c in log.compasses] == ["RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"]
    assert sorted(log.imus) == [0, 1, 2] and log.imu is log.imus[log.primary_compass]
    assert log.compasses[2].field[-1, 0] < 151.0                  # the drop-out: all-zero fields are not kept
    starts = [e for e in log.mag_cal if e.kind == "start"]
    reports = {e.compass: e for e in log.mag_cal if e.kind == "report"}
    assert len(starts) == 1 and starts[0].mask == 0                # DO_START_MAG_CAL from the GCS, all compasses
    assert starts[0].t_s < min(e.t_s for e in log.mag_cal if e.kind == "progress")
    for k, rec in enumerate(sim.compasses):
        r = reports[k]
        assert r.status == MAG_CAL_SUCCESS and r.fitness_mG == pytest.approx(rec.report["fitness_mG"], rel=1e-4)
        np.testing.assert_allclose(r.offsets_mG, rec.report["ofs_mG"], atol=1e-3)
    # history: stale offsets, then the calibrated ones once the vehicle applied them
    first = params_at(log.param_history, 1.0)
    last = params_at(log.param_history, log.duration_s)
    c0 = sim.compasses[0].corrections.offsets_mG
    assert first["COMPASS_OFS_X"] == pytest.approx(c0[0, 0], abs=1.0)
    assert last["COMPASS_OFS_X"] == pytest.approx(c0[-1, 0], abs=1e-3)
    change = [t for t, n, _ in log.param_history if n == "COMPASS_OFS_X"][-1]
    assert sim.cal_applied_s - 1.0 < change < sim.cal_applied_s + 1.5
    assert len(log.throttle) > 100 and 0 < log.throttle[:, 1].max() <= 1.0       # VFR_HUD throttle %


@needs_shared("dronekit/flight_replay_flight.tlog")
def test_real_arducopter_tlog_two_compasses_device_ids_and_offset_history():
    log = read_log(SHARED_DATA / "dronekit" / "flight_replay_flight.tlog")
    assert [(c.compass, c.source, c.device_id) for c in log.compasses] == [(0, "RAW_IMU", 73225),
                                                                          (1, "SCALED_IMU2", 131594)]
    assert all(len(c.field) > 2500 for c in log.compasses)
    ofs_x = [(round(t), v) for t, n, v in log.param_history if n == "COMPASS_OFS_X"]
    # SENSOR_OFFSETS / PARAM_VALUE: -95 at the start, the learnt -97 at the end (as the vehicle reported)
    assert ofs_x[0][1] == -95.0 and ofs_x[-1][1] == -97.0 and len(ofs_x) >= 3
    assert params_at(log.param_history, 0.0)["COMPASS_OFS2_Z"] == -230.0


@needs_shared("px4-pyulog/sample_log_small.ulg")
def test_real_px4_ulog_every_sensor_mag_instance_with_device_id():
    log = read_log(SHARED_DATA / "px4-pyulog" / "sample_log_small.ulg")
    comp = {c.compass: c for c in log.compasses}
    assert comp[0].source == "sensor_mag[0]" and comp[0].device_id == 589858 and comp[0].calibration_applied is False
    # instance 1 is CAL_MAG_PRIME; its raw topic is sparse (1 Hz), so the calibrated topic stands in
    assert comp[1].source == "vehicle_magnetometer" and comp[1].device_id == 592905 and comp[1].calibration_applied
    assert log.primary_compass == 1 and len(log.mag) == 319
    assert len(log.throttle) > 1000 and len(log.battery) > 10 and len(log.param_history) > 900
