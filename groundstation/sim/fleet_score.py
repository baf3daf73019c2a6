"""Scores a fleet review against the simulated fleet's truth (``groundstation.sim.fleet``).

``score_review(truth, rows, alerts)``: rows are the history's flight rows (dicts), alerts its
alerts; airframes are matched by name (the mapping file's) or by their ``serial:N`` identity.
Found means: every drifting airframe has an ``offset_drift`` alert and no steady airframe has one;
the payload airframe a ``payload_change`` alert within ``payload_tolerance_flights`` of the true
flight; every anomaly site an ``anomaly_site`` alert within ``site_tolerance_km``; every planted
interference event a combined alarm in its log (any of them: ``alarm_intervals_s``) starting between
2 s before the onset and 10 s after the end; every damaged file a row that says so ("error", or read with warnings).
"""
from __future__ import annotations

import json
import math
from pathlib import PurePath

import numpy as np

__all__ = ["score_review"]


def _km(lat1, lon1, lat2, lon2) -> float:
    dlat = math.radians(lat2 - lat1)
    dlon = math.radians(lon2 - lon1) * math.cos(math.radians((lat1 + lat2) / 2))
    return 6371.0 * math.hypot(dlat, dlon)


def _by_file(rows: list[dict]) -> dict[str, dict]:
    out = {}
    for r in rows:
        parts = PurePath(str(r.get("path") or "")).parts
        if len(parts) >= 2:
            out[f"{parts[-2]}/{parts[-1]}"] = r
    return out


def _names(vehicle: dict) -> set[str]:
    return {vehicle["airframe"], f"serial:{vehicle['serial']}"}


def _drift(truth: dict, alerts: list[dict]) -> dict:
    drift_airframes = {a["airframe"] for a in alerts if a["kind"] == "offset_drift"}
    planted = [v for v in truth["vehicles"] if v["role"] == "drift"]
    steady = [v for v in truth["vehicles"] if v["role"] != "drift"]
    return {"planted": len(planted), "found": sum(bool(_names(v) & drift_airframes) for v in planted),
            "missed": [v["airframe"] for v in planted if not _names(v) & drift_airframes],
            "steady_airframes": len(steady),
            "false": [v["airframe"] for v in steady if _names(v) & drift_airframes]}


def _payload(truth: dict, alerts: list[dict], rows_by_hash: dict, tolerance: int) -> dict:
    alerts = [a for a in alerts if a["kind"] == "payload_change"]
    planted = [v for v in truth["vehicles"] if v["payload_change_flight"] is not None]
    found, errors, missed = 0, [], []
    for v in planted:
        mine = [a for a in alerts if a["airframe"] in _names(v)]
        flight = None
        for a in mine:
            row = rows_by_hash.get(a.get("log_hash"))
            name = PurePath(str(row.get("path"))).stem if row else ""
            if name.startswith("flight-"):
                flight = int(name.split("-")[1])
        if flight is not None and abs(flight - v["payload_change_flight"]) <= tolerance:
            found += 1
            errors.append(flight - v["payload_change_flight"])
        else:
            missed.append(v["airframe"])
    others = [v for v in truth["vehicles"] if v["payload_change_flight"] is None]
    return {"planted": len(planted), "found": found, "missed": missed, "flight_error": errors,
            "false": [v["airframe"] for v in others if any(a["airframe"] in _names(v) for a in alerts)]}


def _sites(truth: dict, alerts: list[dict], tolerance_km: float) -> dict:
    found_sites = [a for a in alerts if a["kind"] == "anomaly_site" and a.get("lat_deg") is not None]
    planted = [s for s in truth["sites"] if s["anomaly_ned_mG"]]
    near = lambda a, s: _km(a["lat_deg"], a["lon_deg"], s["lat_deg"], s["lon_deg"]) <= tolerance_km  # noqa: E731
    return {"planted": len(planted), "found": sum(any(near(a, s) for a in found_sites) for s in planted),
            "missed": [s["name"] for s in planted if not any(near(a, s) for a in found_sites)],
            "false": [a["site"] for a in found_sites if not any(near(a, s) for s in planted)]}


