"""The hub's calibration part: the wizard, its result in use, and what it says to the vehicle.

``CalibrationControl`` owns the ``CalibrationWizard`` and everything around it that touches the
rest of the hub: starting (asks for the vehicle's parameters, the onboard calibration to
un-apply; in "onboard" mode MAV_CMD_DO_START_MAG_CAL), pausing on link drops, finishing,
leaving compasses out, accepting (the result goes to the estimation stack and, on a live link, to
the vehicle by confirmed PARAM_SET, or MAV_CMD_DO_ACCEPT_MAG_CAL for the vehicle's own fit),
large-vehicle MAV_CMD_FIXED_MAG_CAL_YAW, the reboot (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN) and the
heading check.  ``Session`` keeps thin ``wizard_*`` methods that call these.  It takes no lock of
its own: the hub's lock is passed in and held by every public method.
"""
from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import replace
from typing import Protocol

import numpy as np

from groundstation.io.decode import preferred_source
from groundstation.io.mavlink import mavlink2
from groundstation.samples import GpsSample, MagSample, Sample
from groundstation.station.hub.after_write import AfterWrite
from groundstation.station.hub.param_watch import param_trust, wizard_accept, wizard_on_param, wizard_param_tick
from groundstation.station.hub.sources import ConflictError, SessionError
from groundstation.station.hub.vehicle import RESULT_TEXT
from groundstation.station.wizard import FITNESS_LEVELS, MODES, CalibrationWizard
from groundstation.station.wizard.compass import compass_index
from groundstation.station.wizard.fit import raw_in_result_frame
from groundstation.station.wizard.results import consistency_of, unapply_function
from groundstation.station.wizard.onboard import OnboardCalibration
from groundstation.station.wizard.texts import heading_check_verdict

__all__ = ["CalibrationControl", "Hub"]

_M = mavlink2
DANCE_CLOUD_S = 90.0            # the station's view of a replayed dance: the raw field of this long
DANCE_CLOUD_POINTS = 6000


class Hub(Protocol):
    """What the calibration part needs from the session hub."""

    vehicle: object      # hub.vehicle.VehicleLink
    sources: object      # hub.sources.SourceControl
    flight: object       # hub.flight.FlightState

    def event(self, text: str, level: str = "info") -> None: ...
    def use_calibration(self, calibration: dict | None) -> None: ...
    def changed(self) -> None: ...


