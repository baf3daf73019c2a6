"""Who may drive the station: Host allow-list, same-origin proof for writes, the remote token,
request-body limits, and the same checks on the 3-D view's WebSocket.

Rules (README, "API and security"):
  * Every HTTP request and WebSocket must name an allowed host (``Host`` header): loopback names,
    the bound host and ``StationSettings.allowed_hosts``.  This closes DNS rebinding.
  * No /api request a browser sends from another site is served (``Sec-Fetch-Site`` cross-site or
    same-site, or a foreign ``Origin``: 403).
  * A state-changing request (anything but GET/HEAD/OPTIONS) that comes from a browser (it carries
    ``Origin``, ``Referer`` or ``Sec-Fetch-Site``) must come from the station's own origin *and*
    carry the page token in ``X-MagStation-Token``, which our pages read from ``/api/page-token``
    (a cross-origin page can neither read it nor send the header without a CORS grant, and no
    CORS grant is ever given).  Requests without any of those headers are scripts (curl, Python):
    accepted, as only loopback can reach a station that is not in remote mode.
  * A WebSocket with an ``Origin`` must come from the station's own origin (``null`` is refused).
  * Remote mode (``allow_remote``): every request needs the access token, as
    ``Authorization: Bearer TOKEN``, the HttpOnly SameSite=Strict cookie that ``?token=TOKEN`` on a
    first GET sets, or ``?token=`` on a WebSocket URL.
  * Request bodies are bounded per path prefix (``StationSettings.body_limits``): 413 beyond.
  * Slow clients (``server_options``, ``StationSettings.connection_limits``): a request's line and
    headers must arrive within ``header_timeout_s``; a client holds at most ``max_per_client``
    connections and the station at most ``connection_cap`` in all; to make room the oldest
    connection not inside a request is closed, one that never completed a request (never showed
    a token) first, so a tokened request gets through however many slow sockets are open.
"""
from __future__ import annotations

import http.cookies
import secrets
import socket
from dataclasses import dataclass
from typing import Annotated, Mapping
from urllib.parse import parse_qsl, quote, urlencode, urlsplit

from fastapi import APIRouter, Header, HTTPException, Request
from fastapi.responses import JSONResponse
from starlette.datastructures import Headers

from groundstation.station.settings import LOOPBACK_HOSTS, WILDCARD_HOSTS, ConnectionLimits, StationSettings

__all__ = ["AccessPolicy", "StationGuard", "require_operator", "protect_viser", "router",
           "TOKEN_HEADER", "TOKEN_COOKIE", "PAGE_TOKEN_PATH", "server_options", "connection_cap"]

TOKEN_HEADER = "X-MagStation-Token"
TOKEN_COOKIE = "magstation_token"
PAGE_TOKEN_PATH = "/api/page-token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}
SECURITY_HEADERS = ((b"x-frame-options", b"DENY"), (b"content-security-policy", b"frame-ancestors 'none'"),
                    (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"same-origin"))


def split_host(host: str) -> tuple[str, int | None] | None:
    """``Host`` header -> (lower-case name, port or None); None when malformed."""
    host = host.strip().lower()
    try:
        parts = urlsplit("//" + host)
        name, port = parts.hostname, parts.port
    except ValueError:
        return None
    if not name or parts.username is not None or parts.path or parts.query or parts.fragment:
        return None
    return name, port


def _origin_tuple(origin: str) -> tuple[str, str, int] | None:
    try:
        parts = urlsplit(origin.strip())
        scheme = parts.scheme.lower()
        if scheme not in ("http", "https") or not parts.hostname:
            return None
        return scheme, parts.hostname.lower(), parts.port or DEFAULT_PORTS[scheme]
    except ValueError:
        return None


def _this_machine_names() -> set[str]:
    names = {socket.gethostname().lower(), socket.getfqdn().lower()}
    try:
        names |= {info[4][0] for info in socket.getaddrinfo(socket.gethostname(), None)}
    except OSError:
        pass
    return {n for n in names if n}


