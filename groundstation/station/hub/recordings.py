"""The recordings folder: the logs the station can replay, what is in each, uploads, new sessions.

Every file the station reads or writes is in one folder (``StationSettings.recordings_dir``) and
is named by the station: a request names a file of the folder, never a path.  ``info()`` describes
each log (duration, date, size, vehicle, compasses), read once per file version (modification
time and size) and cached.  ``store_upload`` takes a log from the browser: size-limited, checked
by suffix and by content (the format's own magic bytes), stored under a generated name, then
read once; a file that does not read is removed and refused.  ``LazyRecording`` records a live
link to ``session-*.tlog``, creating the file with the first packet.
"""
from __future__ import annotations

import os
import re
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from groundstation.io.errors import IngestError
from groundstation.io.mavlink import TlogWriter

__all__ = ["RecordingsFolder", "LazyRecording", "RECORDING_SUFFIXES", "UploadError", "sniff_log_type",
           "vehicle_type", "compass_count"]

RECORDING_SUFFIXES = (".tlog", ".bin", ".ulg", ".csv")
ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95"
MAV_TYPES = {1: "fixed wing", 2: "quadrotor", 3: "coaxial", 4: "helicopter", 10: "ground rover", 11: "boat",
             12: "submarine", 13: "hexarotor", 14: "octorotor", 15: "tricopter", 19: "VTOL", 20: "VTOL",
             21: "VTOL tiltrotor", 22: "VTOL", 23: "VTOL tailsitter", 24: "VTOL tiltwing"}


MAX_NAME_TRIES = 10_000
UNREAD = {"duration_s": None, "start_unix_s": None, "autopilot": None, "vehicle": None, "compasses": None,
          "error": None}


class UploadError(Exception):
    """An upload the station refuses (wrong type, unreadable, too large: ``too_large``)."""

    def __init__(self, message: str, too_large: bool = False) -> None:
        super().__init__(message)
        self.too_large = too_large


def sniff_log_type(head: bytes) -> str | None:
    """The log format the first bytes say (".tlog", ".bin", ".ulg", ".csv") or None."""
    if head.startswith(ULOG_MAGIC):
        return ".ulg"
    if head.startswith(DATAFLASH_MAGIC):
        return ".bin"
    if len(head) >= 10 and head[8] in (0xFD, 0xFE):
        unix = int.from_bytes(head[:8], "big") * 1e-6
        if 946684800.0 < unix < 4102444800.0:       # 2000..2100
            return ".tlog"
    try:
        first = head.decode("utf-8").splitlines()[0] if head else ""
    except UnicodeDecodeError:
        return None
    if "," in first and first.isprintable():
        return ".csv"
    return None


def vehicle_type(log) -> str:
    """Vehicle type from the log's parameters (PX4 MAV_TYPE, ArduPilot's per-vehicle
    parameters) or its HEARTBEAT type; "unknown" when nothing says."""
    p = log.params
    if "MAV_TYPE" in p:
        return MAV_TYPES.get(int(p["MAV_TYPE"]), f"MAV_TYPE {int(p['MAV_TYPE'])}")
    if log.autopilot == "ardupilot":
        if "FRAME_CLASS" in p or "FRAME" in p:
            return "multicopter"
        if "Q_ENABLE" in p or "ARSPD_TYPE" in p or "TRIM_ARSPD_CM" in p:
            return "plane"
        if "CRUISE_SPEED" in p:
            return "rover"
    return getattr(log, "_heartbeat_type", None) or "unknown"


def compass_count(log) -> int:
    """Compasses the autopilot has configured (ArduPilot COMPASS_DEV_ID*, PX4 CAL_MAGn_ID), else
    1 when the log has magnetometer samples."""
    p = log.params
    ap = [p.get(k) for k in ("COMPASS_DEV_ID", "COMPASS_DEV_ID2", "COMPASS_DEV_ID3")]
    px4 = [p.get(f"CAL_MAG{n}_ID") for n in range(4)]
    for ids in (ap, px4):
        if any(v is not None for v in ids):
            return sum(1 for v in ids if v)
    return 1 if len(log.mag) else 0


