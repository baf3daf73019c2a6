"""What the page says: the step instructions, the instruction of each phase, the live warnings."""
from __future__ import annotations

from groundstation.station.wizard.coverage import field_unit_ned, next_pose
from groundstation.station.wizard.quality import field_hypothesis

__all__ = ["STEP_TEXT", "instruction", "live_warnings", "HEADING_CHECK_MAX_ERROR_DEG", "heading_check_verdict"]

# A heading check further off than this fails: a good calibration leaves a few degrees (the deviation
# card of a clean dance stays within ±3°); 5° is where a pilot's heading hold visibly crabs.
HEADING_CHECK_MAX_ERROR_DEG = 5.0

STEP_TEXT = {
    "x": {"short": "X (roll it over)",
          "long": "Hold the vehicle level, then roll it over one full turn (360°) about its X axis, the nose axis."},
    "y": {"short": "Y (pitch it over)",
          "long": "Now pitch it over one full turn about its Y axis, the right-wing axis: nose down, over the back, level."},
    "z": {"short": "Z (yaw it round)", "long": "Now hold it flat and turn it one full turn about its Z axis (yaw)."},
    "tumble": {"short": "tumble", "long": "Now tumble it slowly until the sphere is covered."},
}


def _walk_for_course(hc) -> str:
    """Large-vehicle mode: the walk gives the heading to calibrate with."""
    r = hc.result
    if r is None:
        return (f"Walk the vehicle straight along its nose direction ({hc.snapshot()['distance_m']:.0f} m so far), "
                "then press Stop walk.")
    if r.get("reference_deg") is None:
        return f"The walk gave no course: {r.get('message')}. Walk again."
    return (f"GPS course {r['reference_deg']:.1f}° over {r['distance_m']:.0f} m. Stop with the nose on that course, "
            "then press Calibrate with the GPS course.")


def heading_check_verdict(result: dict | None) -> str | None:
    """"pass" (within HEADING_CHECK_MAX_ERROR_DEG), "fail" (measured, further off), None (no measurement)."""
    if not result or not result.get("ok") or result.get("error_deg") is None:
        return None
    return "pass" if abs(result["error_deg"]) <= HEADING_CHECK_MAX_ERROR_DEG else "fail"


def _after_write(w) -> str | None:
    pw, rb, hc = w.param_write, w.reboot, w.heading_check
    if hc is not None and hc.kind == "walk" and w.mode == "fixed_yaw" and (w.fixed_yaw is None or w.fixed_yaw.state != "done"):
        return _walk_for_course(hc)
    if hc is not None:
        r = hc.result
        if r is None:
            return ("Heading check: hold the vehicle pointed at the bearing…" if hc.kind == "bearing" else
                    f"Heading check: walk the vehicle straight ahead ({hc.snapshot()['distance_m']:.0f} m so far), "
                    "then press Stop walk.")
        verdict = heading_check_verdict(r)
        if verdict == "pass":
            return (f"Done. Heading check: {r['message']}. The new calibration is in use; see the deviation card.")
        if verdict == "fail":
            return (f"Heading check failed: {r['message']}, more than {HEADING_CHECK_MAX_ERROR_DEG:.0f}° off. Do not "
                    "fly on this compass. Check the bearing is true (not magnetic) and the nose is on it, the compass "
                    "orientation matches its mounting, no metal is near; then measure again or redo the dance.")
        return f"Heading check incomplete: {r.get('message')}. Try again."
    if rb is not None:
        if rb["state"] in ("sent", "waiting"):
            return "Rebooting the vehicle: waiting for it to come back…"
        if rb["state"] == "back":
            return ("The vehicle is back and uses the new calibration. Heading check: point it at a known bearing and "
                    "press Measure, or walk it straight for a few metres.")
        if rb["state"] == "refused":
            return f"The vehicle did not reboot ({rb['message']}): power-cycle it, then run the heading check."
    if pw is None:
        return None
    if pw.get("state") == "writing":
        return "Writing the parameters to the vehicle…"
    if pw.get("state") == "written":
        return ("Written and confirmed: the vehicle now uses the new calibration. Reboot it (button below) so every "
                "compass driver reloads it, then check the heading.")
    if pw.get("state") == "failed":
        return (f"The write failed ({len(pw['failed'])} of {pw['total']} parameters did not stick). Check the link and "
                "press Retry the write, or export the parameters and load them with another ground station.")
    if pw.get("state") == "not_connected":
        return "Accepted for this station only (no live link): export the parameters and load them into the vehicle."
    return None