class CalibrationControl:
    """Wizard, accepted result, vehicle commands; every public method runs under the hub lock."""

    def __init__(self, lock: threading.RLock, hub: Hub) -> None:
        self._lock = lock
        self._hub = hub
        self.wizard = CalibrationWizard()
        self.after = AfterWrite(self)
        # the first compass's raw field as received while the wizard is idle: t_s, x, y, z (mG)
        self._recent_mag: deque = deque(maxlen=DANCE_CLOUD_POINTS)
        self._recent_instance: int | None = None

    # ------------------------------------------------------------------ helpers
    def live_link(self, why: str):
        """The live link, or ConflictError saying what needs one."""
        src = self._hub.sources
        if src.link is None or src.link_state != "up":
            raise ConflictError(f"{why} needs a live link to the vehicle")
        return src.link

    def send(self, why: str, command: int, *params: float) -> None:
        link = self.live_link(why)
        if not self._hub.vehicle.send_command(link, command, *params):
            raise ConflictError(f"could not send the command for {why}")

    # ------------------------------------------------------------------ samples (lock held)
    def on_sample(self, s: Sample) -> None:
        """Every sensor sample, all compass instances (before the flight's primary filter)."""
        w = self.wizard
        w.on_sample(s)
        if isinstance(s, MagSample) and compass_index(s.instance) == 0:
            self.after.on_compass0(s)
            self._keep_recent(s)
        elif isinstance(s, GpsSample):
            self.after.on_gps(s)

    def on_param(self, name: str, value: float) -> None:
        """A PARAM_VALUE the parameter cache accepted: the wizard's re-reads and change checks."""
        wizard_on_param(self, name, value)

    def _keep_recent(self, s: MagSample) -> None:
        if self.wizard.state != "idle":
            return
        keep = preferred_source(self._recent_instance, s.instance)   # RAW_IMU and SCALED_IMU both carry compass 1
        if keep != self._recent_instance:
            self._recent_instance = keep
            self._recent_mag.clear()
        if s.instance != self._recent_instance or not all(math.isfinite(v) for v in s.mag_body_mG):
            return
        recent = self._recent_mag
        if recent and s.t_s < recent[-1][0]:         # a seek or a loop: the field of another moment
            recent.clear()
        recent.append((s.t_s, *s.mag_body_mG))

    def on_link(self, up: bool, t_s: float) -> None:
        text = self.wizard.on_link(up, t_s)
        if text:
            self._hub.event(text, "info" if up else "warning")
        self.after.on_link(up)

    def after_batch(self) -> None:
        """Vehicle messages (acks, MAG_CAL_*), then finish the wizard once it is complete."""
        hub, w = self._hub, self.wizard
        for msg in hub.vehicle.vehicle_messages(hub.sources.link):
            self._on_vehicle_message(msg)
        self.after.tick()
        if wizard_param_tick(self):      # ready, and the compass parameters re-read (param_watch)
            w.finish(hub.vehicle.autopilot, {**hub.vehicle.params, **w.param_check.reference})
            r = w.result or {}
            hub.event(f"calibration finished: {r.get('status')} {r.get('message') or ''}".strip()[:300])

    def _on_vehicle_message(self, msg) -> None:
        w, kind = self.wizard, msg.get_type()
        if kind == "MAG_CAL_PROGRESS" and w.onboard is not None:
            w.onboard.on_progress(msg)
        elif kind == "MAG_CAL_REPORT" and w.onboard is not None:
            before = w.onboard.state
            w.onboard.on_report(msg)
            if w.onboard.state != before:
                self._hub.event("vehicle calibrator: " + w.onboard.message)
        elif kind == "COMMAND_ACK":
            self._on_ack(int(msg.command), int(msg.result))

    def _on_ack(self, command: int, result: int) -> None:
        w, ok, text = self.wizard, result == _M.MAV_RESULT_ACCEPTED, RESULT_TEXT.get(result, str(result))
        if command == _M.MAV_CMD_DO_START_MAG_CAL and w.onboard is not None:
            w.onboard.on_ack(ok, text)
            if not ok:
                self._hub.event(w.onboard.message, "warning")
        elif command == _M.MAV_CMD_DO_ACCEPT_MAG_CAL:
            self.after.onboard_accepted(ok, text)
        elif command == _M.MAV_CMD_FIXED_MAG_CAL_YAW and w.fixed_yaw is not None:
            w.fixed_yaw.on_ack(ok, text, w._last_t)
            if ok:
                self._vehicle_in_use("the vehicle calibrated its compasses at the entered heading")
            self._hub.event(w.fixed_yaw.message, "info" if ok else "warning")
        elif command == _M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            self.after.reboot_ack(ok, text)

    def _vehicle_in_use(self, why: str) -> None:
        """The vehicle corrects its own field now: the station stops applying its copy."""
        self.wizard.in_use = "vehicle"
        self._hub.use_calibration(None)
        self._hub.event(why)

    # ------------------------------------------------------------------ the dance
    def start(self, mode: str = "guided", connecting: str | None = None) -> None:
        """Start the wizard.  ``connecting``: the name of a link being connected, whose vehicle
        the operator means: nothing is sent or read from the current source's vehicle; the wizard
        shows it is waiting and starts on the new vehicle when the hub switches to it."""
        hub = self._hub
        if mode not in MODES:
            raise SessionError(f"mode must be one of {', '.join(MODES)}")
        with self._lock:
            w = self.wizard
            if w.state == "running":
                return  # a second client pressing Start joins the running wizard
            if connecting is not None:
                w.start(mode)
                w.waiting_for = connecting
                hub.event(f"calibration starts when {connecting} hears its vehicle")
                hub.changed()
                return
            if mode == "onboard":
                if hub.vehicle.autopilot == "px4":
                    raise ConflictError("the onboard calibrator over MAVLink (MAV_CMD_DO_START_MAG_CAL) is "
                                        "ArduPilot's; use the guided mode for PX4")
                self.send("the onboard calibration", _M.MAV_CMD_DO_START_MAG_CAL, 0, 0, 0, 0, 0)
            w.start(mode)
            w.param_check.begin(hub.vehicle.params)        # the corrections the samples come with
            if mode == "onboard":
                w.onboard = OnboardCalibration()
            hub.vehicle.request_params(hub.sources.link)   # the onboard calibration to un-apply
            hub.event({"guided": "calibration started: turn about X",
                       "onboard": "onboard calibration started (MAV_CMD_DO_START_MAG_CAL): turn about X",
                       "fixed_yaw": "large-vehicle calibration: enter the heading"}[mode])
            hub.changed()

    def start_on_new_link(self, mode: str, url: str) -> None:
        """A calibration started while ``url`` was connecting, on its vehicle now (lock held): its
        parameters, its link for the commands; a refusal is told in the events."""
        try:
            self.start(mode)
        except SessionError as err:
            self._hub.event(f"calibration not started on {url}: {err}", level="warning")

    def link_cancelled(self) -> None:
        """The connecting link was given up: a calibration waiting for its vehicle is reset."""
        url = self.wizard.waiting_for
        if url is not None:
            self._hub.event(f"the calibration waiting for the vehicle on {url} is cancelled: that link was given up")
            self.reset()

    def new_source(self) -> None:
        """A new source: the wizard starts over, silently (lock held; nothing is sent, the old
        link is gone)."""
        self.wizard.reset()
        self._recent_mag.clear()
        self._recent_instance = None

    def unwritten_result(self) -> bool:
        """A good result not on a vehicle yet (not accepted, or its write failed, had no link or is
        still being tried on a link that is going away)."""
        w = self.wizard
        ok = w.result is not None and w.result.get("status") == "ok"
        return ok and w.state in ("result", "accepted") and (w.param_write or {}).get("state") != "written"

    def reset(self) -> None:
        with self._lock:
            w = self.wizard
            if w.onboard is not None and w.onboard.state in ("starting", "running", "reported"):
                self._cancel_onboard()
            w.reset()
            self._hub.event("calibration reset")
            self._hub.changed()

    def finish_now(self) -> dict:
        with self._lock:
            w = self.wizard
            if w.state != "running" or w.mode == "fixed_yaw":
                raise ConflictError("the calibration wizard is not running")
            result = w.finish(self._hub.vehicle.autopilot, self._hub.vehicle.params)
            self._hub.changed()
            return result

    def set_included(self, compass: int, included: bool) -> dict:
        with self._lock:
            w = self.wizard
            track = w.tracks.get(int(compass))
            if track is None:
                raise SessionError(f"no compass {compass + 1} in this calibration")
            track.included = bool(included)
            if w.results:
                w.consistency = consistency_of(w, self._hub.vehicle.autopilot or "ardupilot", self._hub.vehicle.params,
                                               w.results)
                w.rebuild_result(self._hub.vehicle.autopilot)
            self._hub.event(f"{track.name} {'included' if included else 'left out'}")
            self._hub.changed()
            return w.snapshot()

    def set_fitness(self, level: str) -> None:
        if level not in FITNESS_LEVELS:
            raise SessionError(f"fitness level must be one of {', '.join(FITNESS_LEVELS)}")
        with self._lock:
            w = self.wizard
            w.settings = replace(w.settings, fitness_level=level)
            for t in w.tracks.values():
                t.settings = w.settings
            if w.results:
                w.rebuild_result(self._hub.vehicle.autopilot)
            self._hub.changed()

    # ------------------------------------------------------------------ accepting
    def accept(self, which: str = "ours") -> dict:
        """Use the result for heading; on a live link write it to the vehicle (background).
        In onboard mode ``which="vehicle"`` accepts the vehicle's own fit instead."""
        with self._lock:
            w = self.wizard
            if which == "vehicle":
                return self.after.accept_onboard()
            if w.result is None or w.result.get("status") != "ok":
                raise ConflictError("no successful calibration result to accept")
            if w.param_write is not None and w.param_write.get("state") in ("writing", "checking"):
                return w.param_write
            if w.onboard is not None and w.onboard.state in ("running", "reported"):
                self._cancel_onboard()
            return wizard_accept(self)           # re-read the compass parameters, then write

    def cancel_onboard(self) -> None:
        with self._lock:
            if self.wizard.onboard is None:
                raise ConflictError("the vehicle's calibrator is not running")
            self._cancel_onboard()
            self._hub.changed()

    def _cancel_onboard(self) -> None:
        w = self.wizard
        try:
            self.send("cancelling the vehicle's calibrator", _M.MAV_CMD_DO_CANCEL_MAG_CAL, 0)
        except ConflictError:
            pass
        w.onboard.state, w.onboard.message = "cancelled", "the vehicle's calibrator was cancelled"
        self._hub.event("vehicle calibrator cancelled (MAV_CMD_DO_CANCEL_MAG_CAL)")

    # ------------------------------------------------------------------ large vehicle
    def fixed_yaw(self, yaw_deg: float | None, source: str = "entered") -> dict:
        """MAV_CMD_FIXED_MAG_CAL_YAW with the crew's heading, or the course of the last walk."""
        from groundstation.station.wizard.largevehicle import FixedYawCalibration

        with self._lock:
            w = self.wizard
            if w.mode != "fixed_yaw" or w.state != "running":
                raise ConflictError("start the large-vehicle mode first")
            if source == "gps":
                walk = w.heading_check
                if walk is None or walk.result is None or walk.result.get("reference_deg") is None:
                    raise ConflictError("walk the vehicle straight first (Start walk, Stop walk)")
                yaw_deg = walk.result["reference_deg"]
            if yaw_deg is None or not math.isfinite(float(yaw_deg)):
                raise SessionError("give the vehicle's true heading in degrees")
            self.send("the large-vehicle calibration", _M.MAV_CMD_FIXED_MAG_CAL_YAW, float(yaw_deg) % 360.0, 0, 0, 0)
            fy = FixedYawCalibration(float(yaw_deg), source, w.field_ned_mG, w.declination_deg)
            roll, pitch, _ = w.latest_att
            fy.compute_ours({k: np.mean(list(v), axis=0) for k, v in w.latest_mag.items() if v},
                            self._hub.vehicle.params, roll, pitch)
            w.fixed_yaw = fy
            w.heading_check = None
            self._hub.event(fy.message)
            self._hub.changed()
            return fy.snapshot()

    # ------------------------------------------------------------------ after writing
    def reboot(self, confirm: bool) -> dict:
        with self._lock:
            return self.after.reboot(confirm)

    def heading_check(self, kind: str, bearing_deg: float | None = None) -> dict:
        with self._lock:
            return self.after.heading_check(kind, bearing_deg)

    def stop_walk(self) -> dict:
        with self._lock:
            return self.after.stop_walk()

    # ------------------------------------------------------------------ reading (lock held)
    def in_use(self) -> bool:
        return self._hub.flight.calibration is not None or self.wizard.in_use == "vehicle"

    def snapshot(self) -> dict:
        if self.wizard.fixed_yaw is not None:
            self.wizard.fixed_yaw.on_params(self._hub.vehicle.params)
        snap = self.wizard.snapshot()
        snap["param_trust"] = trust = param_trust(self._hub)
        if trust["refused"] or trust["values_refused"]:
            snap["warnings"] = snap["warnings"] + [
                f"{trust['refused'] + trust['values_refused']} parameter value(s) refused (not from the vehicle, or "
                "not a possible value): " + (trust["last"] or next(iter(trust["values_refused_names"].values()), ""))]
        hc = snap.get("heading_check")
        if hc is not None and hc.get("result") is not None:
            hc["result"] = dict(hc["result"], verdict=heading_check_verdict(hc["result"]))
        ob = snap.get("onboard")
        if ob is not None:
            from groundstation.station.wizard.onboard import compare
            for c in ob["compasses"]:
                c["compare"] = compare((c.get("report") or None), self.wizard.results.get(c["index"]))
        return snap

    def _dance_cloud(self) -> dict:
        """A recorded dance while the wizard is idle: the first compass's raw field of the last
        DANCE_CLOUD_S, with the fit of the log's own calibration when the log's field had no
        offsets applied (else the view centres the cloud itself)."""
        pts = np.asarray(self._recent_mag, float).reshape(-1, 4)
        pts = pts[pts[:, 0] >= pts[-1, 0] - DANCE_CLOUD_S, 1:4] if len(pts) else np.empty((0, 3))
        fit = None
        cal = getattr(self._hub, "log_calibration", None) or {}
        in_force = ((cal.get("corrections") or {}).get("offsets_in_force_end_mG")) or [None]
        if cal.get("status") == "ok" and all(v is not None and abs(v) < 1e-6 for v in in_force):
            fit = {"offsets_mG": cal["offsets_mG"], "matrix": cal["matrix"], "field_mG": cal.get("field_strength_mG")}
        return {"cloud": pts, "fit": fit, "calibrating": True, "coverage": None, "dance_replay": True}

    def scene_data(self, dancing: bool = False) -> dict:
        """The wizard's arrays for the 3-D view (copies): the first compass's cloud and fit, and
        the directions covered.  ``dancing``: the vehicle shown is being turned over (a replayed
        calibration dance); with the wizard idle the view shows that dance's field instead of
        the route."""
        w = self.wizard
        if w.state == "idle" and dancing and len(self._recent_mag) >= 50:
            return self._dance_cloud()
        track = w.tracks.get(0)
        res = w.results.get(0) if w.results else None
        fit = None
        cloud = track.mag.view()[:, 1:4].copy() if track is not None else np.empty((0, 3))
        if res and res.get("status") == "ok":
            fit = {"offsets_mG": res["offsets_mG"], "matrix": res["matrix"], "field_mG": res.get("field_strength_mG")}
            cloud = raw_in_result_frame(res, cloud, unapply_function(self._hub.vehicle.autopilot or "ardupilot",
                                                                     self._hub.vehicle.params, 0))
        elif track is not None and track.live is not None:
            fit = {"offsets_mG": track.live.offsets_mG.tolist(), "matrix": track.live.matrix.tolist(),
                   "field_mG": track.live.field_mG}
        return {"cloud": cloud, "fit": fit, "calibrating": w.state != "idle",
                "coverage": w.cells.copy() if w.state != "idle" and w.mode != "fixed_yaw" else None}
