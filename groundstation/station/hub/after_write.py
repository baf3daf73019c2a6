"""After the calibration: writing it (confirmed), the vehicle's own accept, the reboot, the heading check.

``AfterWrite`` is the calibration part's helper for everything that follows a result: the
background parameter write (PARAM_SET confirmed by PARAM_VALUE echo, failures named with what the
vehicle answered), MAV_CMD_DO_ACCEPT_MAG_CAL, MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN after the
operator's confirmation (then waiting for the link to drop and return), and the heading check
(held at a bearing, or a straight walk whose GPS course is the reference).  A confirmed write is
added to the airframe's compass history (``jobs.compass_history.record_calibrations``, the fleet
database in the recordings folder or $MAGSTATION_FLEET_DB).  Called by
``calibration.CalibrationControl`` with the hub lock held, except the write thread, which takes it.
"""
from __future__ import annotations

import math
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np

from groundstation.io import fleet_db
from groundstation.io.mavlink import mavlink2
from groundstation.jobs.airframes import identity_key
from groundstation.jobs.compass_history import history_airframe, record_calibrations
from groundstation.samples import GpsSample, MagSample
from groundstation.station.hub.sources import ConflictError, SessionError
from groundstation.station.wizard.aftercheck import HeadingCheck, compass_heading_deg

__all__ = ["AfterWrite", "REBOOT_ASSUME_BACK_S"]

_M = mavlink2
REBOOT_ASSUME_BACK_S = 10.0     # link never dropped this long after the ACK: the vehicle rebooted fast
BEARING_WINDOW_S = 3.0