def _mode_text(w) -> str | None:
    if w.mode == "fixed_yaw":
        fy = w.fixed_yaw
        if fy is None:
            return ("Large vehicle: hold it still, enter its true heading (or walk it straight to take the GPS course) "
                    "and press Calibrate with this heading.")
        return fy.message[0].upper() + fy.message[1:] + "."
    if w.mode == "onboard" and w.onboard is not None and w.state == "running":
        ob = w.onboard
        if ob.state in ("starting", "refused"):
            return ob.message[0].upper() + ob.message[1:] + "."
        if ob.state == "running" and not w.paused:
            return _onboard_progress(w)
    return None


def _onboard_progress(w) -> str:
    """The vehicle's calibrator decides when it has enough: the instruction follows its progress
    (MAG_CAL_PROGRESS completion and sections), not our X/Y/Z steps."""
    ob = w.onboard
    done = {k: c.get("completion_pct", 0) for k, c in sorted(ob.compasses.items())}
    if not done:
        return ("The vehicle's calibrator is running: turn the vehicle slowly, about every axis in turn, "
                "until it reports its progress.")
    least = min(done.values())
    each = ", ".join(f"compass {k + 1} {v} %" for k, v in done.items())
    if least >= 100 or all(c.get("report") is not None for c in ob.compasses.values()):
        return f"The vehicle's calibrator has what it needs ({each}): hold the vehicle still while it fits."
    pose = next_pose(w.cells, field_unit_ned(w.field_ned_mG))
    how = (f"{pose['text'][0].upper()}{pose['text'][1:]}" if pose is not None and least >= 25 else
           "Turn the vehicle slowly through every orientation: roll it over, pitch it over, yaw it round")
    return f"The vehicle's calibrator: {least} % ({each}). {how}, until every compass reaches 100 %."


def instruction(w, pose: dict | None = None) -> str:
    after = _after_write(w)
    if after:
        return after
    mode = _mode_text(w)
    if mode:
        return mode
    if w.state == "idle":
        return "Choose the mode, then press Start and follow the steps."
    if w.state == "running":
        if w.waiting_for is not None:
            return f"Waiting for the vehicle on {w.waiting_for}: the steps start when its first packet arrives."
        if w.paused:
            return "Link lost: calibration paused. Keep the vehicle still until the link returns."
        step = w.step
        text = STEP_TEXT[step]["long"]
        if step == "tumble" and pose is not None:
            text = f"Cover the rest of the sphere: {pose['text']}."
        if w.mode == "onboard":
            text = "The vehicle's calibrator is running. " + text
        return text
    r = w.result or {}
    if w.mode == "onboard" and w.onboard is not None and w.onboard.state == "reported":
        return ("Both fits are done: compare the vehicle's with ours, then accept the vehicle's (it saves its own) "
                "or write ours, or cancel.")
    if r.get("status") == "ok":
        return "Check the result, then Accept (writes the vehicle), export the parameters, or redo."
    return ("The calibration did not pass: read the reason under each compass, leave a failing compass out or "
            "redo the dance.")


def live_warnings(w) -> list[str]:
    out = []
    if w.state != "running" or w.paused:
        return out
    s = w.settings
    if w._last_imu_t < w._fast_until:
        out.append(f"Turning too fast ({w._last_gyro_deg_s:.0f}°/s): keep under {s.too_fast_deg_s:.0f}°/s so the "
                   "samples stay dense.")
    for k, t in sorted(w.tracks.items()):
        if t.disturbed(w._last_t):
            out.append(f"Magnetic disturbance on {t.name}: the field jumped off its fitted sphere; move away from "
                       "metal, cars and power cables.")
    exp = w.expected_field_mG
    if exp:
        for k, t in sorted(w.tracks.items()):
            if t.trusted() and abs(t.live.field_mG - exp) > s.wmm_mismatch_fraction * exp:
                out.append(f"{t.name.capitalize()}: " + field_hypothesis(t.live.field_mG, exp))
    return out
