"""Shared known-truth data for the real-log estimator tests: a synthetic level flight with turns,
and the ArduPilot-realistic simulator's logs read back with groundstation's readers (the pipeline
steps are those of benchmarks/real_logs.py)."""
from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

from estimators.rotations import dcm_body_to_ned

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import real_logs  # noqa: E402,F401  (re-exported: pymavlink extraction + the pipeline the benchmark runs)

H_NED = np.array([230.0, 52.0, -531.0])          # Canberra-like, mG


def level_flight(seed: int = 0, headings_deg=(10, 82, 154, 226, 298), n: int = 1200, noise_mG: float = 2.0,
                 A=None, b=(120.0, -80.0, 45.0), f=(1.2, -0.8, 2.0)):
    """Legs at the given headings, pitch −7° ± 3°, roll ± 3°, current 15–23 A.  m = A(h + f I) + b + ε."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.5
    yaw = np.radians(np.repeat(headings_deg, int(np.ceil(n / len(headings_deg))))[:n]) + rng.normal(0, 0.02, n)
    roll = rng.normal(0, 0.05, n)
    pitch = -0.12 + rng.normal(0, 0.05, n)
    current = 15 + 8 * np.abs(np.sin(t / 20)) + rng.normal(0, 1, n)
    A = np.array([[1.05, 0.02, 0.0], [0.02, 0.97, 0.01], [0.0, 0.01, 1.02]]) if A is None else np.asarray(A)
    h = np.einsum("nji,j->ni", dcm_body_to_ned(roll, pitch, yaw), H_NED)
    raw = (h + current[:, None] * np.asarray(f)) @ A.T + np.asarray(b) + rng.normal(0, noise_mG, (n, 3))
    return dict(t=t, raw=raw, roll=roll, pitch=pitch, yaw=yaw, current=current, A=A, b=np.asarray(b), f=np.asarray(f))


@lru_cache(maxsize=4)
def ardupilot_flight(seed: int = 1, dance: bool = False, imu_rate_hz: float = 2.0):
    """(sim, FlightLog read back from its tlog, WMM field) of a simulated ArduPilot flight."""
    import tempfile

    from groundstation.io.logs import read_log
    from groundstation.jobs.calibrate import expected_field
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
    from groundstation.sim.ardupilot_flight import FlightPlan
    sim = simulate_ardupilot(ArduSimConfig(seed=seed, imu_rate_hz=imu_rate_hz, plan=FlightPlan(dance=dance, legs=6)))
    with tempfile.TemporaryDirectory() as d:
        log = read_log(sim.write_tlog(Path(d) / f"ardusim-{seed}-{int(dance)}-{imu_rate_hz}.tlog"))
    H = np.asarray(expected_field(log)[0].field_ned_mG)
    return sim, log, H
