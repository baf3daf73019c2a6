"""The calibration in use, per vehicle/airframe: what the station applies to the field, where it
came from, and keeping the choice across restarts (the fleet history DB, ``fleet_db.set_in_use``).

Sources (``SOURCES``):
  ``log``        the calibration dance found in the replayed log itself (``review.log_own_calibration``)
  ``recording``  the dance of another recording of the folder (``calibrate_log``, a rotation window)
  ``wizard``     the wizard's last successful result (accepting it chooses it too)
  ``history``    the airframe's latest calibration in the fleet history
  ``vehicle``    the vehicle's own parameters (live link, or the replayed log's), as an absolute calibration
  ``upload``     a calibrate JSON or a vehicle .param file uploaded from the page (stored in recordings/)
  ``none``       nothing: the field as the autopilot sent it
A relative calibration is applied on top of the source's corrections in force
(``jobs.calibrate.frame``); the note says how.  The airframe is the vehicle's identity
(``jobs.airframes.identity_key``: serial, board id, system id, else the log's folder, as `review`
names it), mapped by the history.  A replay starts with the log's own dance when it has one, else
the airframe's stored choice.  Every public method runs with the hub lock held by the caller
unless it says otherwise; the slow parts (fitting a recording, reading the DB) run outside it.
"""
from __future__ import annotations

import json
import logging
import re
import time
from contextlib import closing
from pathlib import Path

from groundstation.jsonsafe import jsonable
from groundstation.station.hub.sources import SessionError

__all__ = ["CalibrationInUse", "SOURCES", "InUseError", "MAX_CALIBRATION_UPLOAD_BYTES", "parse_upload"]

log = logging.getLogger(__name__)
SOURCES = ("log", "recording", "wizard", "history", "vehicle", "upload", "none")
SOURCE_TEXT = {"log": "the dance in this log", "recording": "the dance in", "wizard": "the wizard's result",
               "history": "the fleet history", "vehicle": "the vehicle's own parameters", "upload": "uploaded",
               "none": "none"}
MAX_CALIBRATION_UPLOAD_BYTES = 1 << 20    # the station's request-body limit
UPLOAD_SUFFIXES = (".json", ".param", ".parm", ".params", ".txt")


class InUseError(SessionError):
    """A choice that cannot be made (one line for the page; HTTP 400)."""


def _checked(cal: dict, what: str) -> dict:
    from groundstation.jobs.calibrate.frame import compact
    from groundstation.jobs.calibration_check import check_calibration

    try:
        check_calibration(cal)
    except ValueError as err:
        raise InUseError(f"{what}: unusable calibration: {err}") from None
    return jsonable(compact(cal))


def parse_upload(filename: str, data: bytes, autopilot: str | None) -> tuple[dict, str]:
    """(calibration, note) of an uploaded calibrate JSON or .param file.  Raises InUseError (one line)."""
    from groundstation.io.param_file import parse_param_text
    from groundstation.jobs.calibrate.frame import from_params

    name = Path(filename or "").name[:120]
    suffix = Path(name).suffix.lower()
    if suffix not in UPLOAD_SUFFIXES:
        raise InUseError(f"'{name}': give a calibrate JSON or a .param file ({', '.join(UPLOAD_SUFFIXES)})")
    if not data:
        raise InUseError(f"'{name}' is empty")
    if len(data) > MAX_CALIBRATION_UPLOAD_BYTES:
        raise InUseError(f"'{name}': larger than {MAX_CALIBRATION_UPLOAD_BYTES >> 20} MiB")
    if b"\x00" in data:
        raise InUseError(f"'{name}': binary data, not a calibration")
    text = data.decode("utf-8", errors="replace")
    if suffix == ".json" or text.lstrip().startswith("{"):
        try:
            obj = json.loads(text)
        except (ValueError, RecursionError):
            raise InUseError(f"'{name}': not valid JSON") from None
        cands = obj.get("results", [obj]) if isinstance(obj, dict) else []
        for c in cands if isinstance(cands, list) else []:
            if isinstance(c, dict) and c.get("status") in ("ok", "no_parameters") and c.get("offsets_mG") is not None:
                return _checked(c, name), "calibrate JSON"
        raise InUseError(f"'{name}': holds no calibration with status 'ok'")
    pf = parse_param_text(text, name)
    cal = from_params(pf.values, autopilot)
    if cal is None:
        raise InUseError(f"'{name}': no COMPASS_OFS_X/Y/Z (or CAL_MAG0_X/Y/ZOFF) in {len(pf.values)} parameter(s)"
                         + (f", {pf.skipped} bad line(s) skipped" if pf.skipped else ""))
    note = f"{len(pf.values)} parameter(s)" + (f", {pf.skipped} bad line(s) skipped" if pf.skipped else "")
    return _checked(cal, name), note