@dataclass(frozen=True)
class AccessPolicy:
    """The checks of one running station (built from its settings by ``from_settings``).

    hosts:        allowed Host-header names (no ports).
    remote:       remote mode: every request needs ``access_token``.
    access_token: the remote secret (None in loopback mode).
    page_token:   the per-run token our pages send in ``X-MagStation-Token``.
    scheme:       "http" or "https".
    settings:     the StationSettings (body limits).
    """
    hosts: frozenset[str]
    remote: bool
    access_token: str | None
    page_token: str
    scheme: str
    settings: StationSettings

    @classmethod
    def from_settings(cls, settings: StationSettings) -> "AccessPolicy":
        hosts = set(LOOPBACK_HOSTS) | set(settings.allowed_hosts)
        if settings.host in WILDCARD_HOSTS:
            if settings.allow_remote:
                hosts |= _this_machine_names()
        else:
            hosts.add(settings.host.lower())
        return cls(frozenset(hosts), settings.allow_remote, settings.access_token,
                   secrets.token_urlsafe(32), settings.scheme, settings)

    def host_allowed(self, host_header: str | None) -> bool:
        parsed = split_host(host_header or "")
        return parsed is not None and parsed[0] in self.hosts

    def same_origin(self, origin: str | None, host_header: str | None, scheme: str | None = None) -> bool:
        """``origin`` (an Origin header or a Referer URL) is this request's own origin."""
        own = split_host(host_header or "")
        theirs = _origin_tuple(origin or "")
        if own is None or theirs is None:
            return False
        scheme = {"ws": "http", "wss": "https"}.get(scheme or self.scheme, scheme or self.scheme)
        return theirs == (scheme, own[0], own[1] or DEFAULT_PORTS[scheme]) and own[0] in self.hosts

    def token_ok(self, presented: str | None) -> bool:
        return bool(presented) and self.access_token is not None and \
            secrets.compare_digest(presented.encode(), self.access_token.encode())

    def presented_token(self, headers: Mapping[str, str], query: str) -> tuple[str | None, bool]:
        """(token, came from ?token=) from the Authorization header, the cookie or the query."""
        auth = headers.get("authorization", "")
        if auth[:7].lower() == "bearer ":
            return auth[7:].strip(), False
        cookie = http.cookies.SimpleCookie()
        try:
            cookie.load(headers.get("cookie", ""))
        except http.cookies.CookieError:
            pass
        if TOKEN_COOKIE in cookie:
            return cookie[TOKEN_COOKIE].value, False
        for key, value in parse_qsl(query):
            if key == "token":
                return value, True
        return None, False

    def websocket_refusal(self, headers: Mapping[str, str], query: str, scheme: str) -> str | None:
        """Why a WebSocket handshake is refused (None: accept)."""
        if not self.host_allowed(headers.get("host")):
            return "invalid Host header"
        origin = headers.get("origin")
        if origin is not None and not self.same_origin(origin, headers.get("host"), scheme):
            return f"WebSocket from another origin refused ({origin[:80]})"
        if self.remote and not self.token_ok(self.presented_token(headers, query)[0]):
            return "remote mode: token required"
        return None


def _size(n: int) -> str:
    return f"{n / (1 << 20):g} MiB" if n >= 1 << 20 else f"{n / 1024:g} KiB"


class _BodyTooLarge(HTTPException):
    def __init__(self, limit: int) -> None:
        super().__init__(413, detail=f"request body larger than {_size(limit)}")


