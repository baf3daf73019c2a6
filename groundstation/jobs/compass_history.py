"""Fleet findings from the compass history: sites, anomaly sites, offset drift, payload changes,
interference flights; and ``record_calibration``, which the station calls when it writes an
accepted calibration to a vehicle.

Method (rows = ``groundstation.io.fleet_db`` flight rows with status "ok"):

* **Sites**: take-off positions clustered greedily within ``site_radius_km``.
* **Anomaly sites**: the field-strength and inclination residuals against the WMM (corrections in
  force, fitted motor field removed) of each flight are split by a two-way median polish into
  airframe + site + rest; a site seen by ``anomaly_min_airframes`` airframes whose effect exceeds
  max(``anomaly_strength_mG`` | ``anomaly_inclination_deg``, ``sigma_k`` · 1.2533 · σ / √n) is an
  anomaly site (σ: robust sd of the rest over the fleet, n: the site's flights).  The same polish of the fitted
  offsets gives each site's apparent offset (a local field adds a body-fixed vector in level
  flight), removed before the drift test; flights at an anomaly site are left out of it altogether
  (how much of the local field goes into the fitted offsets depends on the headings flown).
* **Offset drift**: per airframe, compass and calibration segment (a recorded calibration, or a
  change of the corrections in force in the logs, starts a segment), the median of the fitted
  offsets over the last ``window_flights`` flights is compared with the median over the first
  ``window_flights`` (W = 3 or 4 when a segment holds fewer than 2 × ``window_flights`` flights).
  Alarm when |Δ| > max(``floor_mG``, ``sigma_k`` · s), s = 1.2533 · σ · √(2 / W): σ the compass's
  flight-to-flight scatter per axis (robust: 1.4826 · MAD of successive differences / √2, so a slow
  drift does not inflate it; never below ``min_scatter_mG``), 1.2533 the standard error factor of a
  median.  Under no drift each axis of Δ/s is ≈ N(0, 1), so |Δ|/s follows a χ law with 3 degrees of
  freedom: P(χ₃ > 5) = 1.5e-5 per test, ≈ 1.5 % for a thousand tests (20 airframes × 50 flights).
  The fit's own sd (``fit_ofs_sd_*``) is smaller than the flight-to-flight scatter (the site,
  misalignment, the headings flown); flights whose fit sd exceeds ``max_fit_sd_mG`` or
  ``fit_sd_ratio`` × the compass's median fit sd are left out, and so are second copies of a
  flight (a GCS .tlog beside the onboard .bin: same airframe, same start).  Flights with an
  interference alarm stay in: a drifting compass itself raises heading alarms once the nose turns,
  and leaving those out would hide the drift; the medians absorb a disturbed flight.
* **Calibration change**: each recorded calibration against the previous one of the same
  airframe and compass, alarm above ``floor_mG`` + ``sigma_k`` · √(f₁² + f₂²) (f: fitness, mG).
* **Payload change**: the fitted motor field per ampere over an airframe's flights; the split that
  maximises |median after − median before| / s (s as above with the two segment sizes), alarm when
  that exceeds ``sigma_k`` and the change is ≥ ``payload_floor_pct`` of the Earth field at the
  airframe's median peak current.
Units: mG, mG/A, %, deg, km.
"""
from __future__ import annotations

import json
import math
import sqlite3
import time
from contextlib import closing
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from estimators.detection import ned_from_lla
from groundstation.jobs.calibrate.frame import compact, relative_to
from groundstation.io import fleet_db
from groundstation.jsonsafe import jsonable

__all__ = ["offset_summaries", "DriftSettings", "FleetFindings", "analyse_fleet", "refresh_alerts", "record_calibration",
           "record_calibrations", "history_airframe",
           "assign_sites"]

XYZ = ("x", "y", "z")
_MEDIAN_SE = 1.2533          # standard error of a median / standard error of a mean (normal data)


