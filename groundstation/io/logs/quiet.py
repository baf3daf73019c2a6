"""Third-party log readers that print a line per damaged byte or message (pymavlink's DFReader,
pyulog): their prints become counted warnings while we read, one line per kind in the end.

``quiet(module, classify)`` replaces ``print`` in that module (Python looks ``print`` up in the
module before the builtins) by one that, while ``counting(counts)`` is active in the calling
thread, adds ``classify(line)`` to ``counts``; in any other thread, or outside a read, it prints
as before.
"""
from __future__ import annotations

import builtins
import threading
from collections import Counter
from contextlib import contextmanager
from typing import Callable, Iterator

__all__ = ["quiet", "counting", "record"]

_sink = threading.local()


def quiet(module, classify: Callable[[str], tuple[str, int]]) -> None:
    """Count ``module``'s prints (see module docstring); ``classify(line) -> (warning, count)``."""
    def counted_print(*args, sep=" ", end="\n", file=None, flush=False) -> None:
        counts = getattr(_sink, "counts", None)
        if counts is None:
            builtins.print(*args, sep=sep, end=end, file=file, flush=flush)
            return
        key, n = classify(sep.join(str(a) for a in args))
        counts[key] += n

    module.print = counted_print


@contextmanager
def counting(counts: Counter) -> Iterator[None]:
    """Quietened modules' prints in this thread go to ``counts`` for the duration."""
    previous = getattr(_sink, "counts", None)
    _sink.counts = counts
    try:
        yield
    finally:
        _sink.counts = previous


def record(key: str, n: int = 1) -> None:
    """Add ``n`` to warning ``key`` of this thread's active ``counting`` (nothing outside one)."""
    counts = getattr(_sink, "counts", None)
    if counts is not None:
        counts[key] += n
