"""Compile (or load from numba's cache) every numba kernel of the estimators before they are
needed: ``python -m estimators.kernel_warmup``, run by ./run and ./test after the environment is
set up.  A kernel's first call compiles it (tens of seconds in all on a 2-core machine) and
writes the cache beside its module; without this the first replay of a fresh clone would stall
the station that long, and each test process would compile the same kernels at once.  From an
empty cache its parts (the AHRS's kernels, the field test's) compile in processes side by side
(26 s on this 2-core machine, 43 s one after the other); with the cache in place it loads them in
one process in about a second.

The kernels are reached through the estimators' public forms, on a few seconds of a level,
turning body, with the argument types those forms pass in use, so every specialisation the
station and the jobs use is compiled here.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

__all__ = ["warm_up"]


def _level_turn(n: int = 400, rate_hz: float = 50.0) -> dict[str, np.ndarray]:
    """n IMU steps of a level body turning at 10°/s in a 500 mG field inclined 60° (FRD, SI, mG)."""
    t = np.arange(n) / rate_hz
    yaw = np.radians(10.0) * t
    h, z = 250.0, 433.0
    mag = np.c_[h * np.cos(yaw), -h * np.sin(yaw), np.full(n, z)]
    gyro = np.c_[np.zeros(n), np.zeros(n), np.full(n, np.radians(10.0))]
    acc = np.c_[np.zeros(n), np.zeros(n), np.full(n, -9.80665)]
    return {"t": t, "mag": mag, "gyro": gyro, "acc": acc}


def _warm_ahrs() -> None:
    """The AHRS's block logic, batch and per sample."""
    from estimators.ahrs import Ahrs
    from estimators.ahrs_batch import run_ahrs

    d = _level_turn()
    run_ahrs(np.c_[d["t"], d["gyro"], d["acc"]], np.c_[d["t"], d["mag"]])
    ahrs = Ahrs()
    for k in range(len(d["t"])):
        ahrs.update_mag(float(d["t"][k]), d["mag"][k].tolist())
        ahrs.update_imu(float(d["t"][k]), d["gyro"][k].tolist(), d["acc"][k].tolist())


def _warm_field_test() -> None:
    """The field-vector test's step, batch and per sample, its field model's steps one by one
    (the motor-field fits use them), and the low-pass of the tilt gap its tilt is chosen by."""
    from estimators.field_consistency import FieldConsistency, field_consistency
    from estimators.low_pass import low_pass_from_rest, low_pass_state
    from estimators.residual_trackers import FieldModelFilter

    d = _level_turn()
    n = len(d["t"])
    zeros = np.zeros(n)
    field_consistency(d["t"], d["mag"], zeros, zeros, np.ones(n, bool), d["gyro"], np.full(n, 5.0),
                      np.full(n, 50.0), np.ones(n, bool), earth_field_mG=(250.0, 0.0, 433.0))
    live = FieldConsistency(earth_field_mG=(250.0, 0.0, 433.0))
    for k in range(n):
        live.update(float(d["t"][k]), d["mag"][k].tolist(), 0.0, 0.0, True, d["gyro"][k].tolist(), 5.0, 50.0, True)
    live.update(float(n), (math.nan,) * 3, 0.0, 0.0, False, (0.0, 0.0, 0.0), math.nan, 50.0, False)
    low_pass_from_rest(d["t"], np.c_[d["mag"][:, :2]], 10.0, low_pass_state(2))      # the tilt gap's filter
    model = FieldModelFilter((250.0, 0.0, 433.0))
    model.forget(0.02, 4.0)
    model.update(model.jacobian(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), model.signal(5.0)),
                 (250.0, 0.0, 433.0), 0.02, 4.0, 3.0)


PARTS = (_warm_ahrs, _warm_field_test)      # independent kernels: compiled side by side by the CLI


def warm_up(processes: int = 1) -> float:
    """Run every compiled kernel once, in this process (``processes`` 1) or the parts side by
    side in child processes (each compiles and caches its own kernels); returns the seconds."""
    t0 = time.perf_counter()
    if processes > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(processes, len(PARTS)), mp_context=multiprocessing.get_context("spawn")) as pool:
            for done in [pool.submit(part) for part in PARTS]:
                done.result()
    else:
        for part in PARTS:
            part()
    return time.perf_counter() - t0


def _cache_empty() -> bool:
    """No kernel cached yet (a fresh clone, or estimators.kernel_cache just cleared them)."""
    from estimators.kernel_cache import CACHE

    return not any(CACHE.glob("*.nbi"))


if __name__ == "__main__":
    cold = _cache_empty()       # compile the parts side by side; loading them is quicker in one process
    took = warm_up(processes=(os.cpu_count() or 1) if cold else 1)
    how = "compiled" if cold else "loaded from numba's cache"
    print(f"estimator kernels {how} ({took:.1f} s)", file=sys.stderr)