@dataclass(frozen=True)
class DriftSettings:
    """Thresholds of the fleet findings (units in the names); the module docstring justifies them."""
    window_flights: int = 5            # flights per median (fewer, down to 3, on short histories)
    sigma_k: float = 5.0
    floor_mG: float = 10.0
    min_scatter_mG: float = 1.0
    max_fit_sd_mG: float = 15.0        # the review's own limit (review_row.REVIEW_CALIBRATE)
    fit_sd_ratio: float = 2.0          # flights whose fit sd is above this × the airframe's median are left out
    site_radius_km: float = 2.0
    anomaly_strength_mG: float = 15.0
    anomaly_inclination_deg: float = 2.0
    anomaly_min_airframes: int = 2
    payload_floor_pct: float = 4.0
    payload_min_flights: int = 4
    same_flight_s: float = 60.0        # rows of one airframe starting closer than this are one flight


@dataclass
class FleetFindings:
    sites: list[dict]                # name, lat_deg, lon_deg, flights, airframes, strength/inclination effect
    site_of: dict[str, str]          # log_hash -> site name
    alerts: list[dict]               # fleet_db.ALERT_COLUMNS


# ------------------------------------------------------------------------------ helpers
def _col(rows: list[dict], name: str) -> np.ndarray:
    return np.array([np.nan if r.get(name) is None else float(r[name]) for r in rows], dtype=float)


def _vec(rows: list[dict], prefix: str, unit: str = "mG") -> np.ndarray:
    return np.stack([_col(rows, f"{prefix}_{a}_{unit}") for a in XYZ], axis=1) if rows else np.zeros((0, 3))


def _compass_name(row: dict) -> str:
    """"AF-01" for the first compass, "AF-01 compass 2" for the others."""
    k = row.get("compass") or 0
    return row["airframe"] + (f" compass {k + 1}" if k else "")


def _finite_median(values: np.ndarray) -> float:
    """Median of the finite values; NaN (no warning) when there are none."""
    v = values[np.isfinite(values)]
    return float(np.median(v)) if len(v) else float("nan")


