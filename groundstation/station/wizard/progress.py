"""Step progress: the net angle turned about one body axis, from the attitude.

Between two attitude samples the body turns by ΔR = R_prevᵀ · R_now (R = C_b^n, body to NED); its
rotation vector φ (log map, ``estimators.rotations.rotation_to_vector_deg``) is in the body
frame, so φ_k is the angle turned about body axis k.  The step's progress is |Σ φ_k| over the
step: a full turn about X gives 360°; wobbling back and forth cancels; a turn about another axis
adds nothing; held still the attitude does not change, so nothing creeps (the sum of the
increments telescopes to the change of attitude).  Near pitch ±90° the Euler angles of ATTITUDE
stop defining roll and yaw separately, so there the gyro's turn between the two attitude samples is
used; without ATTITUDE messages the gyro is integrated throughout (signed, so noise averages out).

The recent rotation rate (|φ| per second over ``still_window_s``) gives the "no motion" hint.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from estimators.rotations import dcm_body_to_ned, rotation_to_vector_deg

__all__ = ["AxisProgress"]

ATTITUDE_STALE_S = 1.0      # no ATTITUDE for this long: integrate the gyro instead
GIMBAL_PITCH_RAD = math.radians(80.0)


def _small_rotation_deg(rel: np.ndarray) -> np.ndarray:
    """Rotation vector (deg) of a rotation matrix; the exact log map
    (``estimators.rotations.rotation_to_vector_deg``) beyond 20°, where the vee of the
    antisymmetric part (sin θ · axis) stops being the angle."""
    w = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]) / 2.0
    s = float(np.linalg.norm(w))
    if s > 0.34:
        return rotation_to_vector_deg(rel)
    return np.degrees(w * (math.asin(s) / s if s > 1e-12 else 1.0))


class AxisProgress:
    """Net rotation about the current step's body axis (0 = X, 1 = Y, 2 = Z, None = no axis)."""

    def __init__(self, still_window_s: float = 2.0) -> None:
        self.still_window_s = still_window_s
        self.net_deg = np.zeros(3)
        self.axis: int | None = None
        self._prev: tuple[float, np.ndarray] | None = None
        self._last_att_t = -math.inf
        self._last_gyro_t: float | None = None
        self._gyro_since_att = np.zeros(3)
        self._recent: deque = deque()          # (t_s, |rotation| deg) of recent increments
        self.last_t = -math.inf

    def reset(self) -> None:
        self.__init__(self.still_window_s)

    def set_axis(self, axis: int | None) -> None:
        self.axis = axis

    def restart_axis(self, axis: int) -> None:
        """The step starts over (after a long link drop)."""
        self.net_deg[axis] = 0.0

    def gap(self) -> None:
        """Samples were lost: the rotation across the gap is not counted."""
        self._prev = None
        self._last_gyro_t = None
        self._gyro_since_att = np.zeros(3)
        self._recent.clear()

    def on_attitude(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        R = dcm_body_to_ned(roll_rad, pitch_rad, yaw_rad)
        prev = self._prev
        self._prev = (t_s, R, abs(pitch_rad) > GIMBAL_PITCH_RAD)
        self._last_att_t = t_s
        gyro_deg, self._gyro_since_att = self._gyro_since_att, np.zeros(3)
        if prev is None or not 0 < t_s - prev[0] < 1.0:
            return
        if prev[2] or self._prev[2]:
            # near pitch ±90° roll and yaw of ATTITUDE are ill-defined (their split is arbitrary):
            # the gyro turned through this interval instead
            self._count(t_s, gyro_deg)
        else:
            self._count(t_s, _small_rotation_deg(prev[1].T @ R))

    def on_gyro(self, t_s: float, gyro_rad_s) -> None:
        last = self._last_gyro_t
        self._last_gyro_t = t_s
        if last is None or not 0 < t_s - last < 1.0:
            return
        step = np.degrees(np.asarray(gyro_rad_s, float)) * (t_s - last)
        if t_s - self._last_att_t < ATTITUDE_STALE_S:
            self._gyro_since_att += step
        else:
            self._count(t_s, step)

    def _count(self, t_s: float, phi_deg: np.ndarray) -> None:
        if not np.all(np.isfinite(phi_deg)):
            return
        if self.axis is not None:
            self.net_deg[self.axis] += phi_deg[self.axis]
        self._recent.append((t_s, float(np.linalg.norm(phi_deg))))
        while self._recent and self._recent[0][0] < t_s - self.still_window_s:
            self._recent.popleft()
        self.last_t = t_s

    @property
    def progress_deg(self) -> np.ndarray:
        return np.abs(self.net_deg)

    def rate_deg_s(self) -> float | None:
        """Mean rotation rate over the last ``still_window_s`` (None until the window is full)."""
        r = self._recent
        if len(r) < 2 or r[-1][0] - r[0][0] < 0.8 * self.still_window_s:
            return None
        return sum(a for _, a in r) / max(r[-1][0] - r[0][0], 1e-6)
