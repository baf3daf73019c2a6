"""The station's settings: one frozen object, checked once at start."""
from __future__ import annotations

import secrets
from dataclasses import dataclass, field
from pathlib import Path

from groundstation.paths import RECORDINGS_DIR

__all__ = ["StationSettings", "ConnectionLimits", "LOOPBACK_HOSTS", "WILDCARD_HOSTS", "DEFAULT_BODY_LIMITS"]

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
MIB = 1 << 20
# (path prefix, largest request body in bytes); the longest matching prefix wins.  JSON requests
# are small; the log upload route is bounded by ``max_upload_mb`` (UPLOAD_PATH).
UPLOAD_PATH = "/api/recordings/upload"
UPLOAD_OVERHEAD = 64 * 1024           # slack over max_upload_mb (the hub refuses beyond the limit itself)
DEFAULT_BODY_LIMITS: tuple[tuple[str, int], ...] = (("/", 1 * MIB),)


@dataclass(frozen=True)
class ConnectionLimits:
    """Bounds on the web port's HTTP connections (slow clients; ``security.GuardedHttpProtocol``).

    header_timeout_s:    a request's line and headers must arrive within this time of the
                         connection (or of the previous response) [s]; the connection is closed.
    keep_alive_s:        an idle kept-alive connection is closed after this time [s].
    max_header_bytes:    request line + headers larger than this get a 400 [bytes].
    max_per_client:      open connections per client address; beyond, the client's oldest one
                         not inside a request is closed (or the new one refused with a 503).
    max_connections:     open connections in all; None: from the open-file limit (see
                         ``security.connection_cap``), at most ``max_connections_cap``.
    """
    header_timeout_s: float = 10.0
    keep_alive_s: float = 5.0
    max_header_bytes: int = 16 * 1024
    max_per_client: int = 64
    max_connections: int | None = None
    max_connections_cap: int = 4096

    def __post_init__(self) -> None:
        least = {"header_timeout_s": 0.1, "keep_alive_s": 0.1, "max_header_bytes": 1024, "max_per_client": 1,
                 "max_connections": 1, "max_connections_cap": 8}
        for name, low in least.items():
            value = getattr(self, name)
            if value is not None and not value >= low:          # NaN fails too
                raise ValueError(f"connection limit {name} must be at least {low:g}, got {value}")


