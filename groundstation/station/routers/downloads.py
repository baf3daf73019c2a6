"""Downloads: the session's log (its own format, or the .tlog), the analysis report (JSON) and its
per-step CSV."""
from __future__ import annotations

import tempfile
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, PlainTextResponse, Response

from groundstation.jobs.report import write_csv
from groundstation.station.deps import HubDep

router = APIRouter(prefix="/api", tags=["downloads"])


@router.get("/session.tlog", response_class=FileResponse,
            summary="The session as a .tlog (a live link's recording, or a replayed .tlog)")
def session_tlog(hub: HubDep) -> FileResponse:
    path = hub.session_tlog()
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.get("/session/file", response_class=FileResponse,
            summary="The session's log as recorded or replayed (.tlog, .bin, .ulg or .csv)")
def session_file(hub: HubDep) -> FileResponse:
    path = hub.session_file()
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.get("/analysis", summary="analyze report of this session (as `magstation analyze --json`)")
def analysis(hub: HubDep) -> dict:
    report, _ = hub.analysis()
    return report


@router.get("/analysis.csv", response_class=PlainTextResponse)
def analysis_csv(hub: HubDep) -> Response:
    _, table = hub.analysis()
    with tempfile.TemporaryDirectory() as tmp:
        path = write_csv(Path(tmp) / "analysis.csv", table)
        text = path.read_text()
    return PlainTextResponse(text, media_type="text/csv", headers={
        "Content-Disposition": 'attachment; filename="magstation-analysis.csv"'})
