"""Parameters the station can trust: where a PARAM_VALUE may come from, and compass parameters
changed by another ground station.

**Source** (``ParamSourceGuard``, installed on every live link as ``link.param_guard``): a
PARAM_VALUE is taken only from the followed vehicle's system (the link decodes no other) and its
autopilot component (the component of its autopilot HEARTBEAT), and on UDP only from the address
the vehicle's packets come from (the address of its first autopilot heartbeat; another address
takes over only after the known one has been silent for ``ADDRESS_SILENT_S``).  MAVLink 1/2
without signing lets anyone on the network send a PARAM_VALUE in the vehicle's name: one from
another UDP port is refused and counted, and the station says so (event, ``/api/vehicles``,
the wizard's ``param_trust``), never caching it.  Values themselves are judged by
``groundstation.io.params.param_value_problem`` (``VehicleLink.on_param``).

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

import time
from collections import Counter

from groundstation.station.hub.vehicle import same_float32

__all__ = ["on_compass_params_changed", "ParamSourceGuard", "ADDRESS_SILENT_S", "autopilot_change"]

ADDRESS_SILENT_S = 3.0          # the vehicle's known address silent this long: a new one may take over
LEARNING = (1, 2, 3)            # COMPASS_LEARN: internal, EKF, in-flight learning (3 turns itself off when done)
OTHER_GCS_SET_WITHIN_S = 10.0   # a PARAM_SET of this name by another GCS this recently: that station did it
REPORT_EVERY = 100              # after the first refusal of a kind, say so again every this many


def _addr_text(addr) -> str:
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else str(addr)


class ParamSourceGuard:
    """Learns the followed vehicle's autopilot component and UDP address; refuses PARAM_VALUEs from
    elsewhere.  ``check`` is called by the link's reader (one thread) with every packet of the
    followed system; ``snapshot`` by the hub."""

    def __init__(self) -> None:
        self.component: int | None = None
        self.address = None
        self._address_seen_unix = 0.0
        self.refused: Counter = Counter()        # reason kind -> count
        self.last: str | None = None

    def reset(self) -> None:
        """Another vehicle is followed: learn again."""
        self.__init__()

    def _learn(self, msg, addr, unix: float) -> None:
        heartbeat = msg.get_type() == "HEARTBEAT" and getattr(msg, "autopilot", 8) != 8 and getattr(msg, "type", 6) != 6
        if heartbeat and self.component is None:
            self.component = msg.get_srcComponent()
        if addr is None:
            return
        if addr == self.address:
            self._address_seen_unix = unix
        elif heartbeat and (self.address is None or unix - self._address_seen_unix > ADDRESS_SILENT_S):
            self.address, self._address_seen_unix = addr, unix

    def check(self, msg, addr, unix: float) -> tuple[str | None, bool]:
        """(why this packet's PARAM_VALUE is refused or None, whether to say so now)."""
        self._learn(msg, addr, unix)
        if msg.get_type() != "PARAM_VALUE":
            return None, False
        comp = msg.get_srcComponent()
        name = getattr(msg, "param_id", "?")
        name = name.rstrip("\x00") if isinstance(name, str) else str(name)
        if self.component is not None and comp != self.component:
            kind = f"component {comp}"
            why = (f"PARAM_VALUE {name} refused: from component {comp}, not the vehicle's autopilot "
                   f"(component {self.component})")
        elif addr is not None and self.address is not None and addr != self.address:
            kind = f"address {_addr_text(addr)}"
            why = (f"PARAM_VALUE {name} = {float(getattr(msg, 'param_value', float('nan'))):g} refused: it came "
                   f"from {_addr_text(addr)}, not from the vehicle's address {_addr_text(self.address)} (another "
                   "program on the network, or a spoofed packet)")
        else:
            return None, False
        self.refused[kind] += 1
        self.last = why
        n = self.refused[kind]
        return why, n == 1 or n % REPORT_EVERY == 0

    def snapshot(self) -> dict:
        return {"refused": int(sum(self.refused.values())), "by_source": dict(self.refused), "last": self.last,
                "vehicle_address": None if self.address is None else _addr_text(self.address),
                "vehicle_component": self.component}

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


# ------------------------------------------------------------------ the wizard's re-reads
def param_trust(hub) -> dict:
    """What the page shows: PARAM_VALUEs refused for their source (the link's guard) or their
    value (NaN, infinite, out of range: the cache's count and the last reason per name)."""
    guard = getattr(hub.sources.link, "param_guard", None)
    out = guard.snapshot() if guard is not None else {"refused": 0, "by_source": {}, "last": None}
    out["values_refused"] = int(hub.vehicle.refused_count)
    out["values_refused_names"] = dict(list(hub.vehicle.refused_values.items())[-10:])
    return out


def _can_reread(hub) -> bool:
    link = hub.sources.link
    return (hub.sources.kind == "live" and link is not None and hub.sources.link_state == "up"
            and not getattr(link, "passive", False))


def _request_reads(hub, names: list[str]) -> None:
    link = hub.sources.link
    sysid = getattr(link.decoder, "vehicle_sysid", None) or 1
    comp = getattr(getattr(link, "param_guard", None), "component", None) or 1
    for name in names:
        try:
            link.mav.mav.param_request_read_send(sysid, comp, name.encode()[:16], -1)
        except Exception:      # the link went away: the re-read times out and says so
            return


def _start_reread(control, purpose: str) -> bool:
    """Ask the vehicle for every correction parameter again; False when this link cannot."""
    hub, w = control._hub, control.wizard
    if not _can_reread(hub):
        return False
    names = w.param_check.start(purpose, time.monotonic())
    _request_reads(hub, names)
    return True


def wizard_on_param(control, name: str, value: float) -> None:
    """A PARAM_VALUE the cache accepted (hub lock held): a re-read answer, or a change of a
    correction parameter during the dance, which stops the step and re-reads."""
    w, hub = control.wizard, control._hub
    if w.state not in ("running", "result") or w.mode == "fixed_yaw":
        return      # fixed-yaw: the vehicle's own MAV_CMD_FIXED_MAG_CAL_YAW writes its offsets
    change = w.param_check.on_value(name, value)
    if change is None or w.state != "running" or w.param_check.purpose is not None:
        return
    text = (f"The vehicle's compass correction changed during the dance ({change}): another ground station "
            "wrote it, or a spoofed packet. The step is stopped; the parameters are being read again.")
    w.paused = True
    w.banner = {"level": "warning", "text": text}
    hub.event("calibration stopped: compass parameter changed during the dance: " + change, "warning")
    if not _start_reread(control, "dance"):
        _restart_dance(control, [change], "the link cannot re-read")


def _restart_dance(control, diffs: list[str], why: str = "") -> None:
    w, hub = control.wizard, control._hub
    mode = w.mode
    w.start(mode)
    w.param_check.begin(hub.vehicle.params)
    text = ("The vehicle now holds other compass corrections (" + ", ".join(diffs[:4]) +
            (f"; {why}" if why else "") + "): the dance starts again with them. Turn about X.")
    w.banner = {"level": "warning", "text": text}
    hub.event("calibration restarted: the vehicle's compass parameters changed (" + ", ".join(diffs[:4]) + ")",
              "warning")


def wizard_param_tick(control) -> bool:
    """Drive the re-reads (hub lock held, every batch).  True when the wizard may finish now
    (ready and its parameters were re-read, or this link cannot re-read)."""
    w, hub = control.wizard, control._hub
    chk, now = w.param_check, time.monotonic()
    if chk.purpose is not None:
        again = chk.resend(now)
        if again and _can_reread(hub):
            _request_reads(hub, again)
        if chk.done(now):
            _reread_done(control, chk.purpose)
    if chk.purpose is None and w.ready():
        if chk.verified_for_fit or not _start_reread(control, "fit"):
            return True
        w.banner = {"level": "info", "text": "Dance complete: reading the compass parameters from the vehicle "
                    "again before fitting."}
    return False


def _reread_done(control, purpose: str) -> None:
    w, hub = control.wizard, control._hub
    diffs, missing = w.param_check.finish()
    unanswered = f"; {len(missing)} not answered ({', '.join(missing[:3])})" if missing else ""
    if purpose in ("dance", "fit"):
        if diffs:
            _restart_dance(control, diffs)
            return
        if purpose == "dance":
            w.paused = False
            w.banner = {"level": "info", "text": "Re-read: the vehicle still holds the compass corrections the dance "
                        "started with, so the changed value did not come from it and is ignored. The step "
                        "continues." + unanswered}
            hub.event("compass parameters re-read: unchanged on the vehicle; the dance continues" + unanswered)
        else:
            w.param_check.verified_for_fit = True
            w.banner = None
            hub.event("compass parameters re-read before fitting: unchanged" + unanswered)
        return
    # purpose "write": the result goes out only if the vehicle still holds what the fit assumed
    if diffs:
        w.param_check.reference.update({d.split(" ")[0]: w.param_check.answers[d.split(" ")[0]] for d in diffs})
        w.param_write = {"state": "refused", "autopilot": hub.vehicle.autopilot or "ardupilot", "total": 0,
                         "confirmed": [], "failed": [], "failures": [],
                         "message": ("Nothing written: the vehicle's compass parameters changed since the "
                                     "calibration (" + ", ".join(diffs[:4]) + "), by another ground station. "
                                     "Accept again to overwrite them with this result.")}
        hub.event("parameter write refused: the vehicle's compass parameters changed since the fit (" +
                  ", ".join(diffs[:4]) + ")", "warning")
        return
    control.after.write_ours()
    if unanswered and w.param_write is not None:
        w.param_write = dict(w.param_write, message=w.param_write.get("message", "") + " (re-read before writing" +
                             unanswered + ")")


def wizard_accept(control) -> dict:
    """Accept our result: re-read the compass parameters first on a link that can, then write."""
    w = control.wizard
    if not _start_reread(control, "write"):
        return control.after.write_ours()
    autopilot = control._hub.vehicle.autopilot or "ardupilot"
    w.param_write = {"state": "checking", "autopilot": autopilot,
                     "total": len(w.result.get(f"{autopilot}_params") or {}), "confirmed": [], "failed": [],
                     "failures": [], "message": "re-reading the vehicle's compass parameters before writing"}
    control._hub.changed()
    return w.param_write
