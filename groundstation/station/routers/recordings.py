"""The recordings folder: what each log holds, and uploads from the browser.

An upload is the raw file as the request body (``Content-Type: application/octet-stream``) with
its original name in ``?filename=``; the station checks its size, suffix and content and stores
it under a name of its own in recordings/.
"""
from __future__ import annotations

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool

from groundstation.station.deps import HubDep
from groundstation.station.hub.recordings import UploadError
from groundstation.station.schemas import RecordingInfo

router = APIRouter(prefix="/api/recordings", tags=["recordings"])


@router.get("/info", response_model=list[RecordingInfo],
            summary="Every recording with its duration, date, size, vehicle and compasses")
def recordings_info(hub: HubDep) -> list[dict]:
    return hub.recordings_info()


@router.post("/upload", response_model=RecordingInfo, status_code=201,
             summary="Upload a log (.tlog, .bin, .ulg, .csv) as the raw request body")
async def upload(request: Request, hub: HubDep,
                 filename: str = Query(..., min_length=1, max_length=255,
                                       description="the file's own name (its suffix says the type)")) -> dict:
    try:
        declared = int(request.headers.get("content-length") or 0)
        if declared > hub.recordings.max_upload_bytes:
            raise UploadError(f"upload larger than the limit of {hub.recordings.max_upload_bytes / 1e6:g} MB",
                              too_large=True)
        up = hub.recordings.begin_upload(filename)
        try:
            async for chunk in request.stream():
                up.write(chunk)
        except UploadError:
            raise
        except Exception:
            up.abort()
            raise
        return await run_in_threadpool(up.finish)
    except UploadError as err:
        raise HTTPException(413 if err.too_large else 422, detail=str(err)) from None