def _tlog_heartbeat_type(path: Path) -> str | None:
    """The vehicle's MAV_TYPE from the first non-GCS HEARTBEAT in the first 64 kB of a .tlog."""
    from groundstation.io.logs import tlog_records

    with open(path, "rb") as f:
        head = f.read(65536)
    for _, msg in tlog_records(head, Counter()):
        if msg.get_type() == "HEARTBEAT" and msg.type != 6 and msg.autopilot != 8:
            return MAV_TYPES.get(int(msg.type), f"MAV_TYPE {int(msg.type)}")
    return None


class LazyRecording:
    """A live link's .tlog, created at the first packet (a link that hears nothing leaves no file)."""

    def __init__(self, new_path) -> None:
        self._new_path = new_path
        self.writer: TlogWriter | None = None
        self.path: Path | None = None

    def write_packet(self, packet: bytes, unix_s: float) -> None:
        if self.writer is None:
            self.path = self._new_path()
            self.writer = TlogWriter(self.path)
        self.writer.write_packet(packet, unix_s)

    def flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


class RecordingsFolder:
    """The one folder of logs (see module docstring).  Thread-safe."""

    def __init__(self, directory: Path, max_upload_bytes: int) -> None:
        self.dir = Path(directory).resolve()
        self.max_upload_bytes = int(max_upload_bytes)
        self._cache: dict[str, tuple[tuple, dict]] = {}
        self._reading: set[str] = set()          # names being read by another request
        self._lock = threading.Lock()

    def names(self) -> list[str]:
        """The recordings: regular files with a log suffix, no hidden files, no symlinks (a link
        in the folder, e.g. from an unpacked archive, may point anywhere: it is neither listed,
        read nor replayed)."""
        if not self.dir.is_dir():
            return []
        return sorted(p.name for p in self.dir.iterdir()
                      if p.suffix.lower() in RECORDING_SUFFIXES and not p.name.startswith(".")
                      and not p.is_symlink() and p.is_file())

    def resolve(self, name: str) -> Path:
        """A file name from the folder -> its path; anything else (paths, .., symlinks) is refused.
        Raises ValueError (not a name) or FileNotFoundError (no such recording)."""
        if not name or "/" in name or "\\" in name or name.startswith(".") or \
                Path(name).suffix.lower() not in RECORDING_SUFFIXES:
            raise ValueError(f"'{name}' is not a recording name (a file name from recordings/)")
        path = self.dir / name
        if path.is_symlink() or path.resolve().parent != self.dir or not path.is_file():
            raise FileNotFoundError(f"no recording named '{name}' (see GET /api/recordings)")
        return path

    def new_path(self, prefix: str, suffix: str, stem: str = "", content: Path | None = None) -> Path:
        """A fresh file PREFIX-YYYYmmdd-HHMMSS[-stem][_n]SUFFIX, created here and now so that no
        two callers get the same name: empty (exclusive create), or a hard link to ``content``
        (the finished upload; where the file system has no hard links, the name is created
        empty first and ``content`` moved onto it).  Another file is never replaced."""
        base = time.strftime(f"{prefix}-%Y%m%d-%H%M%S", time.gmtime()) + (f"-{stem}" if stem else "")
        for n in range(MAX_NAME_TRIES):
            path = self.dir / (f"{base}{suffix}" if n == 0 else f"{base}_{n}{suffix}")
            try:
                if content is not None:
                    try:
                        os.link(content, path)
                        return path
                    except FileExistsError:
                        raise
                    except OSError:          # no hard links here (FAT, some network shares)
                        pass
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
                if content is not None:
                    os.replace(content, path)            # onto the empty file made just now
                return path
            except FileExistsError:
                continue
        raise OSError(f"no free name for {base}{suffix} in {self.dir} after {MAX_NAME_TRIES} tries")

    def new_session_path(self) -> Path:
        self.dir.mkdir(parents=True, exist_ok=True)
        return self.new_path("session", ".tlog")

    # ------------------------------------------------------------------ metadata
    def info(self, recording_now: Path | None = None) -> list[dict]:
        """One entry per recording (see ``describe``); the live session being written and a
        log another request is reading right now are listed without being read."""
        out = []
        for name in self.names():
            path = self.dir / name
            try:
                st = path.stat()
            except OSError:
                continue
            base = {"name": name, "size_bytes": st.st_size, "modified_unix_s": round(st.st_mtime, 1)}
            live = recording_now is not None and path.resolve() == recording_now.resolve()
            entry = None if live else self._entry(name, path, (st.st_mtime_ns, st.st_size))
            out.append(dict(base, recording=live, **(entry or UNREAD)))
        return out

    def _entry(self, name: str, path: Path, key: tuple) -> dict | None:
        """The cached description of this file version, read now if needed (None: being read)."""
        with self._lock:
            cached = self._cache.get(name)
            if cached is not None and cached[0] == key:
                return cached[1]
            if name in self._reading:
                return None
            self._reading.add(name)
        try:
            entry = self.describe(path)
            with self._lock:
                self._cache[name] = (key, entry)
            return entry
        finally:
            with self._lock:
                self._reading.discard(name)

    @staticmethod
    def describe(path: Path) -> dict:
        """duration_s, start_unix_s, autopilot, vehicle, compasses, error of one log."""
        from groundstation.io.logs import read_log

        try:
            log = read_log(path)
        except IngestError as err:
            return {"duration_s": None, "start_unix_s": None, "autopilot": None, "vehicle": None,
                    "compasses": None, "error": str(err)}
        if path.suffix.lower() == ".tlog":
            try:
                log._heartbeat_type = _tlog_heartbeat_type(path)
            except OSError:
                pass
        return {"duration_s": round(log.duration_s, 1), "start_unix_s": log.start_unix_s,
                "autopilot": log.autopilot, "vehicle": vehicle_type(log), "compasses": compass_count(log),
                "error": None}

    # ------------------------------------------------------------------ uploads
    def begin_upload(self, filename: str) -> "Upload":
        """Start storing a browser upload (see module docstring).  Raises UploadError."""
        return Upload(self, filename)

    def _remember(self, path: Path, entry: dict) -> dict:
        st = path.stat()
        with self._lock:
            self._cache[path.name] = ((st.st_mtime_ns, st.st_size), entry)
        return dict(entry, name=path.name, size_bytes=st.st_size, modified_unix_s=round(st.st_mtime, 1),
                    recording=False)


