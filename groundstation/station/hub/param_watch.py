"""Parameter cache coherence: compass parameters changed by another ground station.

When a PARAM_VALUE nobody here asked for changes a cached COMPASS_* / CAL_MAG* value (another
station wrote it, e.g. loading the .param this station exported), the hub says so in the event
log and re-evaluates the calibration in use:

* the vehicle now holds exactly this station's result (accepted here, or exported as .param and
  loaded by the other station, the passive-mode way): the vehicle corrects its own field, so the
  station does not apply its copy (applying both would correct twice);
* otherwise the live analysis restarts with the calibration in use over the vehicle's new
  parameters (the field rule un-applies the autopilot's current correction), and the
  interference test learns the field again instead of seeing the change as interference.
"""
from __future__ import annotations

from groundstation.station.hub.vehicle import same_float32

__all__ = ["on_compass_params_changed", "autopilot_change"]

LEARNING = (1, 2, 3)            # COMPASS_LEARN: internal, EKF, in-flight learning (3 turns itself off when done)
OTHER_GCS_SET_WITHIN_S = 10.0   # a PARAM_SET of this name by another GCS this recently: that station did it


def autopilot_change(vehicle, link, name: str, now_unix: float) -> str | None:
    """Who changed compass parameter ``name`` (not this station): why the autopilot did it itself,
    or None (another ground station).  A PARAM_SET of it heard from another GCS on the link makes
    it that station's; else COMPASS_DEC with COMPASS_AUTODEC on (ArduPilot's default 1: set from
    its own WMM table once it has a position), and COMPASS_OFS* / COMPASS_LEARN while COMPASS_LEARN
    learns offsets (3, in-flight learning, saves the offsets and sets itself back to 0) are the
    autopilot's own."""
    seen = getattr(link, "param_sets_seen", {}).get(name)
    if seen is not None and now_unix - seen[1] <= OTHER_GCS_SET_WITHIN_S:
        return None
    params, own = vehicle.params, vehicle.changed_by_autopilot
    if name == "COMPASS_DEC" and params.get("COMPASS_AUTODEC", 1.0) != 0:
        return "ArduPilot sets it from its own WMM table (COMPASS_AUTODEC on)"
    learn_old = own["COMPASS_LEARN"][0] if "COMPASS_LEARN" in own else None
    learning = int(params.get("COMPASS_LEARN", 0)) in LEARNING or (learn_old is not None and int(learn_old) in LEARNING)
    if name == "COMPASS_LEARN" and int(vehicle.changed_elsewhere.get(name, (0, 0))[0]) in LEARNING:
        return "ArduPilot's offset learning finished and switched itself off"
    if name.startswith("COMPASS_OFS") and learning:
        return "learnt by ArduPilot's compass offset learning (COMPASS_LEARN)"
    return None


def on_compass_params_changed(hub, names: list[str]) -> None:
    """``names``: compass parameters another station changed in this batch (hub lock held)."""
    vehicle = hub.vehicle
    shown = ", ".join(f"{n} {vehicle.changed_elsewhere[n][0]:g} -> {vehicle.changed_elsewhere[n][1]:g}"
                      for n in names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
    hub.event(f"compass parameters changed by another ground station: {shown}", "warning")
    wizard = hub.calibration.wizard
    result = wizard.result or {}
    ours = (result.get(f"{vehicle.autopilot or 'ardupilot'}_params") or {}) if result.get("status") == "ok" else {}
    if ours and all(n in vehicle.params and same_float32(vehicle.params[n], v) for n, v in ours.items()):
        wizard.state = "accepted"
        hub.calibration._vehicle_in_use("the vehicle now holds this station's calibration (written by another "
                                        "ground station): the station does not apply a copy of its own")
        return
    hub.use_calibration(hub.flight.calibration)
    hub.event("calibration in use re-evaluated with the vehicle's new compass parameters; the interference "
              "test learns the field again")
