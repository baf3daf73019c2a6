"""The station's web server: FastAPI (REST + WebSocket + static pages) and viser, one process.

``create_app(hub)`` builds the FastAPI app from one router per resource
(``groundstation.station.routers``); the routes only translate HTTP to hub calls, and hub errors
become HTTP errors in one place (``deps.install_error_handlers``).  ``Station`` runs the hub, the
viser scene and uvicorn; ``serve(...)`` is what `magstation serve` calls.  REST is under /api
(OpenAPI at /docs); the page gets state pushes on /ws; the 3-D view is a viser server on its own
port.  Everything binds loopback unless the settings allow remote access.
"""
from __future__ import annotations

import contextlib
import asyncio
import threading
import time
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

from groundstation.paths import RECORDINGS_DIR, WEB_DIR
from groundstation.station.deps import install_error_handlers
from groundstation.station.hub.session import Session
from groundstation.station.push import Pusher
from groundstation.station.routers import alarms, calibration, downloads, fleet, line, replay, source, status, ws
from groundstation.station.settings import StationSettings

__all__ = ["create_app", "Station", "serve"]

ROUTERS = (status, source, replay, calibration, line, alarms, downloads, fleet, ws)


def create_app(hub: Session, viser_port: int | None = None) -> FastAPI:
    pusher = Pusher()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        pusher.loop = asyncio.get_running_loop()
        hub.add_listener(pusher.notify)
        yield
        hub.remove_listener(pusher.notify)

    app = FastAPI(title="MagStation", version="0.1.0", lifespan=lifespan,
                  description="Magnetometer calibration, heading integrity and flight replay.")
    app.state.hub = hub
    app.state.pusher = pusher
    app.state.viser_port = viser_port
    app.state.started_unix_s = time.time()
    install_error_handlers(app)
    for module in ROUTERS:
        app.include_router(module.router)

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/index.html")

    app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    return app


class Station:
    """Hub + viser scene + uvicorn in this process; ``start()`` runs uvicorn in a thread
    (tests, benchmarks), ``run()`` blocks (the CLI)."""

    def __init__(self, settings: StationSettings | None = None, **options) -> None:
        import uvicorn

        self.settings = settings = settings or StationSettings(**options)
        self.session = Session(settings.recordings_dir, record_live=settings.record_live)
        self.scene = None
        if settings.viser_port is not None:
            from groundstation.station.scene import Scene
            self.scene = Scene(self.session, host=settings.host, port=settings.viser_port)
        self.viser_port = self.scene.port if self.scene else None
        self.app = create_app(self.session, self.viser_port)
        self.server = uvicorn.Server(uvicorn.Config(self.app, host=settings.host, port=settings.port,
                                                    log_level="warning", ws_ping_interval=None))
        self.host = settings.host
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        for s in self.server.servers:
            for sock in s.sockets:
                return sock.getsockname()[1]
        return self.server.config.port

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self) -> "Station":
        self._thread = threading.Thread(target=self.server.run, daemon=True, name="uvicorn")
        self._thread.start()
        deadline = time.monotonic() + 15
        while not self.server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError("the web server did not start")
            time.sleep(0.02)
        return self

    def run(self) -> None:
        self.server.run()
        self.close()

    def close(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.session.close()
        if self.scene is not None:
            self.scene.close()


def serve(settings: StationSettings, connect: str | None, replay: Path | None, speed: float = 1.0) -> None:
    """Run the station until Ctrl-C: live link ``connect`` or replay ``replay`` (the bundled
    demo loops)."""
    station = Station(settings)
    if connect:
        station.session.connect(connect)
    elif replay is not None:
        replay = Path(replay)
        loop = replay.resolve().parent == RECORDINGS_DIR.resolve() and replay.name == "demo.tlog"
        station.session.start_replay(replay, speed, loop=loop)
    host = settings.host
    print(f"MagStation: web page http://{host}:{station.port if station.server.started else settings.port}/ "
          f"(calibration: /calibrate.html, API: /docs), 3-D view http://{host}:{station.viser_port}/")
    station.run()