class Upload:
    """One upload being stored: ``write`` each chunk (size limit), then ``finish`` (type check
    by suffix and content, generated name, read once) or ``abort``.  Raises UploadError."""

    def __init__(self, folder: RecordingsFolder, filename: str) -> None:
        self.folder = folder
        self.filename = Path(filename or "").name
        self.suffix = Path(self.filename).suffix.lower()
        if self.suffix not in RECORDING_SUFFIXES:
            raise UploadError(f"'{self.filename}': not a log type the station reads "
                              f"({', '.join(RECORDING_SUFFIXES)})")
        folder.dir.mkdir(parents=True, exist_ok=True)
        fd, part = tempfile.mkstemp(prefix=".upload-", suffix=".part", dir=folder.dir)   # exclusive
        self.part = Path(part)
        self._file = os.fdopen(fd, "wb")
        self.size = 0
        self.head = b""

    def write(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.size > self.folder.max_upload_bytes:
            self.abort()
            raise UploadError(f"upload larger than the limit of {self.folder.max_upload_bytes / 1e6:g} MB",
                              too_large=True)
        if len(self.head) < 4096:
            self.head += chunk[:4096 - len(self.head)]
        self._file.write(chunk)

    def abort(self) -> None:
        self._file.close()
        self.part.unlink(missing_ok=True)

    def finish(self) -> dict:
        """Check, name and read the stored file; returns its ``info`` entry."""
        self._file.close()
        try:
            if self.size == 0:
                raise UploadError(f"'{self.filename}' is empty")
            kind = sniff_log_type(self.head)
            if kind != self.suffix:
                raise UploadError(f"'{self.filename}' does not look like a {self.suffix} file"
                                  + (f" (its content is a {kind} log)" if kind else ""))
            stem = re.sub(r"[^A-Za-z0-9_-]+", "_", Path(self.filename).stem)[:40].strip("_") or "log"
            path = self.folder.new_path("upload", self.suffix, stem, content=self.part)
        finally:
            self.part.unlink(missing_ok=True)
        entry = RecordingsFolder.describe(path)
        if entry["error"]:
            path.unlink(missing_ok=True)
            raise UploadError(entry["error"].replace(path.name, self.filename))
        return self.folder._remember(path, entry)
