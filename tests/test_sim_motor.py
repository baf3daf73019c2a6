"""Simulator missions for the detection benchmark: motor-current (payload) and GPS-outage flights."""
from __future__ import annotations

import numpy as np

from groundstation.io.logs import read_log
from groundstation.sim.scenarios import simulate


def test_motor_mission_streams_a_current_varying_by_more_than_8_A_and_its_field(tmp_path):
    sim = simulate("mission-motor", 3, duration_s=80.0)
    log = read_log(sim.write(tmp_path / "motor.tlog"))
    bat = np.asarray(log.battery, dtype=float)
    assert len(bat) > 300 and np.ptp(bat[:, 1]) >= 8.0              # SYS_STATUS current, 10 Hz
    lo, hi = sim.truth["mag"]["current_range_A"]
    assert hi - lo >= 8.0 and sim.truth["mag"]["payload_current_A"] == 10.0
    assert sim.truth["interference"]["onset_s"] is None
    # the payload's field is on the sensor: the same flight without it differs by A (c ΔI)
    plain = simulate("mission-motor", 3, duration_s=80.0, payload=None).result
    r = sim.result
    diff = r.mag_raw_mG - plain.mag_raw_mG
    extra = r.motor_current_A - plain.motor_current_A
    on = extra > 5.0
    truth = np.asarray(sim.truth["mag"]["A"]) @ (10.0 * np.asarray(sim.truth["mag"]["motor_mG_per_A"]))
    np.testing.assert_allclose(np.median(diff[on], axis=0), truth, atol=0.5)


def test_outage_mission_has_no_interference_and_loses_the_fix():
    sim = simulate("gps-outage", 1, duration_s=200.0)
    assert sim.truth["interference"]["onset_s"] is None and sim.truth["gps_outage_s"] == [100.0, 180.0]
    fix = sim.result.gps_fix_type
    t = sim.result.t_s[sim.result.gps_idx]
    assert (fix[(t > 101) & (t < 179)] < 3).all() and (fix[t < 99] >= 3).all()
