"""After writing: the heading check and the deviation card.

**Heading check.**  The crew points the vehicle at a known true bearing (a runway, a surveyed
line, a distant landmark) or walks it straight for a few metres.  The compass heading is the
tilt-compensated heading (seed 000 eq. 11–13, ``estimators.heading``) of the first compass as
the vehicle now reports it, plus the WMM declination; its circular mean over the window is
compared with the bearing, or with the GPS course of the walk (first to last fix, at least
``MIN_WALK_M``).

**Deviation card.**  A ship's compass card: heading error against heading.  From the dance, the
stretches held within ``LEVEL_DEG`` of level and turned through at least half a circle (the Z
turn) give a reference yaw independent of the compass: the gyro yaw rate
ψ' = (q sin φ + r cos φ) / cos θ integrated over the stretch.  The error of the compass heading
before (the field as the vehicle reported it) and after the new calibration is binned by heading
in 30° bins.  A dance cannot see a constant heading offset (the gyro reference has no north),
so each curve is shown about its own mean; the heading check measures the constant part.
"""
from __future__ import annotations

import math

import numpy as np

from estimators.heading import tilt_compensated_heading_rad
from estimators.rotations import wrap_angle_deg
from groundstation.station.wizard.fit import attitude_at

__all__ = ["HeadingCheck", "deviation_card", "compass_heading_deg", "circular_mean_deg", "MIN_WALK_M"]

MIN_WALK_M = 5.0
LEVEL_DEG = 20.0
BIN_DEG = 30.0


def circular_mean_deg(a_deg: np.ndarray) -> float:
    a = np.radians(np.asarray(a_deg, float))
    return float(math.degrees(math.atan2(np.mean(np.sin(a)), np.mean(np.cos(a)))) % 360.0)


def compass_heading_deg(mag_mG: np.ndarray, roll_rad, pitch_rad, declination_deg: float) -> np.ndarray:
    """True heading (deg, 0..360) from the body-frame field, attitude and declination."""
    return (np.degrees(tilt_compensated_heading_rad(mag_mG, roll_rad, pitch_rad)) + declination_deg) % 360.0


class HeadingCheck:
    """One heading check: "bearing" (held at a known bearing) or "walk" (GPS course)."""

    def __init__(self, kind: str, bearing_deg: float | None, duration_s: float, declination_deg: float | None) -> None:
        self.kind, self.bearing_deg, self.duration_s = kind, bearing_deg, duration_s
        self.declination_deg = declination_deg
        self.headings: list[tuple[float, float]] = []      # t_s, heading deg
        self.fixes: list[tuple[float, float, float]] = []  # t_s, north m, east m
        self.t0: float | None = None
        self.state = "measuring"
        self.result: dict | None = None

    def add_heading(self, t_s: float, heading_deg: float) -> None:
        if self.state != "measuring":
            return
        self.t0 = t_s if self.t0 is None else self.t0
        self.headings.append((t_s, heading_deg))
        if self.kind == "bearing" and t_s - self.t0 >= self.duration_s:
            self.finish()

    def add_fix(self, t_s: float, lat_deg: float, lon_deg: float) -> None:
        if self.state == "measuring" and self.kind == "walk":
            if self.fixes:
                lat0, lon0 = self._origin
                n = math.radians(lat_deg - lat0) * 6378137.0
                e = math.radians(lon_deg - lon0) * 6378137.0 * math.cos(math.radians(lat0))
                self.fixes.append((t_s, n, e))
            else:
                self._origin = (lat_deg, lon_deg)
                self.fixes.append((t_s, 0.0, 0.0))

    def finish(self) -> dict:
        self.state = "done"
        h = np.array([x[1] for x in self.headings])
        out: dict = {"kind": self.kind, "samples": int(len(h)), "declination_deg": self.declination_deg}
        if len(h) < 5:
            out.update(ok=False, message="too few compass samples: is the link up?")
        else:
            heading = circular_mean_deg(h)
            spread = float(np.std(wrap_angle_deg(h - heading)))
            out.update(heading_deg=round(heading, 2), spread_deg=round(spread, 2))
            reference = self.bearing_deg if self.kind == "bearing" else self._course(out)
            if reference is not None:
                err = float(wrap_angle_deg(heading - reference))
                out.update(ok=True, reference_deg=round(reference, 2), error_deg=round(err, 2),
                           message=f"compass {heading:.1f}° vs {'bearing' if self.kind == 'bearing' else 'GPS course'} "
                                   f"{reference:.1f}°: error {err:+.1f}°")
            else:
                out.setdefault("ok", False)
        if self.declination_deg is None:
            out["message"] = out.get("message", "") + " (no GPS: declination unknown, magnetic heading shown)"
        self.result = out
        return out

    def _course(self, out: dict) -> float | None:
        f = np.array(self.fixes)
        if len(f) < 2 or math.hypot(f[-1, 1], f[-1, 2]) < MIN_WALK_M:
            out.update(ok=False, message=f"walk at least {MIN_WALK_M:.0f} m in a straight line (GPS saw "
                                         f"{0.0 if len(f) < 2 else math.hypot(f[-1, 1], f[-1, 2]):.1f} m)")
            return None
        course = math.degrees(math.atan2(f[-1, 2], f[-1, 1])) % 360.0
        d = math.hypot(f[-1, 1], f[-1, 2])
        ux, uy = f[-1, 1] / d, f[-1, 2] / d
        off_line = np.abs(f[:, 1] * uy - f[:, 2] * ux)
        out.update(distance_m=round(d, 1), off_line_m=round(float(off_line.max()), 2))
        return course

    def snapshot(self) -> dict:
        return {"kind": self.kind, "state": self.state, "bearing_deg": self.bearing_deg,
                "samples": len(self.headings), "result": self.result,
                "distance_m": round(math.hypot(self.fixes[-1][1], self.fixes[-1][2]), 1) if len(self.fixes) > 1 else 0.0}


