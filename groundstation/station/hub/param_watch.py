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

__all__ = ["on_compass_params_changed"]


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
