"""The station's settings: one frozen object, checked once at start."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from groundstation.paths import RECORDINGS_DIR

__all__ = ["StationSettings", "LOOPBACK_HOSTS"]

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class StationSettings:
    """How the station listens and where it keeps recordings.

    host / port:       the web page and API (loopback unless ``allow_remote``).
    viser_port:        the 3-D view (None: no 3-D view, e.g. in tests); binds the same host.
    allow_remote:      allow a non-loopback ``host``.
    recordings_dir:    live sessions are recorded here; replays and downloads come only from here.
    record_live:       record every live link to ``recordings_dir/session-*.tlog``.
    max_upload_mb:     the largest log the browser may upload to ``recordings_dir`` [MB, 10^6 bytes].

    Raises ValueError when a non-loopback host is asked for without ``allow_remote``.
    """
    host: str = "127.0.0.1"
    port: int = 8000
    viser_port: int | None = 8080
    allow_remote: bool = False
    recordings_dir: Path = field(default=RECORDINGS_DIR)
    record_live: bool = True
    max_upload_mb: float = 512.0

    def __post_init__(self) -> None:
        if self.host not in LOOPBACK_HOSTS and not self.allow_remote:
            raise ValueError(f"refusing to bind {self.host}: the station listens on loopback unless "
                             "--allow-remote is given")
        for name in ("port", "viser_port"):
            value = getattr(self, name)
            if value is not None and not 0 <= int(value) < 65536:
                raise ValueError(f"{name} must be 0..65535, got {value}")
        object.__setattr__(self, "recordings_dir", Path(self.recordings_dir).resolve())
