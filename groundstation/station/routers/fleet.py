"""The fleet page's data: the compass history written by `magstation review` and by accepted
calibrations, read-only.  The database path comes from the app (``app.state.fleet_db_path``), else
``fleet_db.default_db_path`` ($MAGSTATION_FLEET_DB, else fleet.sqlite in the station's recordings
folder, where the calibration write records too), never from the request."""
from __future__ import annotations

import sqlite3
from contextlib import closing, contextmanager
from pathlib import Path
from typing import Iterator

from fastapi import APIRouter, HTTPException, Query, Request

from groundstation.io import fleet_db

router = APIRouter(prefix="/api/fleet", tags=["fleet"])

HISTORY_COLUMNS = ("log_hash", "compass", "file_name", "date", "start_unix_s", "duration_s", "payload", "status", "error",
                   "fit_status", "fit_ofs_x_mG", "fit_ofs_y_mG", "fit_ofs_z_mG", "site", "site_offset_x_mG",
                   "site_offset_y_mG", "site_offset_z_mG", "ofs_change_mG", "interference_pct",
                   "strength_resid_mG", "inclination_resid_deg", "alarm_count", "alarm_evidence",
                   "heading_vs_autopilot_max_deg", "max_cross_track_m", "lat_deg", "lon_deg")


def db_path(request: Request) -> Path:
    configured = getattr(request.app.state, "fleet_db_path", None)
    if configured:
        return Path(configured)
    sources = getattr(getattr(request.app.state, "hub", None), "sources", None)
    return fleet_db.default_db_path(getattr(sources, "recordings_dir", None))


@contextmanager
def _reader(request: Request) -> Iterator[sqlite3.Connection]:
    path = db_path(request)
    try:
        con = fleet_db.connect(path, read_only=True)
    except FileNotFoundError:
        raise HTTPException(404, f"no fleet history yet ({path.name}): run `magstation review` first") from None
    try:
        with closing(con):
            yield con
    except sqlite3.OperationalError as err:   # a file that is not (yet) a history
        raise HTTPException(503, f"fleet history unreadable: {err}") from None


@router.get("/summary", summary="airframes, alerts and sites of the fleet history")
def summary(request: Request) -> dict:
    with _reader(request) as con:
        airframes = fleet_db.airframe_summary(con)
        return {"history": db_path(request).name, "airframes": airframes, "alerts": fleet_db.alert_rows(con),
                "sites": fleet_db.site_rows(con), "flights": sum(a["flights"] for a in airframes),
                "failed": sum(a["failed"] or 0 for a in airframes)}


@router.get("/airframes/{airframe}", summary="one airframe's flights and calibrations, oldest first")
def airframe_history(airframe: str, request: Request) -> dict:
    with _reader(request) as con:
        rows = fleet_db.flight_rows(con, airframe=airframe)
        if not rows:
            raise HTTPException(404, f"no flights of airframe {airframe!r} in the history")
        return {"airframe": airframe, "flights": [{k: r.get(k) for k in HISTORY_COLUMNS} for r in rows],
                "calibrations": fleet_db.calibration_rows(con, airframe=airframe)}


@router.get("/flights", summary="reviewed flights, most concerning first")
def worst_flights(request: Request, limit: int = Query(50, ge=1, le=1000)) -> list[dict]:
    with _reader(request) as con:
        return [{k: r.get(k) for k in HISTORY_COLUMNS + ("airframe",)}
                for r in fleet_db.worst_flight_rows(con, limit)]
