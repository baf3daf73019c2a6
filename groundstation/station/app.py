"""The station's web server: FastAPI (REST + WebSocket + static pages) and viser, one process.

``serve(...)`` is what `magstation serve` calls.  REST is under /api (OpenAPI at /docs); the
page gets state pushes on /ws (one JSON snapshot per state change, at most 50 per second per
client, at least 2 per second); the 3-D view is a viser server on its own port.
Everything binds loopback unless ``allow_remote`` is given.
"""
from __future__ import annotations

import asyncio
import contextlib
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Literal

from fastapi import FastAPI, HTTPException, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, PlainTextResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from groundstation.station.hub.session import Session, SessionError

from groundstation.paths import RECORDINGS_DIR as DEFAULT_RECORDINGS, WEB_DIR
LOOPBACK = ("127.0.0.1", "localhost", "::1")
MIN_PUSH_INTERVAL_S = 0.02     # <= 50 pushes/s per client
MAX_PUSH_GAP_S = 0.5           # >= 2 pushes/s even when nothing changes (ages, liveness)
MAX_INFLIGHT = 2               # unacknowledged pushes per client (see /ws)
ACK_TIMEOUT_S = 1.0


# ----------------------------------------------------------------------------------- models

class Health(BaseModel):
    status: Literal["ok"] = "ok"
    uptime_s: float
    source: str
    viser_port: int | None
    clients: int


class SourceInfo(BaseModel):
    kind: Literal["none", "live", "replay"]
    name: str
    link: str
    autopilot: str | None
    recording: str | None


class ReplayInfo(BaseModel):
    t_s: float
    duration_s: float
    paused: bool
    speed: float
    finished: bool
    loop: bool


class Vehicle(BaseModel):
    roll_deg: float | None
    pitch_deg: float | None
    yaw_deg: float | None
    ap_roll_deg: float | None = Field(description="the autopilot's own attitude estimate")
    ap_pitch_deg: float | None
    ap_yaw_deg: float | None
    heading_mag_deg: float | None = Field(description="tilt-compensated magnetic heading (true)")
    heading_att_deg: float | None = Field(description="attitude-filter heading (true)")
    v_forward_mps: float | None
    v_lateral_mps: float | None
    cross_track_m: float | None
    field_mG: float | None
    lat_deg: float | None
    lon_deg: float | None
    fix_type: int


class AlarmNow(BaseModel):
    active: bool
    evidence: list[str]
    since_s: float | None


class Line(BaseModel):
    a: list[float] = Field(min_length=2, max_length=2, description="[lat_deg, lon_deg]")
    b: list[float] = Field(min_length=2, max_length=2, description="[lat_deg, lon_deg]")
    source: str = "user"


class ParamWrite(BaseModel):
    state: str
    autopilot: str | None = None
    total: int = 0
    confirmed: list[str] = []
    failed: list[str] = []
    message: str = ""


class Wizard(BaseModel):
    state: str
    step: str | None
    step_index: int
    instruction: str
    progress_deg: dict[str, float]
    turn_target_deg: float
    coverage: float
    coverage_target: float
    samples: int
    rls_offsets_mG: list[float] | None
    rls_field_mG: float | None
    expected_field_mG: float | None
    warnings: list[str]
    result: dict[str, Any] | None = Field(description="calibration result object (issue 3) "
                                                      "+ heading_error_deg")
    param_write: ParamWrite | None


class Event(BaseModel):
    t_s: float
    unix_s: float
    level: str
    text: str


class State(BaseModel):
    version: int
    wall_unix_s: float
    t_s: float
    rx_count: int
    rx_age_s: float | None
    source: SourceInfo
    replay: ReplayInfo | None
    vehicle: Vehicle
    alarm: AlarmNow
    alarm_count: int
    line: Line | None
    calibration_in_use: bool
    wizard: Wizard
    events: list[Event]


class Alarm(BaseModel):
    kind: str
    evidence: list[str]
    start_s: float
    end_s: float | None
    peak: float | None


class SourceRequest(BaseModel):
    connect: str | None = Field(None, description="pymavlink connection string, e.g. udpin:127.0.0.1:14550")
    recording: str | None = Field(None, description="a file name from GET /api/recordings")
    speed: float = 1.0
    loop: bool = False


class ReplayStart(BaseModel):
    recording: str
    speed: float = 1.0
    loop: bool = False


class Seek(BaseModel):
    t_s: float


class Speed(BaseModel):
    speed: float


class Pause(BaseModel):
    paused: bool = True


class Ok(BaseModel):
    ok: bool = True
    message: str = ""


# ----------------------------------------------------------------------------------- pushing

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


# ----------------------------------------------------------------------------------- app