def _gyro_yaw_deg(imu: np.ndarray, att_at_imu: np.ndarray) -> np.ndarray:
    roll, pitch = att_at_imu[:, 0], att_at_imu[:, 1]
    rate = (imu[:, 2] * np.sin(roll) + imu[:, 3] * np.cos(roll)) / np.cos(pitch)
    dt = np.diff(imu[:, 0], prepend=imu[0, 0])
    dt[(dt <= 0) | (dt > 0.5)] = 0.0
    return np.degrees(np.cumsum(rate * dt))


def _level_runs(level: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], level.astype(int), [0]])))
    return list(zip(edges[::2], edges[1::2]))


HARMONIC_CHI2 = 18.47        # χ²(4) at p = 0.001
CORRELATION_S = 0.5          # residuals closer than this in time are not independent


def _deviation_model(t: np.ndarray, heading_deg: np.ndarray, err_deg: np.ndarray, run: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """The classic deviation model e = A_run + D_run·t + B sin ψ + C cos ψ + E sin 2ψ + F cos 2ψ:
    an offset and a linear drift per level run (the gyro reference has no north and drifts: neither
    is deviation) and the four harmonics shared.  Returns (harmonic coefficients deg, their
    covariance — OLS scaled by n / n_eff, n_eff = span / CORRELATION_S —, Wald χ²)."""
    psi = np.radians(heading_deg)
    runs = np.unique(run)
    cols = []
    for r in runs:
        m = (run == r).astype(float)
        tr = np.where(run == r, t - t[run == r].mean(), 0.0)
        cols += [m, tr]
    H = np.column_stack([np.sin(psi), np.cos(psi), np.sin(2 * psi), np.cos(2 * psi)])
    X = np.column_stack(cols + [H])
    coef, *_ = np.linalg.lstsq(X, err_deg, rcond=None)
    e = err_deg - X @ coef
    n, p = X.shape
    span = sum(float(np.ptp(t[run == r])) for r in runs)
    inflate = max(1.0, n / max(span / CORRELATION_S, 1.0))
    cov = np.linalg.pinv(X.T @ X) * float(e @ e) / max(n - p, 1) * inflate
    h, V = coef[-4:], cov[-4:, -4:]
    try:
        chi2 = float(h @ np.linalg.solve(V, h))
    except np.linalg.LinAlgError:
        chi2 = float("nan")
    return h, V, chi2


def _harmonics_at(h: np.ndarray, heading_deg) -> np.ndarray:
    psi = np.radians(np.asarray(heading_deg, float))
    return h[0] * np.sin(psi) + h[1] * np.cos(psi) + h[2] * np.sin(2 * psi) + h[3] * np.cos(2 * psi)


def deviation_card(mag_t: np.ndarray, before_mG: np.ndarray, after_mG: np.ndarray, attitude: np.ndarray,
                   imu: np.ndarray, declination_deg: float) -> dict | None:
    """Heading error against heading (30° bins) before and after — the fitted deviation model
    (``_deviation_model``: harmonics of the heading, each run's offset and gyro drift removed) at
    the bin centres, with whether it is beyond the noise (``*_significant``: Wald χ² of the
    harmonics past ``HARMONIC_CHI2``).  None when the dance held no level turn of at least 180°."""
    if len(imu) < 10 or len(attitude) < 10:
        return None
    att_imu = attitude_at(attitude, imu[:, 0])
    level = np.all(np.abs(np.degrees(att_imu[:, :2])) < LEVEL_DEG, axis=1)
    rows = []
    for i, (a, b) in enumerate(_level_runs(level)):
        yaw = _gyro_yaw_deg(imu[a:b], att_imu[a:b])
        if len(yaw) < 10 or np.ptp(yaw) < 180.0:
            continue
        sel = (mag_t >= imu[a, 0]) & (mag_t <= imu[b - 1, 0])
        if sel.sum() < 10:
            continue
        ref = np.interp(mag_t[sel], imu[a:b, 0], yaw)
        att = attitude_at(attitude, mag_t[sel])
        hb = compass_heading_deg(before_mG[sel], att[:, 0], att[:, 1], declination_deg)
        ha = compass_heading_deg(after_mG[sel], att[:, 0], att[:, 1], declination_deg)
        eb, ea = wrap_angle_deg(hb - ref), wrap_angle_deg(ha - ref)
        rows.append(np.column_stack([ha, wrap_angle_deg(eb - circular_mean_deg(eb)),
                                     wrap_angle_deg(ea - circular_mean_deg(ea)), mag_t[sel], np.full(sel.sum(), i)]))
    if not rows:
        return None
    r = np.vstack(rows)
    hb_, Vb, chi_b = _deviation_model(r[:, 3], r[:, 0], r[:, 1], r[:, 4])
    ha_, Va, chi_a = _deviation_model(r[:, 3], r[:, 0], r[:, 2], r[:, 4])
    bins = np.floor(r[:, 0] / BIN_DEG).astype(int) % int(360 / BIN_DEG)
    centres = [(k + 0.5) * BIN_DEG for k in range(int(360 / BIN_DEG)) if (bins == k).sum() >= 3]
    b_dev = [round(float(v), 2) for v in _harmonics_at(hb_, centres)]
    a_dev = [round(float(v), 2) for v in _harmonics_at(ha_, centres)]
    fine = np.arange(0.0, 360.0, 5.0)
    sd_a = float(np.degrees(0) + np.sqrt(max(float(np.trace(Va)), 0.0)))
    return {"heading_deg": centres, "before_deg": b_dev, "after_deg": a_dev, "samples": int(len(r)),
            "max_before_deg": round(float(np.max(np.abs(_harmonics_at(hb_, fine)))), 2) if centres else None,
            "max_after_deg": round(float(np.max(np.abs(_harmonics_at(ha_, fine)))), 2) if centres else None,
            "after_sd_deg": round(sd_a, 3), "before_significant": bool(chi_b > HARMONIC_CHI2),
            "after_significant": bool(chi_a > HARMONIC_CHI2),
            "note": "fitted deviation (harmonics of the heading; offset and gyro drift removed); a constant "
                    "offset needs the heading check"}
