"""numba's on-disk cache of the estimators' kernels, kept true to their source.

numba (``cache=True``) keys a cached kernel on the modification time and size of the one file it
is defined in; a kernel that calls kernels of other files (the field-vector test's step calls the
field model's, the ring buffers' and the rotations'; the AHRS supervisor calls ahrs_math's
Rodrigues coefficients) holds their compiled code too, and numba would load it unchanged after
those files changed.  So at the import of ``estimators`` the text of its modules is hashed; when
the hash differs from the one stored beside the cache, the estimators' cached kernels are
deleted and compile again on their next call (``estimators.kernel_warmup`` does that at once).

Only numba's default cache location (``__pycache__`` beside the sources) is handled; with
NUMBA_CACHE_DIR set, that cache is the caller's to keep.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["keep_consistent", "source_hash"]

FOLDER = Path(__file__).resolve().parent
CACHE = FOLDER / "__pycache__"
STAMP = CACHE / "numba-kernels.sha256"


def source_hash(folder: Path = FOLDER) -> str:
    """sha256 of every estimators module's text, in name order."""
    h = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def keep_consistent(folder: Path = FOLDER) -> bool:
    """Delete the estimators' cached kernels if any estimators module changed since they were
    cached (``source_hash`` against the stamp).  Returns True when it deleted them.  A cache that
    cannot be written (a read-only install) is left alone: numba then caches elsewhere itself."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return False
    cache, stamp = folder / "__pycache__", folder / "__pycache__" / STAMP.name
    now = source_hash(folder)
    try:
        if stamp.is_file() and stamp.read_text().strip() == now:
            return False
        cache.mkdir(exist_ok=True)
        for path in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            path.unlink(missing_ok=True)
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}")
        tmp.write_text(now + "\n")
        tmp.replace(stamp)
    except OSError:
        return False
    return True
