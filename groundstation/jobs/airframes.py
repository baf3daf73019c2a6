"""The operator's airframe mapping: which vehicle identity is which airframe, and its payload.

File formats (``load_airframes``):
  JSON  {"airframes": [{"match": {"serial": 7100}, "airframe": "AF-01", "payload": "lidar",
                        "from_date": "2026-02-01"}, ...]}
        match keys: serial, uid, sysid, folder (the log's folder name), path (a glob on the log path)
  CSV   key,airframe,payload,from_date   with key like  serial:7100  uid:0036...  sysid:3
        folder:AF-01  path:*/hexa-2/*   (payload and from_date may be empty)
An entry with ``from_date`` applies to logs from that date (UTC) on; for one identity the latest
applicable entry wins, so a payload swap is a second line with a later date.  A log no entry matches
keeps its identity key as the airframe name (``groundstation.jobs.review_row.vehicle_identity``).
"""
from __future__ import annotations

import calendar
import csv
import fnmatch
import json
from dataclasses import dataclass
from pathlib import Path

__all__ = ["AirframeEntry", "load_airframes", "resolve_airframe", "identity_key", "airframe_for_vehicle"]

_KINDS = ("serial", "uid", "sysid", "folder", "path")


@dataclass(frozen=True)
class AirframeEntry:
    kind: str            # serial | uid | sysid | folder | path
    value: str
    airframe: str
    payload: str | None = None
    from_unix_s: float = float("-inf")


def _date_unix_s(text: str | None, where: str) -> float:
    if not text:
        return float("-inf")
    try:
        y, m, d = (int(v) for v in str(text).strip()[:10].split("-"))
        return float(calendar.timegm((y, m, d, 0, 0, 0)))
    except ValueError as err:
        raise ValueError(f"{where}: from_date {text!r} is not YYYY-MM-DD") from err


def _entry(kind: str, value, airframe, payload, from_date, where: str) -> AirframeEntry:
    kind = str(kind).strip().lower()
    if kind not in _KINDS:
        raise ValueError(f"{where}: unknown match key {kind!r} (use {', '.join(_KINDS)})")
    if not airframe:
        raise ValueError(f"{where}: no airframe name")
    text = str(value).strip()
    if kind in ("serial", "sysid"):
        try:
            text = str(int(float(text)))
        except ValueError as err:
            raise ValueError(f"{where}: {kind} {value!r} is not a number") from err
    return AirframeEntry(kind, text.upper() if kind == "uid" else text, str(airframe).strip(),
                         (str(payload).strip() or None) if payload else None, _date_unix_s(from_date, where))


def load_airframes(path: str | Path) -> list[AirframeEntry]:
    """Read a mapping file (.json or .csv).  Raises ValueError with the file and entry on bad content,
    OSError when it cannot be read."""
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    out = []
    if path.suffix.lower() == ".csv":
        for i, rec in enumerate(csv.DictReader(text.splitlines()), start=2):
            key = (rec.get("key") or "").strip()
            if ":" not in key:
                raise ValueError(f"{path.name} line {i}: key {key!r} must look like serial:7100")
            kind, value = key.split(":", 1)
            out.append(_entry(kind, value, rec.get("airframe"), rec.get("payload"), rec.get("from_date"),
                              f"{path.name} line {i}"))
        return out
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path.name}: not JSON ({err})") from err
    items = data.get("airframes") if isinstance(data, dict) else None
    if not isinstance(items, list):
        raise ValueError(f'{path.name}: expected {{"airframes": [...]}}')
    for i, item in enumerate(items):
        match = item.get("match") if isinstance(item, dict) else None
        if not isinstance(match, dict) or len(match) != 1:
            raise ValueError(f"{path.name} entry {i}: 'match' must hold exactly one key")
        (kind, value), = match.items()
        out.append(_entry(kind, value, item.get("airframe"), item.get("payload"), item.get("from_date"),
                          f"{path.name} entry {i}"))
    return out


def _matches(e: AirframeEntry, row: dict) -> bool:
    if e.kind == "path":
        return fnmatch.fnmatch(str(row.get("path") or ""), e.value)
    if e.kind == "folder":
        return Path(str(row.get("path") or "")).parent.name == e.value
    have = {"serial": row.get("serial"), "uid": row.get("board_uid"), "sysid": row.get("sysid")}[e.kind]
    return have is not None and str(have).upper() == e.value.upper()


def resolve_airframe(row: dict, entries: list[AirframeEntry]) -> tuple[str, str | None]:
    """(airframe, payload) of a row: the latest entry that matches and applies at the row's date;
    else the row's identity key and no payload."""
    start = row.get("start_unix_s")
    start = float("inf") if start is None else float(start)
    best = None
    for e in entries:
        if e.from_unix_s <= start and _matches(e, row) and (best is None or e.from_unix_s >= best.from_unix_s):
            best = e
    if best is None:
        return str(row.get("identity") or row.get("airframe") or "unknown"), None
    return best.airframe, best.payload


def identity_key(params: dict, board_uid: str | None = None, folder: str | None = None) -> dict:
    """sysid, serial, board_uid, identity (the key that names a vehicle) and identity_source.

    Key order: ``serial:N`` (ArduPilot BRD_SERIAL_NUM when set), ``uid:...`` (the board's unique id
    ArduPilot prints at boot), ``sysid:N`` (SYSID_THISMAV / MAV_SYS_ID when not the default 1),
    ``folder:NAME`` (the log's folder), else ``unknown``."""
    sysid = params.get("SYSID_THISMAV", params.get("MAV_SYS_ID"))
    serial = params.get("BRD_SERIAL_NUM")
    serial = str(int(serial)) if serial else None
    if serial:
        key, source = f"serial:{serial}", "serial"
    elif board_uid:
        key, source = f"uid:{board_uid}", "board_uid"
    elif sysid is not None and int(sysid) != 1:
        key, source = f"sysid:{int(sysid)}", "sysid"
    elif folder:
        key, source = f"folder:{folder}", "folder"
    else:
        key, source = "unknown", "none"
    return {"sysid": int(sysid) if sysid is not None else None, "serial": serial, "board_uid": board_uid,
            "identity": key, "identity_source": source}


def airframe_for_vehicle(params: dict, entries: list[AirframeEntry] = (), board_uid: str | None = None,
                         unix_s: float | None = None) -> str:
    """The airframe name of a connected vehicle from its parameters (what the station passes to
    ``record_calibration``): the mapping's name when an entry matches, else the identity key."""
    row = dict(identity_key(params, board_uid), start_unix_s=unix_s)
    return resolve_airframe(row, list(entries))[0]