class StationGuard:
    """ASGI middleware: Host allow-list, CORS preflights refused, remote-mode token, WebSocket
    Origin, request-body limits and security headers (no framing, no sniffing)."""

    def __init__(self, app, policy: AccessPolicy) -> None:
        self.app = app
        self.policy = policy

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = Headers(scope=scope)
        query = scope.get("query_string", b"").decode("latin-1")
        if scope["type"] == "websocket":
            why = self.policy.websocket_refusal(headers, query, scope.get("scheme", "ws"))
            if why is not None:
                return await send({"type": "websocket.close", "code": 1008, "reason": why[:120]})
            return await self.app(scope, receive, send)
        if not self.policy.host_allowed(headers.get("host")):
            return await _json(scope, send, 400, "invalid Host header (see --allowed-host)")
        if scope["method"] == "OPTIONS" and "access-control-request-method" in headers:
            return await _json(scope, send, 403, "cross-origin requests are not allowed")
        if self.policy.remote:
            token, from_query = self.policy.presented_token(headers, query)
            if not self.policy.token_ok(token):
                return await _json(scope, send, 401, "authentication required: open the address printed at "
                                   "start (with ?token=...) or send Authorization: Bearer TOKEN",
                                   [(b"www-authenticate", b"Bearer")])
            if from_query and scope["method"] in ("GET", "HEAD"):
                return await self._set_cookie_and_redirect(scope, query, send)
        await self._bounded(scope, receive, _with_security_headers(send), headers)

    async def _bounded(self, scope, receive, send, headers: Headers) -> None:
        limit = self.policy.settings.body_limit_for(scope["path"])
        declared = headers.get("content-length")
        if declared is not None and (not (declared.isascii() and declared.isdigit()) or int(declared) > limit):
            return await _json(scope, send, 413, f"request body larger than {_size(limit)}")
        received = 0
        started = False

        async def counting_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise _BodyTooLarge(limit)
            return message

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except _BodyTooLarge as err:
            if started:
                raise
            await _json(scope, send, 413, err.detail)

    async def _set_cookie_and_redirect(self, scope, query: str, send) -> None:
        rest = urlencode([(k, v) for k, v in parse_qsl(query, keep_blank_values=True) if k != "token"])
        # never //other.host nor /\other.host (browsers read a backslash as a slash): the path
        # is percent-encoded (a backslash becomes %5C) and starts with exactly one slash
        path = quote(scope["path"].lstrip("/\\"), safe="/:@!$&'()*+,;=-._~")
        location = "/" + path + ("?" + rest if rest else "")
        cookie = f"{TOKEN_COOKIE}={self.policy.access_token}; HttpOnly; SameSite=Strict; Path=/"
        if self.policy.scheme == "https":
            cookie += "; Secure"
        await send({"type": "http.response.start", "status": 303, "headers": [
            (b"location", location.encode("latin-1", "replace")), (b"set-cookie", cookie.encode()),
            (b"cache-control", b"no-store"), (b"content-length", b"0"), *SECURITY_HEADERS]})
        await send({"type": "http.response.body", "body": b""})


def _with_security_headers(send):
    async def wrapped(message):
        if message["type"] == "http.response.start":
            message = {**message, "headers": [*message.get("headers", []), *SECURITY_HEADERS]}
        await send(message)
    return wrapped


async def _json(scope, send, status: int, detail: str, extra: list | None = None) -> None:
    response = JSONResponse({"detail": detail}, status_code=status)
    response.raw_headers.extend([*SECURITY_HEADERS, *(extra or [])])
    await response(scope, _no_receive, send)


async def _no_receive():
    return {"type": "http.disconnect"}


# ------------------------------------------------------------------------------ the dependency

PageToken = Annotated[str | None, Header(alias=TOKEN_HEADER, description=(
    f"Browsers only: the token from GET {PAGE_TOKEN_PATH}, on every state-changing request. "
    "Scripts that send no Origin header leave it out."))]


def require_operator(request: Request, token: PageToken = None) -> None:
    """FastAPI dependency on the /api routers.  Any request a browser sends from another site
    (``Sec-Fetch-Site`` cross-site/same-site, or a foreign ``Origin``) is refused; a
    state-changing one from a browser must also carry the page token.  Scripts (no Origin,
    Referer or Sec-Fetch-Site) pass.  Raises HTTPException 403 with the reason."""
    policy: AccessPolicy = request.app.state.access
    h = request.headers
    origin, referer, site = h.get("origin"), h.get("referer"), h.get("sec-fetch-site")
    host, scheme = h.get("host"), request.url.scheme
    if site is not None and site not in ("same-origin", "none"):
        raise HTTPException(403, detail=f"cross-site request refused (Sec-Fetch-Site: {site[:20]})")
    if origin is not None and not policy.same_origin(origin, host, scheme):
        raise HTTPException(403, detail=f"cross-origin request refused: Origin {origin[:80]} is not this station")
    if request.method in SAFE_METHODS:
        return
    if origin is None and referer is not None and not policy.same_origin(referer, host, scheme):
        raise HTTPException(403, detail="cross-origin request refused: Referer is not this station")
    if origin is None and referer is None and site is None:
        return                                      # a script, not a browser
    if not token or not secrets.compare_digest(token.encode(), policy.page_token.encode()):
        raise HTTPException(403, detail=f"missing or wrong {TOKEN_HEADER} header (the station's pages "
                            f"send it, from GET {PAGE_TOKEN_PATH}; scripts send no Origin header)")