def _alarm_starts(row: dict) -> list[float]:
    """Start times of every combined alarm of the row (``alarm_intervals_s``; rows written before
    that column: the first alarm only)."""
    if row.get("alarm_intervals_s"):
        return [float(a[0]) for a in json.loads(row["alarm_intervals_s"]) if a[0] is not None]
    return [float(row["first_alarm_s"])] if row.get("alarm_count") and row.get("first_alarm_s") is not None else []


def _interference(truth: dict, by_file: dict) -> dict:
    planted, found, missed, delays = 0, 0, [], []
    false_flights, clean = 0, 0
    for f in truth["flights"]:
        row = by_file.get(f["file"])
        alarms = (row or {}).get("alarm_count") or 0
        if f["interference"]:
            planted += 1
            i = f["interference"]
            starts = [t for t in _alarm_starts(row or {}) if i["onset_s"] - 2.0 <= t <= i["end_s"] + 10.0]
            if starts:
                found += 1
                delays.append(starts[0] - i["onset_s"])
            else:
                missed.append(f["file"])
        elif row is not None:
            clean += 1
            false_flights += bool(alarms)
    return {"planted": planted, "found": found, "missed": missed,
            "median_delay_s": float(np.median(delays)) if delays else None,
            "clean_flights": clean, "false_alarm_flights": false_flights}


def _corrupt(truth: dict, by_file: dict) -> dict:
    reported, not_reported = 0, []
    for c in truth["corrupt"]:
        row = by_file.get(c["file"])
        ok = row is not None and (row["status"] in ("error", "timeout") if c["expected"] == "error" else
                                  row["status"] == "ok" and bool(row.get("warnings")))
        reported += ok
        if not ok:
            not_reported.append(c["file"])
    return {"planted": len(truth["corrupt"]), "reported": reported, "not_reported": not_reported}


def _fit_accuracy(truth: dict, by_file: dict) -> dict:
    """Fitted offsets and motor field against truth, on flights without interference away from
    anomaly sites (there the local field is in the fitted offsets by design)."""
    anomalous = {s["name"] for s in truth["sites"] if s["anomaly_ned_mG"]}
    ofs_err, motor_err = [], []
    for f in truth["flights"]:
        row = by_file.get(f["file"])
        if not row or row.get("fit_ofs_x_mG") is None or f["interference"] or f["site"] in anomalous:
            continue
        fit = np.array([row[f"fit_ofs_{a}_mG"] for a in "xyz"])
        ofs_err.append(np.linalg.norm(fit - np.array(f["offsets_mG"])))
        if row.get("motor_x_mG_per_A") is not None:
            k = np.array([row[f"motor_{a}_mG_per_A"] for a in "xyz"])
            motor_err.append(np.linalg.norm(k - f["motor_mG_per_A"]) / np.linalg.norm(f["motor_mG_per_A"]))
    pct = lambda v, q: float(np.percentile(v, q)) if v else None  # noqa: E731
    return {"flights": len(ofs_err), "offset_error_median_mG": pct(ofs_err, 50), "offset_error_p90_mG": pct(ofs_err, 90),
            "motor_rel_error_median": pct(motor_err, 50)}


def score_review(truth: dict, rows: list[dict], alerts: list[dict], *, payload_tolerance_flights: int = 2,
                 site_tolerance_km: float = 3.0) -> dict:
    """Every planted finding against what the review found (see the module docstring)."""
    by_file = _by_file(rows)
    rows_by_hash = {r["log_hash"]: r for r in rows}
    return {"drift": _drift(truth, alerts), "payload": _payload(truth, alerts, rows_by_hash, payload_tolerance_flights),
            "anomaly_sites": _sites(truth, alerts, site_tolerance_km), "interference": _interference(truth, by_file),
            "corrupt": _corrupt(truth, by_file), "fit": _fit_accuracy(truth, by_file),
            "logs": {"planted": len(truth["flights"]) + len(truth["corrupt"]), "rows": len(by_file)}}
