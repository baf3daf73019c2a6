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
import errno
import os
import socket
import threading
import time
from pathlib import Path

from fastapi import Depends, FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from groundstation.io.errors import IngestError
from groundstation.paths import RECORDINGS_DIR, WEB_DIR
from groundstation.station import security
from groundstation.station.deps import install_error_handlers
from groundstation.station.hub.session import Session, SessionError
from groundstation.station.push import Pusher
from groundstation.station.routers import (alarms, calibration, downloads, fleet, line, plots, recordings, replay,
                                           source, status, vehicles, ws)
from groundstation.station.security import AccessPolicy, StationGuard, protect_viser, require_operator, server_options
from groundstation.station.settings import WILDCARD_HOSTS, StationSettings

__all__ = ["create_app", "Station", "StationStartError", "serve"]

ROUTERS = (status, source, recordings, replay, plots, calibration, line, alarms, downloads, vehicles, fleet)


class StationStartError(Exception):
    """The station cannot start (port busy, bad TLS files, source refused): one line for the user."""


def create_app(hub: Session, viser_port: int | None = None, settings: StationSettings | None = None,
               access: AccessPolicy | None = None) -> FastAPI:
    """The FastAPI app over ``hub``: every /api router behind ``require_operator``, the whole app
    behind ``StationGuard`` (Host allow-list, remote token, WebSocket Origin, body limits)."""
    pusher = Pusher()
    settings = settings or StationSettings(viser_port=viser_port, recordings_dir=getattr(
        getattr(hub, "sources", None), "recordings_dir", RECORDINGS_DIR))
    access = access or AccessPolicy.from_settings(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        pusher.loop = asyncio.get_running_loop()
        hub.add_listener(pusher.notify)
        yield
        hub.remove_listener(pusher.notify)

    # /docs from the Swagger UI files that fastapi-offline ships (served under /static-offline-docs):
    # the API page renders on a field laptop without internet, no CDN.  No /redoc: its page fetches
    # its logo from the vendor's CDN, and one API page is enough.
    app = FastAPIOffline(title="MagStation", version="0.1.0", lifespan=lifespan, redoc_url=None,
                         description="Magnetometer calibration, heading integrity and flight replay.")
    app.state.hub = hub
    app.state.pusher = pusher
    app.state.viser_port = viser_port
    app.state.started_unix_s = time.time()
    app.state.access = access
    install_error_handlers(app)
    for module in ROUTERS:
        app.include_router(module.router, dependencies=[Depends(require_operator)])
    app.include_router(ws.router)              # WebSocket Origin/Host/token: StationGuard
    app.include_router(security.router, dependencies=[Depends(require_operator)])

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/index.html")

    app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    app.add_middleware(StationGuard, policy=access)
    return app


def open_forwarder(settings: StationSettings):
    """The forwarding outputs of ``settings.forward`` (None without); raises IngestError."""
    if not settings.forward:
        return None
    from groundstation.io.forward import Forwarder

    return Forwarder(settings.forward, listen_any=settings.allow_remote).start()


def bind_listening_socket(host: str, port: int) -> socket.socket:
    """Bind and listen on host:port now, so a busy port is reported before anything is printed.

    Raises:
        StationStartError: one line (port in use, address not available, permission denied).
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host or "0.0.0.0", port))
        sock.listen(2048)
        sock.set_inheritable(True)
    except OSError as err:
        sock.close()
        why = {errno.EADDRINUSE: "the port is in use by another program (choose one with --port)",
               errno.EACCES: "permission denied (ports below 1024 need privileges)"}.get(
            err.errno, os.strerror(err.errno) if err.errno else str(err))
        raise StationStartError(f"cannot listen on {host}:{port}: {why}") from err
    return sock


class Station:
    """Hub + viser scene + uvicorn in this process; ``start()`` runs uvicorn in a thread
    (tests, benchmarks), ``run()`` blocks (the CLI).  The web port is bound in the constructor.

    Raises:
        StationStartError: port busy, TLS files unreadable.
    """

    def __init__(self, settings: StationSettings | None = None, **options) -> None:
        import uvicorn

        self.settings = settings = settings or StationSettings(**options)
        self.socket = bind_listening_socket(settings.host, settings.port)
        self.scene = None
        try:
            forwarder = open_forwarder(settings)
        except IngestError as err:
            self.socket.close()
            raise StationStartError(str(err)) from err
        self.session = Session(settings.recordings_dir, record_live=settings.record_live,
                               max_upload_bytes=int(settings.max_upload_mb * 1e6),
                               link_options=settings.link_options(), forwarder=forwarder)
        if settings.params_in_force is not None:      # serve --params / --assume-uncalibrated
            self.session.in_use.params_in_force = (dict(settings.params_in_force), settings.params_label)
        try:
            self.access = AccessPolicy.from_settings(settings)
            if settings.viser_port is not None:
                from groundstation.station.scene import Scene
                self.scene = Scene(self.session, host=settings.viser_host, port=settings.viser_port)
                protect_viser(self.scene.server, self.access)
            self.viser_port = self.scene.port if self.scene else None
            # with TLS the 3-D view is on loopback only: the page (remote, https) does not embed it
            page_viser_port = None if settings.tls else self.viser_port
            self.app = create_app(self.session, page_viser_port, settings, self.access)
            tls = {"ssl_certfile": str(settings.tls_cert), "ssl_keyfile": str(settings.tls_key)} if settings.tls else {}
            config = uvicorn.Config(self.app, host=settings.host, port=settings.port, log_level="warning",
                                    ws_ping_interval=None, **server_options(settings.connection_limits), **tls)
            try:
                config.load()
            except (OSError, ValueError) as err:   # ssl.SSLError is an OSError
                raise StationStartError(f"cannot use the TLS certificate/key: {err}") from err
            self.server = uvicorn.Server(config)
        except BaseException:
            self.close_resources()
            raise
        self.host = settings.host
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self.socket.getsockname()[1]

    @property
    def url(self) -> str:
        host = socket.gethostname() if self.host in WILDCARD_HOSTS else self.host
        host = f"[{host}]" if ":" in host else host
        return f"{self.settings.scheme}://{host}:{self.port}"

    @property
    def viser_url(self) -> str | None:
        if self.viser_port is None:
            return None
        host = self.settings.viser_host
        host = socket.gethostname() if host in WILDCARD_HOSTS else host
        return f"http://{host}:{self.viser_port}/"

    def start(self) -> "Station":
        self._thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.socket]},
                                        daemon=True, name="uvicorn")
        self._thread.start()
        deadline = time.monotonic() + 15
        while not self.server.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise RuntimeError("the web server did not start")
            time.sleep(0.02)
        return self

    def run(self) -> None:
        try:
            self.server.run(sockets=[self.socket])
        finally:
            self.close()

    def close(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.close_resources()

    def close_resources(self) -> None:
        self.session.close()
        if self.scene is not None:
            self.scene.close()
            self.scene = None
        self.socket.close()


def serve(settings: StationSettings, connect: str | None, replay: Path | None, speed: float = 1.0) -> None:
    """Run the station until Ctrl-C: live link ``connect`` or replay ``replay`` (the bundled
    demo loops).  The address is printed once the port is bound and the source is open.

    Raises:
        StationStartError: one line (port busy, TLS files, the source refused).
    """
    station = Station(settings)
    try:
        if connect:
            station.session.connect(connect)
        elif replay is not None:
            replay = Path(replay)
            loop = replay.resolve().parent == RECORDINGS_DIR.resolve() and replay.name == "demo.tlog"
            station.session.start_replay(replay, speed, loop=loop)
    except SessionError as err:
        station.close_resources()
        raise StationStartError(str(err)) from err
    token = f"?token={settings.access_token}" if settings.allow_remote else ""
    print(f"MagStation: web page {station.url}/{token} (calibration: /calibrate.html, API: /docs), "
          f"3-D view {station.viser_url or 'off'}", flush=True)
    for line_text in link_lines(settings):
        print(f"MagStation: {line_text}", flush=True)
    if settings.allow_remote:
        print(f"MagStation: remote mode: scripts send 'Authorization: Bearer {settings.access_token}'; "
              f"allowed host names: {', '.join(sorted(station.access.hosts))}", flush=True)
    station.run()


def link_lines(settings: StationSettings) -> list[str]:
    """What the operator chose for the live link, one line each (the signing key never shown)."""
    out = []
    if settings.sysid is not None:
        out.append(f"following vehicle (system id) {settings.sysid}")
    if settings.passive:
        out.append("passive: listening only, nothing is sent to the vehicle")
    for url in settings.forward:
        out.append(f"forwarding the vehicle link to {url}")
    if settings.signing_key is not None:
        from groundstation.io.signing import key_id
        out.append(f"MAVLink 2 signing on (key id {key_id(settings.signing_key)})")
    return out