class AfterWrite:
    def __init__(self, control) -> None:
        self._c = control

    @property
    def _w(self):
        return self._c.wizard

    @property
    def _hub(self):
        return self._c._hub

    # ------------------------------------------------------------------ writing our result
    def write_ours(self) -> dict:
        w, hub = self._w, self._hub
        hub.use_calibration(w.result)      # the detector re-learns with it
        w.state, w.in_use = "accepted", "station"
        hub.in_use.accepted(w.result)       # the calibration in use for this airframe from now on
        autopilot = hub.vehicle.autopilot or "ardupilot"
        params = w.result.get(f"{autopilot}_params") or {}
        link = hub.sources.link
        base = {"autopilot": autopilot, "total": len(params), "confirmed": [], "failed": [], "failures": []}
        if link is not None and hub.sources.link_state == "up" and params:
            w.param_write = {"state": "writing", "message": f"writing {len(params)} parameters", **base}
            threading.Thread(target=self._write, args=(link, dict(params)), daemon=True, name="param-write").start()
        else:
            w.param_write = {"state": "not_connected",
                             "message": "accepted for this station; no live link, export the parameters", **base}
        hub.event("calibration accepted")
        hub.changed()
        return w.param_write

    def _write(self, link, params: dict[str, float]) -> None:
        hub, w = self._hub, self._w

        def progress(confirmed: list[str]) -> None:
            if w.param_write is not None:         # (a reset meanwhile leaves nothing to update)
                w.param_write = dict(w.param_write, confirmed=confirmed)

        confirmed, failed, echoed = hub.vehicle.write_params(link, params, progress)
        with self._c._lock:
            pw = w.param_write or {"autopilot": hub.vehicle.autopilot or "ardupilot", "total": len(params)}
            failures = [{"name": n, "sent": params[n], "echoed": echoed.get(n),
                         "text": (f"{n}: the vehicle kept {echoed[n]:.6g} instead of {params[n]:.6g}" if n in echoed
                                  else f"{n}: no answer from the vehicle")} for n in failed]
            pw.update(confirmed=confirmed, failed=failed, failures=failures)
            if failed:
                silent = sum(1 for f in failures if f["echoed"] is None)
                why = ("the vehicle did not answer" if silent == len(failed) else
                       "the vehicle answered with other values" if silent == 0 else "no answer or other values")
                names = ", ".join(failed[:3]) + (f" and {len(failed) - 3} more" if len(failed) > 3 else "")
                pw.update(state="failed", message=f"{len(failed)} of {len(params)} parameters did not stick after "
                                                  f"3 tries: {why} ({names})")
                hub.event(pw["message"], "error")
            else:
                pw.update(state="written", message=f"all {len(params)} parameters written and confirmed by the vehicle")
                hub.event(pw["message"])
                # the vehicle now corrects its own field: applying the result here too would
                # correct twice (its onboard calibration was un-applied for the fit)
                w.in_use = "vehicle"
                hub.use_calibration(None)
            w.param_write = pw
            hub.changed()
            recorded = self._history_entry(self._our_results()) if not failed else None
        if recorded is not None:
            self._record_in_history(*recorded)

    # ------------------------------------------------------------------ the fleet's compass history
    def _our_results(self) -> dict[int, dict]:
        w = self._w
        included = (w.result or {}).get("compasses_included") or []
        return {k: dict(w.results[k]) for k in included if k in w.results}

    def _onboard_results(self) -> dict[int, dict]:
        """The vehicle's own calibration as the history keeps it (MAG_CAL_REPORT: COMPASS_OFS = −b,
        DIA/ODI the symmetric matrix, fitness the RMS residual)."""
        out = {}
        for k, c in (self._w.onboard.compasses if self._w.onboard is not None else {}).items():
            rep = c.get("report") or {}
            if not rep.get("success") or None in rep.get("ofs_mG", [None]):
                continue
            (dx, dy, dz), (ox, oy, oz) = rep["diag"], rep["offdiag"]
            out[int(k)] = {"offsets_mG": [-v for v in rep["ofs_mG"]], "matrix": [[dx, ox, oy], [ox, dy, oz], [oy, oz, dz]],
                           "residual_rms_mG": rep["fitness_mG"], "message": "the vehicle's onboard calibration",
                           "orientation": {"old": rep["old_orientation"], "new": rep["new_orientation"]}}
        return out

    def _history_entry(self, results: dict[int, dict]) -> tuple[Path, dict, dict[int, dict], dict]:
        """What the history keeps of a confirmed write (taken with the lock held): the database
        (``fleet_db.default_db_path`` under the recordings folder), the vehicle's parameters, the
        compasses' results with the WMM field, and where the vehicle was."""
        w, hub = self._w, self._hub
        if w.field_ned_mG is not None:
            n, e, d = (float(v) for v in w.field_ned_mG)
            wmm = {"expected_field_mG": math.sqrt(n * n + e * e + d * d),
                   "expected_inclination_deg": math.degrees(math.atan2(d, math.hypot(n, e))),
                   "expected_declination_deg": w.declination_deg}
            results = {k: {**r, **wmm} for k, r in results.items()}
        gps = w.gps.view()
        fixes = gps[gps[:, 7] >= 3] if len(gps) else gps
        where = {"lat_deg": float(fixes[-1, 1]), "lon_deg": float(fixes[-1, 2])} if len(fixes) else {}
        path = fleet_db.default_db_path(hub.sources.recordings_dir)
        return path, dict(hub.vehicle.params), results, where

    def _record_in_history(self, path: Path, params: dict, results: dict[int, dict], where: dict) -> None:
        """Append the written calibration to the airframe's compass history (outside the hub lock:
        the drift alerts are recomputed); a failure is an event, never an error of the write."""
        try:
            airframe = history_airframe(path, identity_key(params)["identity"])
            out = record_calibrations(path, airframe, results, **where)
        except (OSError, sqlite3.Error, ValueError) as err:
            text, level = f"calibration not added to the fleet history ({path.name}): {err}", "warning"
        else:
            text, level = f"calibration added to the fleet history of {airframe} ({path.name})", "info"
            text += "".join(f"; {a['message']}" for a in out["alerts"] if a["kind"] == "calibration_change")
        with self._c._lock:
            self._hub.event(text, level)
            self._hub.changed()

    # ------------------------------------------------------------------ the vehicle's own fit
    def accept_onboard(self) -> dict:
        w = self._w
        ob = w.onboard
        if ob is None or ob.state != "reported":
            raise ConflictError("the vehicle's calibrator has no report to accept")
        if not all(c["report"]["success"] for c in ob.compasses.values()):
            raise ConflictError("the vehicle's calibration failed for a compass: cancel it, or accept ours")
        self._c.send("accepting the vehicle's calibration", _M.MAV_CMD_DO_ACCEPT_MAG_CAL, 0)
        w.state = "accepted"
        w.param_write = {"state": "writing", "autopilot": "ardupilot", "total": len(ob.compasses), "confirmed": [],
                         "failed": [], "failures": [],
                         "message": "asking the vehicle to save its calibration (MAV_CMD_DO_ACCEPT_MAG_CAL)"}
        self._hub.changed()
        return w.param_write

    def onboard_accepted(self, ok: bool, text: str) -> None:
        w, hub = self._w, self._hub
        if w.param_write is None or w.param_write.get("state") != "writing":
            return
        if ok:
            w.onboard.state, w.onboard.message = "accepted", "the vehicle saved its own calibration"
            w.param_write.update(state="written", message="the vehicle saved its own calibration "
                                                          "(MAV_CMD_DO_ACCEPT_MAG_CAL accepted)")
            self._c._vehicle_in_use("the vehicle saved its own calibration")
            hub.vehicle.request_params(hub.sources.link)
            threading.Thread(target=self._record_in_history, args=self._history_entry(self._onboard_results()),
                             daemon=True, name="fleet-history").start()
        else:
            w.param_write.update(state="failed", message=f"the vehicle refused to save its calibration ({text})")
            hub.event(w.param_write["message"], "error")

    # ------------------------------------------------------------------ reboot
    def reboot(self, confirm: bool) -> dict:
        w = self._w
        if not confirm:
            raise SessionError("confirm the reboot: the vehicle will be unreachable for a few seconds")
        with self._c._lock:
            self._c.send("the reboot", _M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, 0, 0, 0, 0, 0, 0)
            w.reboot = {"state": "sent", "message": "reboot command sent", "sent_unix_s": time.time(),
                        "ack_unix_s": None, "lost": False}
            w.heading_check = None
            self._hub.event("reboot requested (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN)")
            self._hub.changed()
            return w.reboot

    def reboot_ack(self, ok: bool, text: str) -> None:
        rb = self._w.reboot
        if rb is None or rb["state"] != "sent":
            return
        if ok:
            rb.update(state="waiting", message="the vehicle is rebooting", ack_unix_s=time.time())
        else:
            rb.update(state="refused", message=f"reboot {text}")
            self._hub.event(f"the vehicle refused to reboot ({text})", "warning")

    def on_link(self, up: bool) -> None:
        rb = self._w.reboot
        if rb is None or rb["state"] not in ("sent", "waiting"):
            return
        if not up:
            rb.update(state="waiting", lost=True, message="the vehicle is rebooting (link down)")
        elif rb["lost"]:
            self._back("the vehicle is back after its reboot")

    def tick(self) -> None:
        rb = self._w.reboot
        if (rb is not None and rb["state"] == "waiting" and not rb["lost"] and rb["ack_unix_s"]
                and time.time() - rb["ack_unix_s"] > REBOOT_ASSUME_BACK_S and self._hub.sources.link_state == "up"):
            self._back("the vehicle answered again after the reboot command")

    def _back(self, text: str) -> None:
        self._w.reboot.update(state="back", message=text)
        self._hub.vehicle.request_params(self._hub.sources.link)
        self._hub.event(text)

    # ------------------------------------------------------------------ heading check
    def heading_check(self, kind: str, bearing_deg: float | None) -> dict:
        w = self._w
        if kind not in ("bearing", "walk"):
            raise SessionError("kind must be 'bearing' or 'walk'")
        if kind == "bearing" and (bearing_deg is None or not math.isfinite(float(bearing_deg))):
            raise SessionError("give the known true bearing in degrees")
        if w.state == "idle":
            raise ConflictError("nothing to check: calibrate first")
        self._c.live_link("the heading check")
        w.heading_check = HeadingCheck(kind, None if bearing_deg is None else float(bearing_deg) % 360.0,
                                       BEARING_WINDOW_S, w.declination_deg)
        self._hub.event(f"heading check started ({kind})")
        self._hub.changed()
        return w.heading_check.snapshot()

    def stop_walk(self) -> dict:
        hc = self._w.heading_check
        if hc is None or hc.kind != "walk" or hc.state != "measuring":
            raise ConflictError("no walk is being measured")
        r = hc.finish()
        self._hub.event("walk measured: " + (r.get("message") or ""))
        self._hub.changed()
        return hc.snapshot()

    def on_compass0(self, s: MagSample) -> None:
        w = self._w
        roll, pitch, _ = w.latest_att
        if not (math.isfinite(roll) and math.isfinite(pitch)):
            return
        m = self._hub.flight.policy.apply(np.asarray(s.mag_body_mG, dtype=float))[0]
        if w.heading_check is not None and w.heading_check.state == "measuring":
            h = float(compass_heading_deg(np.asarray(m), roll, pitch, w.declination_deg or 0.0))
            w.heading_check.add_heading(s.t_s, h)
            if w.heading_check.state == "done":
                self._hub.event("heading check: " + (w.heading_check.result.get("message") or ""))
        if w.fixed_yaw is not None:
            was = w.fixed_yaw.state
            w.fixed_yaw.on_sample(s.t_s, np.asarray(m, float), roll, pitch)
            if was != w.fixed_yaw.state:
                self._hub.event(w.fixed_yaw.message)

    def on_gps(self, s: GpsSample) -> None:
        hc = self._w.heading_check
        if hc is not None and s.fix_type >= 3 and math.isfinite(s.lat_deg):
            hc.add_fix(s.t_s, s.lat_deg, s.lon_deg)
