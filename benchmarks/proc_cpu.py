"""CPU time of processes from /proc (Linux), for the benchmarks that report what a process costs
(live, forwarding, the page in the browser): user + system seconds, fields 14 and 15 of
/proc/PID/stat (proc(5)), read after the command name, which may hold spaces or parentheses."""
from __future__ import annotations

import os
from pathlib import Path


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_seconds_of(marker: str) -> float:
    """User + system CPU seconds of the live processes whose command line holds ``marker``."""
    total = 0.0
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            if marker.encode() in Path(f"/proc/{pid}/cmdline").read_bytes():
                total += cpu_seconds(int(pid))
        except OSError:            # gone meanwhile
            continue
    return total
