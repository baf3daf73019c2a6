"""MAVLink 2 message signing: the key, and signing a pymavlink connection.

The secret key is 32 bytes.  From a passphrase it is SHA-256 of the passphrase (UTF-8), as
MAVProxy's ``signing setup PASSPHRASE`` and Mission Planner derive it.  A key file holds either
the 32 raw bytes, 64 hexadecimal digits, or a passphrase (its first line).  The key is never
printed or logged: ``key_id`` (the first 4 bytes of SHA-256 of the key, hex) tells keys apart.

When signing is on, outgoing packets are signed and incoming packets without a valid signature
are refused (not decoded, not recorded) and counted, except RADIO_STATUS, which SiK radios
inject unsigned (MAVProxy makes the same exception).
"""
from __future__ import annotations

import hashlib
import hmac
import os
import re
import stat
import struct
import types
from pathlib import Path

from .errors import IngestError

__all__ = ["SIGNING_KEY_BYTES", "key_from_passphrase", "read_key_file", "passphrase_from_env", "passphrase_variables",
           "key_id", "LinkSigning"]

SIGNING_KEY_BYTES = 32
MAX_KEY_FILE_BYTES = 4096
MAVLINK_MSG_ID_RADIO_STATUS = 109
_HEX64 = re.compile(rb"^[0-9a-fA-F]{64}$")


def key_from_passphrase(passphrase: str) -> bytes:
    """SHA-256 of the passphrase: the 32-byte secret key (MAVProxy's convention).

    Raises:
        IngestError: an empty passphrase.
    """
    if not passphrase:
        raise IngestError("the signing passphrase is empty")
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def read_key_file(path: str | Path) -> bytes:
    """The 32-byte key in a file: 32 raw bytes, 64 hex digits, or a passphrase on its first line.

    Raises:
        IngestError: missing, not a regular file, too large, or empty.
    """
    p = Path(path)
    try:
        info = p.stat()
    except OSError as err:
        raise IngestError(f"cannot read the signing key file {p}: {err.strerror or err}") from None
    if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_KEY_FILE_BYTES:
        raise IngestError(f"the signing key file {p} must be a small regular file")
    data = p.read_bytes()
    if len(data) == SIGNING_KEY_BYTES and not _HEX64.match(data.strip()):
        return data
    text = data.strip()
    if _HEX64.match(text):
        return bytes.fromhex(text.decode("ascii"))
    line = text.splitlines()[0].decode("utf-8", "replace").strip() if text else ""
    return key_from_passphrase(line)


def key_id(key: bytes) -> str:
    """A short public name of a key (never the key itself)."""
    return hashlib.sha256(key).hexdigest()[:8]


class LinkSigning:
    """Signs a pymavlink connection's outgoing packets and counts the refused incoming ones."""

    def __init__(self, key: bytes) -> None:
        if len(key) != SIGNING_KEY_BYTES:
            raise IngestError(f"a MAVLink signing key has {SIGNING_KEY_BYTES} bytes, not {len(key)}")
        self._key = bytes(key)
        self.key_id = key_id(self._key)
        self.unsigned_or_bad = 0        # every packet without a valid signature
        self._mav = None

    def __repr__(self) -> str:          # never shows the key
        return f"LinkSigning(key_id={self.key_id})"

    def install(self, conn, link_id: int = 0) -> None:
        """Sign ``conn`` (a pymavlink mavfile); the timestamp starts now (10 us since 2015)."""
        conn.setup_signing(self._key, sign_outgoing=True, allow_unsigned_callback=self._allow_unsigned,
                           link_id=link_id)
        self._mav = conn.mav
        conn.mav.check_signature = types.MethodType(check_signature_first, conn.mav)

    def _allow_unsigned(self, _mav, msg_id: int) -> bool:
        self.unsigned_or_bad += 1
        return msg_id == MAVLINK_MSG_ID_RADIO_STATUS

    def snapshot(self) -> dict:
        s = getattr(self._mav, "signing", None)
        bad = int(getattr(s, "badsig_count", 0))
        return {"on": True, "key_id": self.key_id, "good": int(getattr(s, "goodsig_count", 0)),
                "bad_signature": bad, "unsigned": max(0, self.unsigned_or_bad - bad),
                "refused": int(getattr(s, "reject_count", 0))}


NEW_STREAM_SLACK = 6000 * 1000       # a new stream may be up to 60 s behind (10 us units), as pymavlink


def check_signature_first(mav, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """pymavlink's ``MAVLink.check_signature`` with the signature checked before the stream's
    timestamp is stored.  pymavlink 2.4 stores the timestamp of a packet whose signature then
    fails, so one forged packet with a future timestamp makes every genuine packet of that stream
    look like a replay; here only a packet signed with our key moves the stream's timestamp.
    The rules (MAVLink 2 message signing): SHA-256(key + packet without the 6 signature bytes),
    first 48 bits; the timestamp (10 us since 2015-01-01) must grow per (link id, system,
    component) stream, and a new stream may start at most a minute behind our own timestamp."""
    signing = mav.signing
    expected = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
    if not hmac.compare_digest(expected, bytes(msgbuf[-6:])):
        return False
    tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
    timestamp = tlow + (thigh << 32)
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if (last is not None and timestamp <= last) or (last is None and timestamp + NEW_STREAM_SLACK < signing.timestamp):
        return False
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


_PASSPHRASE_VARIABLES: set[str] = set()


def passphrase_from_env(name: str) -> bytes:
    """The key of the passphrase in environment variable ``name`` (kept off the command line).
    The name is remembered (``passphrase_variables``): the processes the station starts (the
    forwarding process) get an environment without it.

    Raises:
        IngestError: the variable is not set or empty.
    """
    _PASSPHRASE_VARIABLES.add(name)
    value = os.environ.get(name, "")
    if not value:
        raise IngestError(f"environment variable {name} holds no signing passphrase")
    return key_from_passphrase(value)


def passphrase_variables() -> frozenset[str]:
    """The environment variables read as signing passphrases in this process (never passed on)."""
    return frozenset(_PASSPHRASE_VARIABLES)