@dataclass(frozen=True)
class StationSettings:
    """How the station listens, who may drive it, and where it keeps recordings.

    host / port:       the web page and API (loopback unless ``allow_remote``).
    viser_port:        the 3-D view (None: no 3-D view, e.g. in tests).  It binds ``host``, except
                       with TLS, where it binds loopback (viser speaks no TLS; see README).
    allow_remote:      remote mode: a non-loopback ``host`` may be bound, every request needs
                       ``access_token`` (Bearer header or the cookie set by ``/?token=...``), and
                       requests may open live-link listeners on any interface.
    allowed_hosts:     extra Host-header names the station answers to (DNS names or addresses it
                       is reached by); loopback names, a specific ``host`` and, when binding all
                       interfaces, this machine's name are always allowed.
    access_token:      remote mode's secret; generated at start (secrets.token_urlsafe) unless given.
    tls_cert/tls_key:  PEM files: serve HTTPS/WSS through uvicorn (both or neither).
    body_limits:       (path prefix, bytes) pairs bounding request bodies; longest prefix wins.
    recordings_dir:    live sessions are recorded here; replays and downloads come only from here.
    record_live:       record every live link to ``recordings_dir/session-*.tlog``.
    max_upload_mb:     the largest log the browser may upload to ``recordings_dir`` [MB, 10^6 bytes].
    sysid:             the vehicle (MAVLink system id) to follow on a live link; None: the first heard.
    passive:           listen only: send nothing to the vehicle (no heartbeat, stream rates, writes).
    forward:           forwarding outputs (``udpout:HOST:PORT``, ``tcpin:127.0.0.1:PORT``): every
                       packet of the vehicle link goes to them, theirs go to the vehicle.
    signing_key:       MAVLink 2 signing key (32 bytes; ``groundstation.io.signing``), never shown.
    connection_limits: header time, keep-alive and connections per client (``ConnectionLimits``).

    Raises ValueError when a non-loopback host is asked for without ``allow_remote``, a port is
    out of range, only one of the TLS files is given or one is not a file, a body limit is not
    a positive size, a forwarding output is refused (``tcpin`` off loopback needs ``allow_remote``),
    the system id is not 1..255 or the signing key is not 32 bytes.
    """
    host: str = "127.0.0.1"
    port: int = 8000
    viser_port: int | None = 8080
    allow_remote: bool = False
    allowed_hosts: tuple[str, ...] = ()
    access_token: str | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    body_limits: tuple[tuple[str, int], ...] = DEFAULT_BODY_LIMITS
    recordings_dir: Path = field(default=RECORDINGS_DIR)
    record_live: bool = True
    max_upload_mb: float = 512.0
    sysid: int | None = None
    passive: bool = False
    forward: tuple[str, ...] = ()
    signing_key: bytes | None = field(default=None, repr=False)
    connection_limits: ConnectionLimits = field(default_factory=ConnectionLimits)
    params_in_force: tuple[tuple[str, float], ...] | None = None   # serve --params: values in force when a log has none
    params_label: str | None = None                                # the file's name, or "--assume-uncalibrated"

    def __post_init__(self) -> None:
        self._check_link()
        if self.host not in LOOPBACK_HOSTS and not self.allow_remote:
            raise ValueError(f"refusing to bind {self.host}: the station listens on loopback unless "
                             "--allow-remote is given")
        for name in ("port", "viser_port"):
            value = getattr(self, name)
            if value is not None and not 0 <= int(value) < 65536:
                raise ValueError(f"{name} must be 0..65535, got {value}")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("TLS needs both --tls-cert and --tls-key")
        for name in ("tls_cert", "tls_key"):
            value = getattr(self, name)
            if value is not None:
                if not Path(value).is_file():
                    raise ValueError(f"{name.replace('_', '-')} {value} is not a file")
                object.__setattr__(self, name, Path(value).resolve())
        if not self.body_limits or any(not p.startswith("/") or int(n) <= 0 for p, n in self.body_limits):
            raise ValueError("body_limits are (path prefix starting with '/', positive size) pairs")
        if self.allow_remote and not self.access_token:
            object.__setattr__(self, "access_token", secrets.token_urlsafe(32))
        if self.access_token is not None and len(self.access_token) < 16:
            raise ValueError("the access token must have at least 16 characters")
        object.__setattr__(self, "allowed_hosts", tuple(h.strip().lower() for h in self.allowed_hosts if h.strip()))
        object.__setattr__(self, "recordings_dir", Path(self.recordings_dir).resolve())

    def _check_link(self) -> None:
        from groundstation.io.errors import IngestError
        from groundstation.io.forward import parse_forward_url
        from groundstation.io.link import LinkOptions

        try:
            forward = tuple(parse_forward_url(u, listen_any=self.allow_remote).text for u in self.forward)
        except IngestError as err:
            raise ValueError(str(err)) from None
        if len(set(forward)) != len(forward):
            raise ValueError("a forwarding output is given twice")
        object.__setattr__(self, "forward", forward)
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")
        LinkOptions(self.sysid, self.passive, self.signing_key)     # checks the system id

    def link_options(self):
        """The live link's options (groundstation.io.link.LinkOptions)."""
        from groundstation.io.link import LinkOptions

        return LinkOptions(sysid=self.sysid, passive=self.passive, signing_key=self.signing_key)

    @property
    def tls(self) -> bool:
        return self.tls_cert is not None

    @property
    def scheme(self) -> str:
        return "https" if self.tls else "http"

    @property
    def viser_host(self) -> str:
        """Where the 3-D view binds: ``host``, but loopback when TLS is on (viser has no TLS)."""
        return "127.0.0.1" if self.tls else self.host

    def body_limit_for(self, path: str) -> int:
        """The largest request body accepted on ``path`` (longest matching prefix)."""
        limits = dict(self.body_limits)
        limits.setdefault(UPLOAD_PATH, int(self.max_upload_mb * 1e6) + UPLOAD_OVERHEAD)
        best = max((p for p in limits if path.startswith(p)), key=len, default=None)
        return limits[best] if best is not None else min(limits.values())