class CalibrationInUse:
    """The choice and its persistence; ``hub`` is the Session (use_calibration, event, changed,
    vehicle, sources, recordings, calibration)."""

    def __init__(self, hub) -> None:
        self._hub = hub
        self.current: dict | None = None        # {source, label, note, calibration, airframe, unix_s}
        self.log_fit: dict | None = None        # the replayed log's own dance fit
        self.airframe: str | None = None
        self.params_in_force: tuple[dict, str] | None = None   # serve --params: (values, label)

    def fill_params(self, flight_log) -> str | None:
        """serve --params / --assume-uncalibrated: the values in force where the replayed log has none."""
        if self.params_in_force is None:
            return None
        from groundstation.io.param_file import apply_to_log, uncalibrated_params
        values, label = self.params_in_force
        if label == "--assume-uncalibrated":
            values = uncalibrated_params(flight_log.autopilot)
        return apply_to_log(flight_log, values, label)

    # ------------------------------------------------------------------ where
    def db_path(self) -> Path:
        from groundstation.io import fleet_db
        return fleet_db.default_db_path(self._hub.sources.recordings_dir)

    def airframe_of(self, params: dict, folder: str | None) -> str:
        """The history's name of the vehicle (outside the lock: reads the DB)."""
        from groundstation.jobs.airframes import identity_key
        from groundstation.jobs.compass_history import history_airframe
        return history_airframe(self.db_path(), identity_key(params or {}, folder=folder)["identity"])

    def _stored(self, airframe: str) -> dict | None:
        from groundstation.io import fleet_db
        try:
            with closing(fleet_db.connect(self.db_path(), read_only=True)) as con:
                return fleet_db.get_in_use(con, airframe)
        except (FileNotFoundError, OSError, Exception) as err:   # noqa: BLE001 - a broken DB: no stored choice
            if not isinstance(err, FileNotFoundError):
                log.warning("calibration in use: cannot read the history: %s", err)
            return None

    # ------------------------------------------------------------------ replay start (no lock)
    def for_replay(self, flight_log, path: Path | None, own_fit: dict | None) -> dict | None:
        """The choice a replay starts with: the log's own dance, else the airframe's stored choice."""
        airframe = self.airframe_of(flight_log.params, path.parent.name if path is not None else None)
        if own_fit is not None:
            return self._choice("log", "the dance in this log", own_fit, airframe,
                                f"fitted on {path.name if path else 'the log'}")
        stored = self._stored(airframe)
        if stored is None:
            return {"source": "none", "airframe": airframe, "calibration": None, "label": "none", "note": ""}
        return dict(stored, note=f"stored for {airframe} on {time.strftime('%Y-%m-%d %H:%M', time.gmtime(stored['unix_s']))}")

    def start(self, choice: dict | None, own_fit: dict | None) -> None:
        """The replay's analysis is in (lock held)."""
        self.log_fit = own_fit
        self.current = choice if choice and choice.get("calibration") is not None else None
        self.airframe = (choice or {}).get("airframe")
        if self.current is not None and self.current["source"] != "log":
            self._hub.event(f"calibration in use: {self.current['label']} ({self.current['source']}; "
                            f"{self.current.get('note') or ''})", t_s=0.0)

    def new_source(self) -> None:
        self.current, self.log_fit, self.airframe = None, None, None

    # ------------------------------------------------------------------ choosing
    @staticmethod
    def _choice(source: str, label: str, calibration: dict | None, airframe: str | None, note: str = "") -> dict:
        return {"source": source, "label": label, "note": note, "calibration": calibration, "airframe": airframe,
                "unix_s": time.time()}

    def _resolve(self, source: str, name: str | None) -> tuple[dict | None, str, str]:
        """(calibration, label, note) of a source (no lock: may fit a recording or read the DB)."""
        hub = self._hub
        if source == "none":
            return None, "none", "the field as the autopilot sent it"
        if source == "log":
            with hub._lock:
                fit = self.log_fit
            if fit is None:
                raise InUseError("this log has no calibration dance (a replayed log with a rotation window)")
            return fit, "the dance in this log", ""
        if source == "recording":
            from groundstation.jobs.calibrate import calibrate_log
            from groundstation.io.logs import read_log
            try:
                path = hub.recordings.resolve(name or "")
            except (ValueError, FileNotFoundError) as err:
                raise InUseError(str(err)) from None
            try:
                r = calibrate_log(read_log(path))
            except Exception as err:   # noqa: BLE001 - a hostile recording: one line
                raise InUseError(f"{path.name}: cannot be read ({str(err)[:120]})") from None
            if r.get("status") != "ok" or r.get("method") != "window":
                raise InUseError(f"{path.name}: no calibration dance found ({r.get('status')}: "
                                 f"{(r.get('message') or '')[:120]})")
            return _checked(r, path.name), f"the dance in {path.name}", f"window {r['window_s'][0]:.0f}-{r['window_s'][1]:.0f} s"
        if source == "wizard":
            with hub._lock:
                r = hub.calibration.wizard.result
            if not r or r.get("status") != "ok":
                raise InUseError("the wizard has no successful result")
            return _checked(r, "the wizard's result"), "the wizard's result", ""
        if source == "history":
            from groundstation.io import fleet_db
            air = self.airframe or "unknown"
            try:
                with closing(fleet_db.connect(self.db_path(), read_only=True)) as con:
                    rec = fleet_db.calibration_in_force(con, air)
            except FileNotFoundError:
                rec = None
            if rec is None:
                raise InUseError(f"no calibration of {air} in the fleet history")
            when = time.strftime("%Y-%m-%d %H:%M", time.gmtime(rec.get("unix_s") or 0))
            return _checked(rec["calibration"], "history"), f"{air}'s calibration of {when}", rec.get("source") or ""
        if source == "vehicle":
            from groundstation.io.params import ardupilot_never_calibrated
            from groundstation.jobs.calibrate.frame import from_params
            with hub._lock:
                params, ap = dict(hub.vehicle.params), hub.vehicle.autopilot
            cal = from_params(params, ap)
            if cal is None:
                raise InUseError("the vehicle's parameters hold no compass offsets (yet)")
            if ap != "px4" and ardupilot_never_calibrated(params):
                raise InUseError("the vehicle was never calibrated (COMPASS_OFS_* are 0): its parameters are no "
                                 "calibration")
            return _checked(cal, "vehicle"), "the vehicle's own parameters", f"{len(cal.get('ardupilot_params') or cal.get('px4_params') or {})} parameters"
        raise InUseError(f"source must be one of {', '.join(SOURCES)}")

    def choose(self, source: str, name: str | None = None) -> dict:
        """Use a source's calibration from now on and store the choice for the airframe (called
        without the lock)."""
        self._ensure_airframe()
        cal, label, note = self._resolve(source, name)
        return self._use(source, label, cal, note)

    def _ensure_airframe(self) -> None:
        """The airframe of a live vehicle (from its parameters so far) or of the replayed log."""
        hub = self._hub
        with hub._lock:
            if self.airframe is not None:
                return
            params, path, live = dict(hub.vehicle.params), hub.sources.log_path, hub.sources.kind == "live"
        air = self.airframe_of(params, None if live or path is None else path.parent.name)
        with hub._lock:
            self.airframe = self.airframe or air

    def upload(self, filename: str, data: bytes) -> dict:
        """A calibrate JSON or .param file from the page: checked, stored in recordings/ under a
        name of the station's own, then used (called without the lock).  Raises InUseError."""
        hub = self._hub
        self._ensure_airframe()
        with hub._lock:
            autopilot = hub.vehicle.autopilot
        cal, note = parse_upload(filename, data, autopilot)
        suffix = ".json" if cal.get("method") != "parameters" else ".param"
        stem = re.sub(r"[^A-Za-z0-9_-]+", "_", Path(filename).stem)[:40].strip("_") or "calibration"
        folder = hub.recordings
        folder.dir.mkdir(parents=True, exist_ok=True)
        path = folder.new_path("calibration", suffix, stem)
        path.write_bytes(data)
        return self._use("upload", f"uploaded {Path(filename).name[:60]}", cal, f"{note}; stored as {path.name}")

    def accepted(self, result: dict) -> None:
        """The wizard's result was accepted (lock held): it is the calibration in use, stored in the
        background."""
        try:
            cal = _checked(result, "the wizard's result")
        except InUseError:
            return
        self.current = self._choice("wizard", "the wizard's result", cal, self.airframe, "accepted")
        self._store_later(self.current, history=self._hub.sources.kind != "live")

    def _use(self, source: str, label: str, cal: dict | None, note: str) -> dict:
        from groundstation.jobs.calibrate.frame import frame_label
        hub = self._hub
        with hub._lock:
            choice = self._choice(source, label, cal, self.airframe, note)
            applied = self._for_source(cal) if cal is not None else None
            self.current = choice if cal is not None else None
            hub.use_calibration(applied)
            hub.event(f"calibration in use: {label}" + (f" ({frame_label(cal)})" if cal else ""))
            hub.changed()
        self._store(choice, history=source in ("log", "recording", "wizard", "upload") and cal is not None
                    and cal.get("method") != "parameters")
        with hub._lock:
            return self.snapshot()

    def _for_source(self, cal: dict) -> dict:
        """The calibration as the flight analysis takes it (lock held).  Replays: as it is (the
        whole-log analysis applies a relative one on top of the log's corrections).  Live: a
        relative one is composed with the vehicle's corrections in force when they are known."""
        hub = self._hub
        if hub.sources.kind != "live":
            return cal
        from groundstation.jobs.calibrate.frame import for_log, from_params
        from groundstation.jobs.calibration_check import check_calibration
        own = from_params(hub.vehicle.params, hub.vehicle.autopilot)
        b, C = check_calibration(cal)
        a = for_log(b, C, cal, "ok" if own is not None else "no_parameters",
                    None if own is None else own["offsets_mG"], None if own is None else own["matrix"])
        hub.event(f"calibration in use: {a.note}")
        return dict(cal, offsets_mG=a.offsets_mG.tolist(), matrix=a.matrix.tolist(), relative_to="raw"
                    if own is not None else cal.get("relative_to"))

    # ------------------------------------------------------------------ storing
    def _store_later(self, choice: dict, history: bool) -> None:
        import threading
        threading.Thread(target=self._store, args=(choice, history), daemon=True, name="in-use-store").start()

    def _store(self, choice: dict, history: bool) -> None:
        """The choice for the airframe (and, for a fit, a history record so `review` uses it)."""
        from groundstation.io import fleet_db
        try:
            if not choice.get("airframe"):          # a live vehicle accepted before anything was chosen
                self._ensure_airframe()
                choice["airframe"] = self.airframe
            air = choice["airframe"]
            with closing(fleet_db.connect(self.db_path())) as con:
                fleet_db.set_in_use(con, air, choice["source"], choice["label"], choice.get("calibration"),
                                    choice["unix_s"])
            if history:
                from groundstation.jobs.compass_history import record_calibration
                record_calibration(self.db_path(), air, choice["calibration"], compass=choice["calibration"].get(
                    "compass") or 0, written_to_vehicle=False, source=f"station: {choice['label']}",
                    unix_s=self._dance_time(choice))
        except Exception as err:   # noqa: BLE001 - the choice stays in use; the page says it was not kept
            log.warning("calibration in use not stored: %s", err)
            with self._hub._lock:
                self._hub.event(f"calibration in use not stored in the history: {str(err)[:160]}", "warning")

    def _dance_time(self, choice: dict) -> float:
        """When the calibration was made: the dance's time in its log when known, else now."""
        hub = self._hub
        with hub._lock:
            r = hub.sources.replay
            start = getattr(getattr(r, "log", None), "start_unix_s", None)
        w = (choice.get("calibration") or {}).get("window_s")
        if choice["source"] == "log" and start and w:
            return float(start) + float(w[0])
        if choice["source"] == "recording" and w:
            try:
                from groundstation.io.logs import read_log
                path = hub.recordings.resolve(choice["label"].rsplit(" ", 1)[-1])
                s = read_log(path).start_unix_s
                if s:
                    return float(s) + float(w[0])
            except Exception:   # noqa: BLE001 - fall back to now
                pass
        return float(choice["unix_s"])

    # ------------------------------------------------------------------ reading (lock held)
    def options(self) -> dict:
        hub = self._hub
        from groundstation.jobs.calibrate.frame import from_params
        opts = [{"source": "none", "label": "none (the field as the autopilot sent it)"}]
        if self.log_fit is not None:
            opts.append({"source": "log", "label": "the dance in this log"})
        if (hub.calibration.wizard.result or {}).get("status") == "ok":
            opts.append({"source": "wizard", "label": "the wizard's result"})
        if from_params(hub.vehicle.params, hub.vehicle.autopilot) is not None:
            opts.append({"source": "vehicle", "label": "the vehicle's own parameters"})
        opts.append({"source": "history", "label": f"the fleet history ({self.airframe or 'this vehicle'})"})
        for n in hub.recordings.names():
            opts.append({"source": "recording", "name": n, "label": f"the dance in {n}"})
        return {"current": self.snapshot(), "options": opts}

    def snapshot(self) -> dict:
        from groundstation.jobs.calibrate.frame import frame_label
        c = self.current
        if c is None or c.get("calibration") is None:
            return {"source": "none", "label": "none", "relative_to": None, "frame": None, "note": "",
                    "airframe": self.airframe}
        cal = c["calibration"]
        review = self._hub.flight.review
        applied = review.calibration_note if review is not None and review.calibration is not None else None
        return {"source": c["source"], "label": c["label"], "relative_to": cal.get("relative_to"),
                "frame": frame_label(cal), "note": c.get("note") or "", "airframe": c.get("airframe") or self.airframe,
                "unix_s": c.get("unix_s"), "applied": applied}