def _scatter(values: np.ndarray, floor: float) -> np.ndarray:
    """Per-column flight-to-flight σ: 1.4826 · MAD(successive differences) / √2, at least ``floor``."""
    if len(values) < 3:
        return np.full(values.shape[1], max(floor, 5.0))
    d = np.diff(values, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return np.maximum(1.4826 * mad / math.sqrt(2.0), floor)


def assign_sites(rows: list[dict], radius_km: float) -> tuple[list[dict], dict[str, str]]:
    """Greedy clustering of take-off positions; sites named by their first position."""
    sites: list[dict] = []
    site_of: dict[str, str] = {}
    for r in sorted(rows, key=lambda r: (r.get("start_unix_s") or 0.0)):
        lat, lon = r.get("lat_deg"), r.get("lon_deg")
        if lat is None or lon is None:
            continue
        best = None
        for s in sites:
            n, e = ned_from_lla(lat, lon, s["lat_deg"], s["lon_deg"])
            if math.hypot(float(n), float(e)) <= radius_km * 1000.0:
                best = s
                break
        if best is None:
            best = {"name": f"{abs(lat):.3f}{'N' if lat >= 0 else 'S'} {abs(lon):.3f}{'E' if lon >= 0 else 'W'}",
                    "lat_deg": float(lat), "lon_deg": float(lon), "flights": 0, "airframes": set()}
            sites.append(best)
        best["flights"] += 1
        best["airframes"].add(r.get("airframe"))
        site_of[r["log_hash"]] = best["name"]
    return sites, site_of


def _groups(keys: list) -> dict:
    out: dict = {}
    for i, k in enumerate(keys):
        out.setdefault(k, []).append(i)
    return {k: np.array(v) for k, v in out.items()}


def median_polish(values: np.ndarray, rows_a: list, rows_s: list, sweeps: int = 4) -> tuple[dict, dict, np.ndarray]:
    """values (n, k) = airframe effect + site effect + rest (Tukey's median polish, NaN ignored);
    returns (airframe effects, site effects, rest)."""
    v = np.array(values, dtype=float, copy=True)
    groups = (_groups(rows_a), _groups(rows_s))
    effects = ({a: np.zeros(v.shape[1]) for a in groups[0]}, {s: np.zeros(v.shape[1]) for s in groups[1]})
    for _ in range(sweeps):
        for eff, grp in zip(effects, groups):
            for key, idx in grp.items():
                block = v[idx]
                finite = np.isfinite(block)
                if finite.all():
                    m = np.median(block, axis=0)
                else:     # np.nanmedian is slow on small blocks; NaN rows are rare
                    m = np.array([np.median(c[f]) if f.any() else 0.0 for c, f in zip(block.T, finite.T)])
                eff[key] = eff[key] + m
                v[idx] -= m
    return effects[0], effects[1], v


# ------------------------------------------------------------------------------ findings
def _alert(kind: str, message: str, **fields) -> dict:
    out = {n: None for n, _ in fleet_db.ALERT_COLUMNS}
    out.update(kind=kind, message=message, **fields)
    return out


def _site_alerts(ok: list[dict], sites: list[dict], site_of: dict, s: DriftSettings) -> tuple[list[dict], dict]:
    """Anomaly sites, and the apparent offset of every site (to remove before the drift test)."""
    keys_a = [r["airframe"] for r in ok]
    keys_s = [site_of.get(r["log_hash"], "?") for r in ok]
    field = np.stack([_col(ok, "strength_resid_mG"), _col(ok, "inclination_resid_deg")], axis=1)
    _, site_field, rest = median_polish(field, keys_a, keys_s)
    _, site_offsets, _ = median_polish(_vec(ok, "fit_ofs"), keys_a, keys_s)
    sigma = np.array([1.4826 * np.median(np.abs(c[np.isfinite(c)])) if np.isfinite(c).any() else np.inf
                      for c in rest.T])
    alerts = []
    for site in sites:
        eff = site_field.get(site["name"], np.zeros(2))
        site.update(strength_effect_mG=round(float(eff[0]), 2), inclination_effect_deg=round(float(eff[1]), 3),
                    offset_effect_mG=[round(float(v), 2) for v in site_offsets.get(site["name"], np.zeros(3))])
        seen = len(site["airframes"] - {None})
        limit = np.maximum([s.anomaly_strength_mG, s.anomaly_inclination_deg],
                           s.sigma_k * _MEDIAN_SE * sigma / math.sqrt(max(site["flights"], 1)))
        site["anomaly"] = bool(seen >= s.anomaly_min_airframes and np.any(np.abs(eff) > limit))
        if site["anomaly"]:
            alerts.append(_alert("anomaly_site", f"site {site['name']}: field {eff[0]:+.0f} mG, inclination "
                                 f"{eff[1]:+.1f} deg against the WMM, seen by {seen} airframes",
                                 site=site["name"], lat_deg=site["lat_deg"], lon_deg=site["lon_deg"],
                                 value=float(eff[0]), threshold=s.anomaly_strength_mG,
                                 unit="mG"))
    for site in sites:
        site["airframes"] = sorted(a for a in site["airframes"] if a is not None)
    return alerts, site_offsets


def _segments(rows: list[dict], cal_times: list[float]) -> list[list[dict]]:
    """Split one airframe's rows (time order) at recorded calibrations and at in-force changes."""
    segs: list[list[dict]] = [[]]
    prev_cal = None
    cal_iter = sorted(cal_times)
    for r in rows:
        cal = np.array([r.get(f"cal_ofs_{a}_mG") or 0.0 for a in XYZ])
        t = r.get("start_unix_s") or 0.0
        new_cal = bool(cal_iter and cal_iter[0] <= t)
        while cal_iter and cal_iter[0] <= t:
            cal_iter.pop(0)
        if segs[-1] and (new_cal or (prev_cal is not None and np.max(np.abs(cal - prev_cal)) > 0.5)):
            segs.append([])
        segs[-1].append(r)
        prev_cal = cal
    return [g for g in segs if g]


def _distinct_flights(rows: list[dict], same_flight_s: float) -> list[dict]:
    """A compass's rows (time order), one per flight: a flight logged twice (the GCS .tlog and the
    onboard .bin, or a damaged copy) keeps the row with fewer warnings."""
    out: list[dict] = []
    for r in rows:
        if out and abs((r.get("start_unix_s") or 0.0) - (out[-1].get("start_unix_s") or 0.0)) < same_flight_s:
            if (r.get("warnings") is None) and out[-1].get("warnings") is not None:
                out[-1] = r
            continue
        out.append(r)
    return out


def _drift_in_segment(seg: list[dict], site_of: dict, site_offsets: dict, anomalous: set[str],
                      s: DriftSettings) -> dict | None:
    seg = [r for r in _distinct_flights(seg, s.same_flight_s) if site_of.get(r["log_hash"]) not in anomalous]
    sd = np.fmax.reduce(_vec(seg, "fit_ofs_sd"), axis=1) if seg else np.zeros(0)   # NaN only when all are
    typical = float(np.nanmedian(sd)) if np.isfinite(sd).any() else np.inf
    limit = min(s.max_fit_sd_mG, s.fit_sd_ratio * typical)
    use = [r for r, v in zip(seg, sd) if np.isfinite(v) and v <= limit]
    W = min(s.window_flights, len(use) // 2)
    if W < 3:
        return None
    ofs = _vec(use, "fit_ofs") - np.array([site_offsets.get(site_of.get(r["log_hash"]), np.zeros(3)) for r in use])
    sigma = _scatter(ofs, s.min_scatter_mG)
    se = _MEDIAN_SE * sigma * math.sqrt(2.0 / W)
    ref = np.median(ofs[:W], axis=0)
    for j in range(2 * W - 1, len(use)):
        delta = np.median(ofs[j - W + 1:j + 1], axis=0) - ref
        z = float(np.linalg.norm(delta / se))
        size = float(np.linalg.norm(delta))
        if z > s.sigma_k and size > s.floor_mG:
            r = use[j]
            return _alert("offset_drift", f"{_compass_name(r)}: fitted offsets moved {size:.0f} mG "
                          f"({', '.join(f'{v:+.0f}' for v in delta)} mG) since {use[0].get('date') or 'the first flight'}"
                          f"; {z:.1f} sigma (flight-to-flight sigma {', '.join(f'{v:.1f}' for v in sigma)} mG)",
                          airframe=r["airframe"], unix_s=r.get("start_unix_s"), log_hash=r["log_hash"],
                          value=size, threshold=max(s.floor_mG, s.sigma_k * float(np.linalg.norm(se)) / math.sqrt(3)),
                          sigma=z, unit="mG")
    return None


def _payload_alert(rows: list[dict], s: DriftSettings) -> dict | None:
    rows = _distinct_flights(rows, s.same_flight_s)
    k = _vec(rows, "motor", "mG_per_A")
    keep = np.all(np.isfinite(k), axis=1)
    rows, k = [r for r, ok in zip(rows, keep) if ok], k[keep]
    m = s.payload_min_flights
    if len(rows) < 2 * m:
        return None
    sigma = _scatter(k, 0.02)
    best = (0.0, None, None)
    for j in range(m, len(rows) - m + 1):
        delta = np.median(k[j:], axis=0) - np.median(k[:j], axis=0)
        se = _MEDIAN_SE * sigma * math.sqrt(1.0 / j + 1.0 / (len(rows) - j))
        z = float(np.linalg.norm(delta / se))
        if z > best[0]:
            best = (z, j, delta)
    z, j, delta = best
    if j is None:
        return None
    current = _finite_median(_col(rows, "current_max_A"))
    strength = _finite_median(_col(rows, "wmm_strength_mG"))
    pct = float(np.linalg.norm(delta)) * current / strength * 100.0 if strength > 0 else float("nan")
    if z <= s.sigma_k or not pct >= s.payload_floor_pct:
        return None
    r = rows[j]
    before, after = _finite_median(_col(rows[:j], "interference_pct")), _finite_median(_col(rows[j:], "interference_pct"))
    return _alert("payload_change", f"{_compass_name(r)}: motor-current field changed by {np.linalg.norm(delta):.2f} mG/A "
                  f"from {r.get('date') or 'this flight'} on (interference {before:.0f} % -> {after:.0f} % of the Earth field)",
                  airframe=r["airframe"], unix_s=r.get("start_unix_s"), log_hash=r["log_hash"], value=pct,
                  threshold=s.payload_floor_pct, sigma=z, unit="% of Earth field")


def _calibration_alerts(cals: list[dict], s: DriftSettings) -> list[dict]:
    out = []
    by_key: dict[tuple, dict] = {}
    for c in cals:
        key = (c["airframe"], c.get("compass") or 0)
        prev = by_key.get(key)
        by_key[key] = c
        if prev is None:
            continue
        delta = np.array([c[f"ofs_{a}_mG"] - prev[f"ofs_{a}_mG"] for a in XYZ], dtype=float)
        f = math.hypot(prev.get("fitness_mG") or 0.0, c.get("fitness_mG") or 0.0)
        limit = s.floor_mG + s.sigma_k * f
        if np.linalg.norm(delta) > limit:
            out.append(_alert("calibration_change", f"{c['airframe']}: calibration moved the offsets "
                              f"{np.linalg.norm(delta):.0f} mG from the previous one",
                              airframe=c["airframe"], unix_s=c["unix_s"], value=float(np.linalg.norm(delta)),
                              threshold=limit, unit="mG"))
    return out


def _interference_alerts(ok: list[dict]) -> list[dict]:
    return [_alert("interference", f"{r['airframe']}: {r['alarm_count']} interference alarm(s) in {r['file_name']}, "
                   f"first at {r.get('first_alarm_s')} s ({r.get('alarm_evidence') or 'no evidence named'})",
                   airframe=r["airframe"], unix_s=r.get("start_unix_s"), log_hash=r["log_hash"],
                   value=float(r["alarm_count"]), unit="alarms")
            for r in ok if (r.get("alarm_count") or 0) > 0]


def analyse_fleet(rows: list[dict], calibrations: list[dict] = (), settings: DriftSettings = DriftSettings()
                  ) -> FleetFindings:
    """Sites and every alert from the history (pure: rows and calibration records in, findings out)."""
    ok = [r for r in rows if r.get("status") == "ok"]
    ok.sort(key=lambda r: (r.get("start_unix_s") or 0.0, r["log_hash"]))
    sites, site_of = assign_sites(ok, settings.site_radius_km)
    alerts, site_offsets = _site_alerts(ok, sites, site_of, settings) if ok else ([], {})
    cals = sorted(calibrations, key=lambda c: (c.get("unix_s") or 0.0))
    anomalous = {site["name"] for site in sites if site.get("anomaly")}
    by_compass: dict[tuple[str, int], list[dict]] = {}
    for r in ok:
        by_compass.setdefault((r["airframe"], r.get("compass") or 0), []).append(r)
    for (airframe, compass), mine in sorted(by_compass.items()):
        cal_times = [c["unix_s"] for c in cals if c["airframe"] == airframe and (c.get("compass") or 0) == compass]
        for seg in _segments(mine, cal_times):
            a = _drift_in_segment(seg, site_of, site_offsets, anomalous, settings)
            if a:
                alerts.append(a)
        p = _payload_alert(mine, settings)
        if p:
            alerts.append(p)
    alerts += _calibration_alerts(cals, settings)
    alerts += _interference_alerts([r for r in ok if (r.get("compass") or 0) == 0])   # an alarm is per log
    return FleetFindings(sites, site_of, alerts)


def _weighted_line(t_d: np.ndarray, y: np.ndarray, sd: np.ndarray) -> tuple[float, float, float, float]:
    """Weighted least squares y = a + b (t − t̄_w), w = 1/sd²: (a at the weighted mean time, its 1σ,
    b per day, its 1σ), the 1σ scaled by the Birge ratio √(χ²/(n − 2)) when above 1 (the flights
    scatter more than their stated 1σ: site, headings flown)."""
    w = 1.0 / sd ** 2
    tm = float(np.sum(w * t_d) / np.sum(w))
    x = t_d - tm
    sxx = float(np.sum(w * x * x))
    a = float(np.sum(w * y) / np.sum(w))
    b = float(np.sum(w * x * y) / sxx) if sxx > 0 else 0.0
    chi2 = float(np.sum(w * (y - a - b * x) ** 2))
    birge = math.sqrt(max(1.0, chi2 / max(len(y) - 2, 1)))
    return a, birge / math.sqrt(float(np.sum(w))), b, (birge / math.sqrt(sxx) if sxx > 0 else float("nan"))


def offset_summaries(rows: list[dict], settings: DriftSettings = DriftSettings()) -> list[dict]:
    """Each airframe's and compass's in-flight offsets across its flights (review rows with a fit,
    ``ok`` or ``weak``; one row per flight, ``_distinct_flights``), with their uncertainty:

    * ``spread_mG``: the flight-to-flight SD per axis, beside ``stated_sd_mG`` (the median per-flight 1σ);
    * ``combined_mG`` ± ``combined_sd_mG``: the flights combined, inverse-variance weighted by their
      stated 1σ (the offsets are the raw sensor's, comparable across calibration changes), the 1σ
      scaled by the Birge ratio when the flights scatter more than they state — the combined answer
      of several weak flights that alone are not recommended;
    * ``drift_mG_per_30d`` ± ``drift_sd_mG_per_30d``: the weighted linear trend over time (same
      weights and scaling), and ``drift_sigma`` the largest |trend|/1σ of the three axes.
    Flights of a site the findings call anomalous are kept (this is a summary, not an alert)."""
    mine: dict[tuple[str, int], list[dict]] = {}
    for r in sorted((r for r in rows if r.get("status") == "ok"), key=lambda r: (r.get("start_unix_s") or 0.0)):
        mine.setdefault((r.get("airframe") or "?", r.get("compass") or 0), []).append(r)
    out = []
    for (airframe, compass), group in sorted(mine.items()):
        group = _distinct_flights(group, settings.same_flight_s)
        ofs, sd = _vec(group, "fit_ofs"), _vec(group, "fit_ofs_sd")
        use = np.all(np.isfinite(ofs), axis=1) & np.all(np.isfinite(sd) & (sd > 0), axis=1)
        if not use.any():
            continue
        ofs, sd = ofs[use], sd[use]
        t_d = np.array([(r.get("start_unix_s") or 0.0) / 86400.0 for r, u in zip(group, use) if u])
        n = len(ofs)
        fits = [_weighted_line(t_d, ofs[:, i], sd[:, i]) if n >= 3 and np.ptp(t_d) > 0 else None for i in range(3)]
        w = 1.0 / sd ** 2
        mean = np.sum(w * ofs, axis=0) / np.sum(w, axis=0)
        chi2 = np.sum(w * (ofs - mean) ** 2, axis=0)
        combined_sd = np.sqrt(np.maximum(1.0, chi2 / max(n - 1, 1)) / np.sum(w, axis=0))
        r2 = lambda v: [round(float(x), 2) for x in v]  # noqa: E731
        rec = {"airframe": airframe, "compass": compass, "flights": n,
               "first_unix_s": float(t_d.min() * 86400.0), "last_unix_s": float(t_d.max() * 86400.0),
               "combined_mG": r2(mean), "combined_sd_mG": r2(combined_sd),
               "spread_mG": r2(np.std(ofs, axis=0, ddof=1)) if n >= 2 else None,
               "stated_sd_mG": r2(np.median(sd, axis=0)), "drift_mG_per_30d": None, "drift_sd_mG_per_30d": None,
               "drift_sigma": None}
        if all(f is not None for f in fits):
            slope = np.array([f[2] for f in fits]) * 30.0
            slope_sd = np.array([f[3] for f in fits]) * 30.0
            rec.update(drift_mG_per_30d=r2(slope), drift_sd_mG_per_30d=r2(slope_sd),
                       drift_sigma=round(float(np.max(np.abs(slope) / slope_sd)), 2))
        name = airframe + (f" compass {compass + 1}" if compass else "")
        vec = lambda v: ", ".join(f"{x:.1f}" for x in v)  # noqa: E731
        line = (f"{name}: {n} flight(s); offsets [{vec(rec['combined_mG'])}] ± [{vec(rec['combined_sd_mG'])}] mG "
                "combined (1σ)")
        if rec["spread_mG"] is not None:
            line += f"; spread [{vec(rec['spread_mG'])}] mG flight to flight (stated 1σ [{vec(rec['stated_sd_mG'])}])"
        if rec["drift_mG_per_30d"] is not None:
            line += (f"; drift [{vec(rec['drift_mG_per_30d'])}] ± [{vec(rec['drift_sd_mG_per_30d'])}] mG per 30 days "
                     f"({rec['drift_sigma']:.1f}σ)")
        rec["line"] = line
        out.append(rec)
    return out


def refresh_alerts(con, settings: DriftSettings = DriftSettings()) -> FleetFindings:
    """Recompute the findings from the database and rewrite its derived tables (alerts, sites)."""
    findings = analyse_fleet(fleet_db.flight_rows(con), fleet_db.calibration_rows(con), settings)
    fleet_db.replace_findings(con, findings.alerts, findings.sites, findings.site_of)
    return findings


def _calibration_record(airframe: str, compass: int, result: dict, unix_s: float, **where) -> dict:
    offsets = result.get("offsets_mG")
    if not offsets or len(offsets) != 3 or not all(v is not None and math.isfinite(v) for v in offsets):
        raise ValueError(f"the calibration result of compass {compass} holds no finite offsets_mG")
    return {"airframe": airframe, "unix_s": unix_s, "compass": int(compass),
            **{f"ofs_{a}_mG": float(v) for a, v in zip(XYZ, offsets)},
            "matrix_json": json.dumps(jsonable(result.get("matrix"))), "fitness_mG": result.get("residual_rms_mG"),
            "orientation": json.dumps(jsonable(result.get("orientation", result.get("misalignment_deg")))),
            "wmm_strength_mG": result.get("expected_field_mG"),
            "wmm_inclination_deg": result.get("expected_inclination_deg"),
            "wmm_declination_deg": result.get("expected_declination_deg"), "note": result.get("message"),
            "relative_to": relative_to(result), "calibration_json": json.dumps(jsonable(compact(result)), allow_nan=False),
            "recorded_unix_s": time.time(),
            **where}


def record_calibrations(db_path: str | Path, airframe: str, results: dict[int, dict], *, written_to_vehicle: bool = True,
                        source: str = "station", unix_s: float | None = None, lat_deg: float | None = None,
                        lon_deg: float | None = None, site: str | None = None,
                        settings: DriftSettings = DriftSettings()) -> dict:
    """Append accepted calibrations ({compass: the calibrate JSON object: offsets_mG, matrix,
    residual_rms_mG, expected_field_mG / _inclination_deg / _declination_deg, orientation ...}) to the
    airframe's history and refresh the alerts once.  Returns {"ids": record ids, "alerts": alerts of
    this airframe}.  Raises ValueError when a result holds no offsets (nothing is written then)."""
    when = time.time() if unix_s is None else float(unix_s)
    records = [_calibration_record(airframe, k, r, when, source=source, lat_deg=lat_deg, lon_deg=lon_deg, site=site,
                                   written_to_vehicle=int(bool(written_to_vehicle))) for k, r in sorted(results.items())]
    with closing(fleet_db.connect(db_path)) as con:
        ids = [fleet_db.insert_calibration(con, rec) for rec in records]
        findings = refresh_alerts(con, settings)
    return {"ids": ids, "alerts": [a for a in findings.alerts if a["airframe"] == airframe]}


def record_calibration(db_path: str | Path, airframe: str, result: dict, *, compass: int = 0, **kw) -> dict:
    """One compass's calibration (``record_calibrations``); returns {"id", "alerts"}."""
    out = record_calibrations(db_path, airframe, {compass: result}, **kw)
    return {"id": out["ids"][0], "alerts": out["alerts"]}


def history_airframe(db_path: str | Path, identity: str) -> str:
    """The name a vehicle identity (``airframes.identity_key``) has in the history (the review's
    airframe mapping), else the identity itself."""
    try:
        with closing(fleet_db.connect(db_path, read_only=True)) as con:
            return fleet_db.airframe_of_identity(con, identity) or identity
    except (FileNotFoundError, sqlite3.Error):
        return identity


def settings_dict(settings: DriftSettings) -> dict:
    return asdict(settings)
