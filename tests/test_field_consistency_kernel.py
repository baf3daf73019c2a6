"""The field-vector test's compiled step (estimators.field_consistency_kernel): its ring buffers,
the live object's views of the state, and the per-sample form against the batch form with a prior
that arrives mid-flight (issue 29: one implementation, run by both)."""
from __future__ import annotations

import math

import numpy as np

from estimators import ring_buffers as ring
from estimators.field_consistency import FieldConsistency, field_consistency
from estimators.field_consistency_kernel import HIST, SIG
from test_field_consistency_reference import H_MAG, _flight


def test_a_ring_is_a_deque_that_drops_its_oldest_entry_when_full():
    cap = 4
    buf, p = np.zeros(cap), np.zeros(2, dtype=np.int64)
    for v in range(6):                       # 0 and 1 dropped when 4 and 5 arrive
        buf[ring.push(p, cap)] = v
    assert ring.size(p) == cap
    assert [buf[ring.at(p, i, cap)] for i in range(cap)] == [2.0, 3.0, 4.0, 5.0]
    assert buf[ring.first(p, cap)] == 2.0 and buf[ring.last(p, cap)] == 5.0
    ring.pop_front(p, cap)
    ring.pop_back(p)
    assert [buf[ring.at(p, i, cap)] for i in range(ring.size(p))] == [3.0, 4.0]


def test_the_windows_of_a_1_khz_imu_fit_the_rings():
    """At 1 kHz the signal's window (1.5 s) and the tilt's (2 s) hold 1.5-2 thousand samples,
    well inside CAPACITY (the deque code they replaced gives the same numbers up to it)."""
    f = _flight(3, n_s=30.0, rate_hz=1000.0)
    fc = FieldConsistency(earth_field_mG=tuple(H_MAG))
    for i in range(len(f["t"])):
        fc.update(f["t"][i], f["mag"][i], f["roll"][i], f["pitch"][i], True, f["gyro"][i], f["motor"][i], 1000.0, True)
    ptr = fc._state[6]
    assert 1400 <= ptr[SIG, 1] <= 1600 and 1900 <= ptr[HIST, 1] <= 2100
    assert ptr[:, 1].max() < ring.CAPACITY


def test_the_live_object_reads_its_state_and_equals_the_batch_with_a_late_prior():
    f = _flight(5, n_s=60.0)
    prior_from_s = 4.0
    batch = field_consistency(f["t"], f["mag"], f["roll"], f["pitch"], f["ok"], f["gyro"], f["motor"], f["rate"],
                              True, earth_field_mG=tuple(H_MAG), prior_from_s=prior_from_s)
    fc = FieldConsistency()
    assert fc.model is None and fc.motor is None and fc.h is None and fc.psi is None and fc.prior is None
    steps = []
    for i in range(len(f["t"])):
        if fc.prior is None and f["t"][i] >= prior_from_s:
            fc.set_prior(tuple(H_MAG))
        steps.append(fc.update(f["t"][i], f["mag"][i], f["roll"][i], f["pitch"][i], True, f["gyro"][i],
                               f["motor"][i], 50.0, True))
    assert fc.prior == tuple(H_MAG)
    np.testing.assert_array_equal([s.status for s in steps], batch.status)
    np.testing.assert_array_equal([s.z for s in steps], batch.z)
    np.testing.assert_array_equal([s.q for s in steps], batch.q)
    np.testing.assert_array_equal([s.motor_mG_per_unit for s in steps], batch.motor_mG_per_unit)
    # the attributes are views of the state the step changed
    motor = fc.motor
    assert motor.f == list(steps[-1].motor_mG_per_unit) == fc.f
    assert motor.sd == batch.motor_sd_mG_per_unit[-1].tolist()
    assert tuple(fc.h) == batch.earth_field_mG and tuple(fc.b) == batch.offset_mG
    assert tuple(math.degrees(v) for v in fc.tilt.tilt_rad) == batch.tilt_deg
    assert fc.noise_mG == batch.noise_mG and math.isfinite(fc.psi)
    assert isinstance(motor.significant(), bool) and motor.theta.shape == (11,)
