"""From the collected dance to results: per-compass fits, their consistency, the deviation card, and
the combined result the station accepts and writes (the included compasses only)."""
from __future__ import annotations

import numpy as np

from groundstation.io.params import unapply_ardupilot, unapply_px4
from groundstation.station.wizard.aftercheck import deviation_card
from groundstation.station.wizard.consistency import check_consistency
from groundstation.station.wizard.fit import DanceData, calibrated_in_new_frame, fit_compass
from groundstation.station.wizard.quality import judge

__all__ = ["build_results", "merged_result", "unapply_function", "consistency_of"]

MIN_SAMPLES = 50


def unapply_function(autopilot: str, params: dict[str, float], k: int):
    prefix = f"CAL_MAG{k}_" if autopilot == "px4" else f"COMPASS_OFS{'' if k == 0 else k + 1}_"
    if not any(n.startswith(prefix) for n in params):
        return lambda m: np.asarray(m, float)
    if autopilot == "px4":
        return lambda m: unapply_px4(m, params, k)
    return lambda m: unapply_ardupilot(m, params, k)


def build_results(w, autopilot: str, params: dict[str, float]) -> tuple[dict[int, dict], dict | None, dict | None]:
    """Fit every compass with enough samples; the consistency of the included ones; the card."""
    data = DanceData(w.att.view().copy(), w.gps.view().copy(), w.start_unix_s, w.field_ned_mG)
    results: dict[int, dict] = {}
    for k, track in sorted(w.tracks.items()):
        mag = track.mag.view().copy()
        if len(mag) < MIN_SAMPLES:
            track.result = results[k] = {"status": "no_data", "compass": k, "samples": int(len(mag)), "pass": False,
                                         "reasons": [f"only {len(mag)} samples: is this compass streaming?"],
                                         "cautions": [], "ardupilot_params": {}, "px4_params": {}}
            continue
        track.result = results[k] = fit_compass(k, mag, autopilot, params, data, w.settings, track.disturbances)
    consistency = consistency_of(w, autopilot, params, results)
    deviation = _deviation(w, autopilot, params, results)
    return results, consistency, deviation


def consistency_of(w, autopilot: str, params: dict[str, float], results: dict[int, dict]) -> dict | None:
    """Consistency of the included compasses that fitted."""
    entries = [(k, r, w.tracks[k].mag.view(), unapply_function(autopilot, params, k))
               for k, r in sorted(results.items()) if w.tracks[k].included and r.get("status") == "ok"]
    return check_consistency(entries, w.settings, w.expected_field_mG, w.att.view())


def _deviation(w, autopilot, params, results) -> dict | None:
    k = min((k for k, r in results.items() if r.get("status") == "ok"), default=None)
    if k is None:
        return None
    mag = w.tracks[k].mag.view()
    after = calibrated_in_new_frame(results[k], unapply_function(autopilot, params, k)(mag[:, 1:4]), as_vehicle=True)
    card = deviation_card(mag[:, 0], mag[:, 1:4], after, w.att.view(), w.imu.view(), w.declination_deg or 0.0)
    if card is not None:
        card["compass"] = k
    return card


def merged_result(w, autopilot: str) -> dict | None:
    """The first included compass's result, with the parameters of every included compass and a
    status that is "ok" only when every included compass passed."""
    if not w.results:
        return None
    for k, r in w.results.items():
        if r.get("status") == "ok":
            r.update(judge(r, k, r.get("orientation"), r.get("disturbances", 0), w.settings, w.field_ned_mG))
    included = [k for k in sorted(w.results) if w.tracks[k].included]
    if not included:
        return {"status": "failed", "message": "every compass is left out", "autopilot": autopilot,
                "ardupilot_params": {}, "px4_params": {}, "compasses_included": []}
    first = w.results[included[0]]
    out = {key: v for key, v in first.items() if key not in ("ardupilot_params", "px4_params")}
    out["ardupilot_params"], out["px4_params"] = {}, {}
    failing = []
    for k in included:
        r = w.results[k]
        if r.get("status") != "ok" or not r.get("pass"):
            failing.append(f"compass {k + 1}: " + " ".join(r.get("reasons") or [r.get("message") or "failed"]))
        out["ardupilot_params"].update(r.get("ardupilot_params") or {})
        out["px4_params"].update(r.get("px4_params") or {})
    if w.consistency is not None and w.consistency["status"] != "ok":
        out["consistency_warning"] = w.consistency["text"]
    out["compasses_included"] = [k for k in included]
    out["autopilot"] = autopilot
    if failing:
        out.update(status="failed", message="; ".join(failing))
    return out
