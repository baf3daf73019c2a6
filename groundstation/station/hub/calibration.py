"""The hub's calibration part: the guided wizard, its result in use, and writing it to the vehicle.

``CalibrationControl`` owns the ``CalibrationWizard`` and everything around it that touches the
rest of the hub: starting (asks the vehicle for its parameters, the onboard calibration to
un-apply), finishing when the wizard is ready, accepting (the result goes to the estimation
stack and, on a live link, to the vehicle in a background thread confirmed by PARAM_VALUE echo).
``Session`` keeps thin ``wizard_*`` methods that call these.  It takes no lock of its own: the
hub's lock is passed in and held by every public method.
"""
from __future__ import annotations

import threading
from typing import Protocol

from groundstation.samples import Sample
from groundstation.station.hub.sources import ConflictError
from groundstation.station.wizard import CalibrationWizard

__all__ = ["CalibrationControl", "Hub"]


class Hub(Protocol):
    """What the calibration part needs from the session hub."""

    vehicle: object      # hub.vehicle.VehicleLink
    sources: object      # hub.sources.SourceControl
    flight: object       # hub.flight.FlightState

    def event(self, text: str, level: str = "info") -> None: ...
    def changed(self) -> None: ...


class CalibrationControl:
    """Wizard, accepted result and parameter write; every method runs under the hub lock."""

    def __init__(self, lock: threading.RLock, hub: Hub) -> None:
        self._lock = lock
        self._hub = hub
        self.wizard = CalibrationWizard()

    # ------------------------------------------------------------------ samples (lock held)
    def on_sample(self, s: Sample) -> None:
        self.wizard.on_sample(s)

    def after_batch(self) -> None:
        """Finish the wizard once its last step is complete (called after each batch)."""
        w = self.wizard
        if w.ready():
            w.finish(self._hub.vehicle.autopilot, self._hub.vehicle.params)
            r = w.result or {}
            self._hub.event(f"calibration finished: {r.get('status')} {r.get('message') or ''}".strip())

    # ------------------------------------------------------------------ commands
    def start(self) -> None:
        hub = self._hub
        with self._lock:
            if self.wizard.state == "running":
                return  # a second client pressing Start joins the running wizard
            self.wizard.start()
            hub.vehicle.request_params(hub.sources.link)   # the onboard calibration to un-apply
            hub.event("calibration started: turn about X")
            hub.changed()

    def reset(self) -> None:
        with self._lock:
            self.wizard.reset()
            self._hub.event("calibration reset")
            self._hub.changed()

    def finish_now(self) -> dict:
        with self._lock:
            if self.wizard.state != "running":
                raise ConflictError("the calibration wizard is not running")
            return self.wizard.finish(self._hub.vehicle.autopilot, self._hub.vehicle.params)

    def accept(self) -> dict:
        """Use the result for heading; on a live link write it to the vehicle (background)."""
        hub = self._hub
        with self._lock:
            w = self.wizard
            if w.result is None or w.result.get("status") != "ok":
                raise ConflictError("no successful calibration result to accept")
            if w.param_write is not None and w.param_write.get("state") == "writing":
                return w.param_write
            hub.flight.stack.set_calibration(w.result)     # the detector re-learns with it
            w.state = "accepted"
            autopilot = hub.vehicle.autopilot or "ardupilot"
            params = w.result.get(f"{autopilot}_params") or {}
            link = hub.sources.link
            if link is not None and hub.sources.link_state == "up" and params:
                w.param_write = {"state": "writing", "autopilot": autopilot, "total": len(params),
                                 "confirmed": [], "failed": [], "message": "writing parameters"}
                threading.Thread(target=self._write_params, args=(link, dict(params)), daemon=True,
                                 name="param-write").start()
            else:
                w.param_write = {"state": "not_connected", "autopilot": autopilot, "total": len(params),
                                 "confirmed": [], "failed": [],
                                 "message": "accepted for this station; no live link, export the parameters"}
            hub.event("calibration accepted")
            hub.changed()
            return w.param_write

    def _write_params(self, link, params: dict[str, float]) -> None:
        hub = self._hub

        def progress(confirmed: list[str]) -> None:
            self.wizard.param_write = dict(self.wizard.param_write or {}, confirmed=confirmed)

        confirmed, failed = hub.vehicle.write_params(link, params, progress)
        with self._lock:
            pw = self.wizard.param_write or {}
            pw.update(confirmed=confirmed, failed=failed)
            if failed:
                pw.update(state="failed", message=f"{len(failed)} of {len(params)} parameters did not stick "
                                                  f"after 3 tries: {', '.join(failed)}")
                hub.event(pw["message"], "error")
            else:
                pw.update(state="written", message=f"all {len(params)} parameters written and confirmed")
                hub.event(pw["message"])
                # the vehicle now corrects its own field: applying the result here too would
                # correct twice (its onboard calibration was un-applied for the fit)
                hub.flight.stack.set_calibration(None)
            self.wizard.param_write = pw
            hub.changed()

    # ------------------------------------------------------------------ reading (lock held)
    def in_use(self) -> bool:
        return self._hub.flight.stack.calibration is not None

    def snapshot(self) -> dict:
        return self.wizard.snapshot()

    def scene_data(self) -> dict:
        """The wizard's arrays for the 3-D view (copies)."""
        w = self.wizard
        est = w.rls_estimate_cached
        res = w.result if w.result and w.result.get("status") == "ok" else None
        if res:
            fit = {"offsets_mG": res["offsets_mG"], "matrix": res["matrix"], "field_mG": res.get("field_strength_mG")}
        elif est:
            fit = {"offsets_mG": est[0].tolist(), "matrix": est[1].tolist(), "field_mG": est[2]}
        else:
            fit = None
        return {"cloud": w.mag.view()[:, 1:4].copy(), "fit": fit, "calibrating": w.state != "idle"}
