"""What disturbs the simulated magnetometer besides the vehicle's own errors (pure numpy).

* ``Interference``: a field on the sensor axes that follows time alone (seed 002's ramp, step
  and bump).  The autopilot's heading filter sees it (it is inside the closed loop).
* ``PayloadLoad``: a payload switched on and off (a square wave of extra current).  In the motor
  wires (``mG_per_A`` None) its field is the motor's c·ΔI; on its own lead (a power cable routed
  past the compass) it has a field per ampere of its own, which no motor compensation knows.
* ``GroundAnomaly``: a magnetised mass on the ground (a steel structure, a buried tank) seen as a
  point dipole: B = μ0/(4π) (3 (m·r̂) r̂ − m) / |r|³ (Jackson, Classical Electrodynamics, eq. 5.56).
  With μ0/(4π) = 1e-7 T·m/A and 1 mG = 1e-7 T, B [mG] = (3 (m·r̂) r̂ − m) / |r|³ for m in A·m² and
  r in m.  The field is tied to a place: it rises and falls as the vehicle passes.

Payload and anomaly fields are added after the closed loop (the autopilot's heading does not see
them), through the sensor model A like the motor field.  Frames: NED, FRD body; units: mG, A, m, s.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.rotations import dcm_body_to_ned

__all__ = ["Interference", "PayloadLoad", "GroundAnomaly", "payload_current_A", "payload_field_body_mG",
           "anomaly_field_ned_mG"]


@dataclass
class Interference:
    """External field added on the magnetometer's sensor axes [mG].

    kind: "none" | "ramp" (rise at rate_mG_s for rise_s, hold hold_s, fall at the same rate)
          | "bump" (smooth rise-then-fall, peak amplitude_mG over duration_s, seed 002 sim.)
          | "step" (amplitude_mG from onset for duration_s).
    axis: unit vector in the sensor frame (seed 002 flight tests: +Y).
    """
    kind: str = "none"
    onset_s: float = 60.0
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    rate_mG_s: float = 0.0
    rise_s: float = 20.0
    hold_s: float = 10.0
    amplitude_mG: float = 0.0
    duration_s: float = 30.0

    @property
    def end_s(self) -> float | None:
        if self.kind == "none":
            return None
        if self.kind == "ramp":
            return self.onset_s + 2 * self.rise_s + self.hold_s
        return self.onset_s + self.duration_s

    def magnitude_mG(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float) - self.onset_s
        if self.kind == "ramp":
            peak = self.rate_mG_s * self.rise_s
            up = np.clip(t, 0, self.rise_s) * self.rate_mG_s
            down = np.clip(t - self.rise_s - self.hold_s, 0, self.rise_s) * self.rate_mG_s
            return np.where(t > 0, np.minimum(up, peak) - down, 0.0)
        if self.kind == "bump":
            x = np.clip(t / self.duration_s, 0, 1)
            return self.amplitude_mG * np.sin(np.pi * x) ** 2
        if self.kind == "step":
            return np.where((t >= 0) & (t < self.duration_s), self.amplitude_mG, 0.0)
        return np.zeros_like(t)

    def field_sensor_mG(self, t_s: np.ndarray) -> np.ndarray:
        ax = np.asarray(self.axis, dtype=float)
        ax = ax / np.linalg.norm(ax)
        return self.magnitude_mG(t_s)[:, None] * ax[None, :]


@dataclass(frozen=True)
class PayloadLoad:
    """A payload drawing ``current_A`` for the first half of every ``period_s`` from ``from_s``.
    ``mG_per_A`` (body) None: it shares the motor wires (field c·ΔI, learnable as motor field)."""
    current_A: float = 0.0
    period_s: float = 20.0
    from_s: float = 0.0
    mG_per_A: tuple[float, float, float] | None = None


def payload_current_A(load: PayloadLoad, t_s: np.ndarray) -> np.ndarray:
    """The payload's current at each time [A] (0 before ``from_s`` and in the off halves)."""
    t = np.asarray(t_s, dtype=float)
    on = (t >= load.from_s) & (np.mod(t - load.from_s, load.period_s) < 0.5 * load.period_s)
    return np.where(on, load.current_A, 0.0)


def payload_field_body_mG(load: PayloadLoad, t_s: np.ndarray, motor_mG_per_A: np.ndarray) -> np.ndarray:
    """The payload's field in the body frame [mG] (N,3)."""
    per_amp = np.asarray(motor_mG_per_A if load.mG_per_A is None else load.mG_per_A, dtype=float)
    return payload_current_A(load, t_s)[:, None] * per_amp[None, :]


@dataclass(frozen=True)
class GroundAnomaly:
    """A point dipole at ``pos_ned_m`` (from the mission origin; down from the ground level, so 0
    is on the ground) with moment ``moment_ned_Am2`` [A·m²]."""
    pos_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    moment_ned_Am2: tuple[float, float, float] = (0.0, 0.0, 0.0)


def anomaly_field_ned_mG(anomaly: GroundAnomaly, pos_ned_m: np.ndarray) -> np.ndarray:
    """The dipole's field at positions (N,3) [m, same frame], NED [mG] (Jackson eq. 5.56)."""
    r = np.asarray(pos_ned_m, dtype=float).reshape(-1, 3) - np.asarray(anomaly.pos_ned_m, dtype=float)
    dist = np.maximum(np.linalg.norm(r, axis=1), 1.0)            # never inside the mass
    r_hat = r / dist[:, None]
    m = np.asarray(anomaly.moment_ned_Am2, dtype=float)
    return (3.0 * (r_hat @ m)[:, None] * r_hat - m[None, :]) / dist[:, None] ** 3


def anomaly_field_body_mG(anomaly: GroundAnomaly, pos_ned_m: np.ndarray, roll_rad: np.ndarray,
                          pitch_rad: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """The dipole's field in the body frame [mG] (N,3) along a flight with this true attitude."""
    c = dcm_body_to_ned(roll_rad, pitch_rad, yaw_rad)
    return np.einsum("nji,nj->ni", c, anomaly_field_ned_mG(anomaly, pos_ned_m))