def create_app(session: Session, viser_port: int | None = None) -> FastAPI:
    started = time.time()
    pusher = Pusher()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        pusher.loop = asyncio.get_running_loop()
        session.add_listener(pusher.notify)
        yield
        session.remove_listener(pusher.notify)

    app = FastAPI(title="MagStation", version="0.1.0", lifespan=lifespan,
                  description="Magnetometer calibration, heading integrity and flight replay.")
    app.state.session = session
    app.state.pusher = pusher

    def guard(fn, *args):
        try:
            return fn(*args)
        except SessionError as err:
            raise HTTPException(status_code=400, detail=str(err)) from err

    @app.get("/api/health", response_model=Health, tags=["station"])
    def health() -> Health:
        snap = session.snapshot()
        return Health(uptime_s=round(time.time() - started, 1), source=snap["source"]["kind"],
                      viser_port=viser_port, clients=len(pusher.clients))

    @app.get("/api/state", response_model=State, tags=["station"])
    def state() -> dict:
        return session.snapshot()

    @app.get("/api/recordings", response_model=list[str], tags=["source"])
    def recordings() -> list[str]:
        return session.recording_names()

    @app.post("/api/source", response_model=SourceInfo, tags=["source"],
              summary="Choose the source: a live connection string or a recording name")
    def choose_source(req: SourceRequest) -> dict:
        if (req.connect is None) == (req.recording is None):
            raise HTTPException(400, detail="give exactly one of 'connect' or 'recording'")
        if req.connect is not None:
            guard(session.connect, req.connect)
        else:
            path = guard(session.resolve_recording, req.recording)
            guard(session.start_replay, path, req.speed, req.loop)
        return session.snapshot()["source"]

    @app.post("/api/source/stop", response_model=Ok, tags=["source"])
    def stop_source() -> Ok:
        session.stop()
        return Ok(message="stopped")

    @app.post("/api/replay/start", response_model=ReplayInfo, tags=["replay"])
    def replay_start(req: ReplayStart) -> dict:
        path = guard(session.resolve_recording, req.recording)
        guard(session.start_replay, path, req.speed, req.loop)
        return session.snapshot()["replay"]

    @app.post("/api/replay/stop", response_model=Ok, tags=["replay"])
    def replay_stop() -> Ok:
        if session.replay is None:
            raise HTTPException(400, detail="no replay running")
        session.stop()
        return Ok(message="replay stopped")

    @app.post("/api/replay/pause", response_model=ReplayInfo, tags=["replay"])
    def replay_pause(req: Pause) -> dict:
        guard(session.replay_pause, req.paused)
        return session.snapshot()["replay"]

    @app.post("/api/replay/seek", response_model=ReplayInfo, tags=["replay"])
    def replay_seek(req: Seek) -> dict:
        guard(session.replay_seek, req.t_s)
        return session.snapshot()["replay"]

    @app.post("/api/replay/speed", response_model=ReplayInfo, tags=["replay"])
    def replay_speed(req: Speed) -> dict:
        guard(session.replay_speed, req.speed)
        return session.snapshot()["replay"]

    @app.get("/api/calibration", response_model=Wizard, tags=["calibration"])
    def calibration() -> dict:
        return session.snapshot()["wizard"]

    @app.post("/api/calibration/start", response_model=Wizard, tags=["calibration"])
    def calibration_start() -> dict:
        session.wizard_start()
        return session.snapshot()["wizard"]

    @app.post("/api/calibration/reset", response_model=Wizard, tags=["calibration"])
    def calibration_reset() -> dict:
        session.wizard_reset()
        return session.snapshot()["wizard"]

    @app.post("/api/calibration/finish", response_model=Wizard, tags=["calibration"],
              summary="Fit now with what was collected (skip the remaining steps)")
    def calibration_finish() -> dict:
        guard(session.wizard_finish_now)
        return session.snapshot()["wizard"]

    @app.post("/api/calibration/accept", response_model=ParamWrite, tags=["calibration"],
              summary="Use the result; on a live link write it to the vehicle (confirmed by echo)")
    def calibration_accept() -> dict:
        return guard(session.wizard_accept)

    @app.get("/api/calibration/params", tags=["calibration"], response_class=PlainTextResponse,
             summary="The result as an autopilot .param file")
    def calibration_params(autopilot: Literal["ardupilot", "px4"] | None = Query(None)) -> Response:
        snap = session.snapshot()
        result = snap["wizard"]["result"]
        if not result or result.get("status") != "ok":
            raise HTTPException(404, detail="no successful calibration result yet")
        ap = autopilot or snap["source"]["autopilot"] or "ardupilot"
        params = result.get(f"{ap}_params") or {}
        if not params:
            raise HTTPException(404, detail=f"the result has no {ap} parameters")
        from groundstation.io.params import format_param_file
        text = format_param_file(params)
        return PlainTextResponse(text, headers={
            "Content-Disposition": f'attachment; filename="magstation-{ap}.param"'})

    @app.get("/api/line", response_model=Line | None, tags=["line"])
    def get_line() -> dict | None:
        return session.snapshot()["line"]

    @app.put("/api/line", response_model=Line, tags=["line"], summary="Set the preset line by coordinates")
    def put_line(line: Line) -> dict:
        return guard(session.set_line, line.a, line.b, "user")

    @app.post("/api/line/from-mission", response_model=Line, tags=["line"],
              summary="Set the preset line from the first and last mission waypoints")
    def line_from_mission() -> dict:
        return guard(session.line_from_mission)

    @app.get("/api/alarms", response_model=list[Alarm], tags=["alarms"])
    def alarms() -> list[dict]:
        return session.alarm_list()

    @app.get("/api/session.tlog", tags=["downloads"], response_class=FileResponse)
    def session_tlog() -> FileResponse:
        path = guard(session.session_tlog)
        return FileResponse(path, media_type="application/octet-stream", filename=path.name)

    @app.get("/api/analysis", tags=["downloads"], summary="analyze report (issue 5) of this session")
    def analysis() -> dict:
        try:
            report, _ = guard(session.analysis)
        except ImportError as err:
            raise HTTPException(503, detail=f"analysis not available: {err}") from err
        return report

    @app.get("/api/analysis.csv", tags=["downloads"], response_class=PlainTextResponse)
    def analysis_csv() -> Response:
        try:
            _, table = guard(session.analysis)
            from groundstation.jobs.analyze import write_csv
        except ImportError as err:
            raise HTTPException(503, detail=f"analysis not available: {err}") from err
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "analysis.csv"
            write_csv(path, table)
            text = path.read_text()
        return PlainTextResponse(text, media_type="text/csv", headers={
            "Content-Disposition": 'attachment; filename="magstation-analysis.csv"'})

    @app.websocket("/ws")
    async def ws(websocket: WebSocket) -> None:
        """State pushes.  Flow control: the client answers each message with any short text
        ("ack"); at most MAX_INFLIGHT unanswered messages are outstanding, so a slow client gets
        the newest state when it is ready instead of a growing backlog of old ones.  A client
        that never answers still gets one message per ACK_TIMEOUT_S."""
        await websocket.accept()
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
                await websocket.send_text(session.snapshot_json())
                state["inflight"] += 1
                last = time.monotonic()
        except (WebSocketDisconnect, RuntimeError, ConnectionError):
            pass
        finally:
            pusher.clients.discard(ev)
            read_task.cancel()

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/index.html")

    app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    return app


