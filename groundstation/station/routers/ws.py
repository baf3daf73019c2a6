"""/ws: the live state stream the page renders from."""
from __future__ import annotations

from fastapi import APIRouter, WebSocket

from groundstation.station.push import stream_state

router = APIRouter()


@router.websocket("/ws")
async def ws(websocket: WebSocket) -> None:
    await websocket.accept()
    app = websocket.app
    await stream_state(websocket, app.state.pusher, app.state.hub.snapshot_json)
