"""State pushes to the page: one JSON snapshot per state change, flow-controlled per client.

``Pusher.notify`` is the hub listener (called on the worker thread); it wakes every client's
coroutine on the event loop.  ``stream_state`` runs one client: at most 50 pushes per second, at
least 2 (ages keep moving), and at most ``MAX_INFLIGHT`` unacknowledged messages, so a slow
client gets the newest state when it is ready instead of a growing backlog of old ones.
"""
from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Callable

from fastapi import WebSocket, WebSocketDisconnect

__all__ = ["Pusher", "stream_state"]

MIN_PUSH_INTERVAL_S = 0.02     # <= 50 pushes/s per client
MAX_PUSH_GAP_S = 0.5           # >= 2 pushes/s even when nothing changes (ages, liveness)
MAX_INFLIGHT = 2               # unacknowledged pushes per client
ACK_TIMEOUT_S = 1.0


class Pusher:
    """Wakes every WebSocket client when the session changes (called from the worker thread)."""

    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None
        self.clients: set[asyncio.Event] = set()
        self._pending = False

    def notify(self) -> None:
        loop = self.loop
        if loop is None or self._pending or loop.is_closed():
            return
        self._pending = True
        try:
            loop.call_soon_threadsafe(self._wake)
        except RuntimeError:
            self._pending = False

    def _wake(self) -> None:
        self._pending = False
        for ev in self.clients:
            ev.set()


async def stream_state(websocket: WebSocket, pusher: Pusher, snapshot_json: Callable[[], str]) -> None:
    """Push snapshots to one accepted client until it goes away.  The client answers each
    message with any short text ("ack"); a client that never answers still gets one message
    per ACK_TIMEOUT_S."""
    ev = asyncio.Event()
    acked = asyncio.Event()
    pusher.clients.add(ev)
    state = {"inflight": 0, "closed": False}

    async def reader() -> None:
        try:
            while True:
                await websocket.receive_text()
                state["inflight"] = max(0, state["inflight"] - 1)
                acked.set()
        except Exception:  # disconnect or a malformed frame: stop this client
            state["closed"] = True
            ev.set()
            acked.set()

    read_task = asyncio.create_task(reader())
    last = 0.0
    try:
        while not state["closed"]:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(ev.wait(), timeout=MAX_PUSH_GAP_S)
            while state["inflight"] >= MAX_INFLIGHT and not state["closed"]:
                acked.clear()
                try:
                    await asyncio.wait_for(acked.wait(), timeout=ACK_TIMEOUT_S)
                except asyncio.TimeoutError:
                    state["inflight"] = MAX_INFLIGHT - 1
            wait = MIN_PUSH_INTERVAL_S - (time.monotonic() - last)
            if wait > 0:
                await asyncio.sleep(wait)
            if state["closed"]:
                break
            ev.clear()
            await websocket.send_text(snapshot_json())
            state["inflight"] += 1
            last = time.monotonic()
    except (WebSocketDisconnect, RuntimeError, ConnectionError):
        pass
    finally:
        pusher.clients.discard(ev)
        read_task.cancel()