router = APIRouter(prefix="/api", tags=["station"])


@router.get("/page-token", summary="The token our pages echo in X-MagStation-Token on writes")
def page_token(request: Request) -> JSONResponse:
    """Behind ``require_operator`` like every /api route: never answered to another site."""
    policy: AccessPolicy = request.app.state.access
    return JSONResponse({"token": policy.page_token, "header": TOKEN_HEADER}, headers={
        "Cache-Control": "no-store", "Cross-Origin-Resource-Policy": "same-origin"})


# ------------------------------------------------------------------------------ the 3-D view

def protect_viser(server, policy: AccessPolicy) -> None:
    """Apply the WebSocket rules (Host, Origin, remote token) to a ``viser.ViserServer``.

    viser runs its own ``websockets`` server with no handshake hook we can pass in, but its
    connection handler awaits every registered connect callback, in order, before it starts
    sending anything, and keeps the raw connection (with the handshake request) in
    ``_live_connections``.  Our callback goes first and closes a refused connection (1008) before
    a single scene message is sent.  Clients that connected before the guard was installed are
    disconnected (they reconnect through it).  Raises RuntimeError when this viser build lacks
    those internals, so a 3-D view is never served unguarded.
    """
    ws = getattr(server, "_websock_server", None)
    callbacks = getattr(ws, "_client_connect_cb", None)
    if ws is None or not isinstance(callbacks, list) or not isinstance(getattr(ws, "_live_connections", None), dict):
        raise RuntimeError("this viser version cannot be guarded (no connect hook); run without the 3-D view")

    async def guard(client) -> None:
        connection = ws._live_connections.get(client.client_id)
        request = getattr(connection, "request", None)
        if request is None:
            return
        headers = {k.lower(): v for k, v in request.headers.raw_items()}
        query = urlsplit(request.path).query
        why = policy.websocket_refusal(headers, query, "http")
        if why is not None:
            await connection.close(1008, why[:120])

    callbacks.insert(0, guard)
    ws.disconnect_all_clients()


# ------------------------------------------------------------------------------ slow clients

CONNECTION_RESERVE_FILES = 96   # descriptors kept for the station's files, the 3-D view, the relay
_REFUSED_BODY = b"too many open connections: try again"
REFUSED_RESPONSE = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\nretry-after: 1\r\n"
                    b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(_REFUSED_BODY), _REFUSED_BODY))