# ----------------------------------------------------------------------------------- running

class Station:
    """Session + viser scene + uvicorn in this process; ``start()`` runs uvicorn in a thread
    (tests, benchmarks), ``run()`` blocks (the CLI)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8000, viser_port: int | None = 8080,
                 recordings_dir: str | Path = DEFAULT_RECORDINGS, allow_remote: bool = False,
                 record_live: bool = True) -> None:
        import uvicorn

        if host not in LOOPBACK and not allow_remote:
            raise ValueError(f"refusing to bind {host}: pass allow_remote=True to listen beyond loopback")
        self.session = Session(recordings_dir, record_live=record_live)
        self.scene = None
        if viser_port is not None:
            from groundstation.station.scene import Scene
            self.scene = Scene(self.session, host=host, port=viser_port)
        self.viser_port = self.scene.port if self.scene else None
        self.app = create_app(self.session, self.viser_port)
        self.server = uvicorn.Server(uvicorn.Config(self.app, host=host, port=port, log_level="warning",
                                                    ws_ping_interval=None))
        self.host = host
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


def serve(connect: str | None, replay: Path | None, speed: float = 1.0, host: str = "127.0.0.1",
          port: int = 8000, viser_port: int = 8080, allow_remote: bool = False) -> None:
    """Run the station until Ctrl-C: live link ``connect`` or replay ``replay`` (the bundled
    demo loops)."""
    station = Station(host=host, port=port, viser_port=viser_port, allow_remote=allow_remote)
    if connect:
        station.session.connect(connect)
    elif replay is not None:
        replay = Path(replay)
        loop = replay.resolve().parent == DEFAULT_RECORDINGS.resolve() and replay.name == "demo.tlog"
        station.session.start_replay(replay, speed, loop=loop)
    print(f"MagStation: web page http://{host}:{station.port if station.server.started else port}/ "
          f"(calibration: /calibrate.html, API: /docs), 3-D view http://{host}:{station.viser_port}/")
    station.run()
