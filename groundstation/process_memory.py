"""This process's own resident memory, from /proc/self/status (Linux): now (``VmRSS``) and its
high-water mark (``VmHWM``), in MB.

Not ``getrusage``'s ``ru_maxrss``: a process started by fork (or vfork) and exec begins with its
parent's high-water mark in it (Linux records the old memory's peak at exec: proc(5), getrusage(2)),
so a Dask worker or a benchmark's child would read at least its parent's peak (a worker started
after its parent held 480 MB read 516 MB there, 62 MB in VmHWM)."""
from __future__ import annotations

__all__ = ["status_MB", "peak_rss_MB"]


def status_MB(field: str) -> float | None:
    """A kB field of /proc/self/status ("VmRSS", "VmHWM") in MB; None where there is no /proc."""
    try:
        with open("/proc/self/status") as status:
            line = next((line for line in status if line.startswith(field + ":")), None)
    except OSError:
        return None
    return int(line.split()[1]) / 1024.0 if line else None


def peak_rss_MB() -> float | None:
    """This process's peak resident memory [MB]: VmHWM; without /proc, ``ru_maxrss`` (kB on Linux,
    bytes on macOS), which may carry the parent's peak (module docstring)."""
    peak = status_MB("VmHWM")
    if peak is not None:
        return peak
    try:
        import resource
        import sys
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return kb / 2**20 if sys.platform == "darwin" else kb / 1024.0
    except (ImportError, OSError):
        return None