def connection_cap(limits: ConnectionLimits, open_files: int | None = None) -> int:
    """Open HTTP connections allowed in all: ``limits.max_connections`` when set, else half of what
    the open-file limit (RLIMIT_NOFILE, or ``open_files``) leaves after CONNECTION_RESERVE_FILES
    (each connection is a descriptor; the other half is for WebSockets, logs and the relay),
    between 8 and ``limits.max_connections_cap``."""
    if limits.max_connections is not None:
        return limits.max_connections
    if open_files is None:
        try:
            import resource
            soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
            open_files = soft if soft != resource.RLIM_INFINITY else 1 << 20
        except (ImportError, OSError, ValueError):       # Windows: no such limit
            open_files = 1 << 20
    return max(8, min(limits.max_connections_cap, (open_files - CONNECTION_RESERVE_FILES) // 2))


class ConnectionBook:
    """The open HTTP connections of one server, in the order they came, and by client address.
    Used on the server's event loop only.  Counts what it closed: ``shed`` (room made for a new
    connection), ``refused`` (no room: every connection was inside a request), ``timed_out``
    (headers too slow)."""

    def __init__(self, limits: ConnectionLimits, cap: int) -> None:
        self.limits = limits
        self.cap = cap
        self.open: dict = {}                       # protocol -> None, oldest first
        self.by_client: dict[str, dict] = {}
        self.shed = self.refused = self.timed_out = 0

    def admit(self, conn) -> bool:
        """Count a new connection, making room by closing the oldest connection not inside a
        request (one that never completed a request first: it showed no token) of the same client,
        then of all.  False: no room (the caller refuses it)."""
        peers = self.by_client.get(conn.client_key, {})
        if len(peers) >= self.limits.max_per_client and not self._shed_one(peers):
            self.refused += 1
            return False
        if len(self.open) >= self.cap and not self._shed_one(self.open):
            self.refused += 1
            return False
        self.open[conn] = None
        self.by_client.setdefault(conn.client_key, {})[conn] = None
        return True

    def _shed_one(self, conns: dict) -> bool:
        victim = next((c for c in conns if c.idle and not c.served), None) or \
            next((c for c in conns if c.idle), None)
        if victim is None:
            return False
        self.discard(victim)
        victim.transport.close()
        self.shed += 1
        return True

    def discard(self, conn) -> None:
        self.open.pop(conn, None)
        peers = self.by_client.get(conn.client_key)
        if peers is not None:
            peers.pop(conn, None)
            if not peers:
                del self.by_client[conn.client_key]


def server_options(limits: ConnectionLimits) -> dict:
    """uvicorn.Config options bounding slow clients: the HTTP protocol ``GuardedHttpProtocol``
    (uvicorn's h11 protocol with a header timeout and the connection bounds of ``limits``), the
    keep-alive time and h11's largest request head.

    Why not uvicorn's own options: ``limit_concurrency`` answers 503 to everyone once slow
    clients hold the connections (the operator too), ``timeout_keep_alive`` starts only after a
    response and stops at every byte received, so a client sending a header line every few
    seconds held its connection (and a descriptor) for ever."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    book = ConnectionBook(limits, connection_cap(limits))

    class GuardedHttpProtocol(H11Protocol):
        """One HTTP connection: its request line and headers must come within
        ``header_timeout_s`` of the connection or of its previous response, and it is counted
        in ``book`` (which may close it to make room while it is not inside a request)."""
        connections = book

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self.client_key = self.client[0] if self.client else ""
            self.idle, self.served, self._header_timer = True, 0, None
            if not book.admit(self):
                transport.write(REFUSED_RESPONSE)
                transport.close()
                return
            self._arm_header_timer()

        def handle_events(self) -> None:
            cycle = self.cycle
            super().handle_events()
            if self.cycle is not cycle:           # a request's line and headers are in
                self.idle = False
                self._disarm_header_timer()

        def on_response_complete(self) -> None:
            self.served += 1
            self.idle = True
            if not self.transport.is_closing():
                self._arm_header_timer()
            super().on_response_complete()        # may start a pipelined request (handle_events)

        def handle_websocket_upgrade(self, event) -> None:
            self.idle = False                     # a WebSocket now: StationGuard checks it
            self._disarm_header_timer()
            book.discard(self)
            super().handle_websocket_upgrade(event)

        def connection_lost(self, exc) -> None:
            self._disarm_header_timer()
            book.discard(self)
            super().connection_lost(exc)

        def _arm_header_timer(self) -> None:
            self._disarm_header_timer()
            self._header_timer = self.loop.call_later(limits.header_timeout_s, self._headers_too_slow)

        def _disarm_header_timer(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _headers_too_slow(self) -> None:
            self._header_timer = None
            if self.idle and not self.transport.is_closing():
                book.timed_out += 1
                book.discard(self)
                self.transport.close()

    return {"http": GuardedHttpProtocol, "timeout_keep_alive": limits.keep_alive_s,
            "h11_max_incomplete_event_size": limits.max_header_bytes}
