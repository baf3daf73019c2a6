"""groundstation.process_memory: a process's own peak, not its parent's.  getrusage's ru_maxrss
of a child started by fork/vfork and exec begins at the parent's high-water mark (the review's
Dask workers and the memory benchmark's children are such children)."""
import subprocess
import sys

import numpy as np

from groundstation.process_memory import peak_rss_MB, status_MB

CHILD = "from groundstation.process_memory import peak_rss_MB\nprint(peak_rss_MB())\n"


def test_a_child_reads_its_own_peak_not_its_parents():
    held = np.ones(300 * 2**20 // 8)          # 300 MB resident in this process
    held[::512] += 1.0
    here = peak_rss_MB()
    del held
    assert here >= 300.0 and here >= status_MB("VmRSS") > 0.0, (here, status_MB("VmRSS"))
    own = float(subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True).stdout)
    assert 1.0 < own < 100.0, own                # a bare interpreter and this small module (ru_maxrss: 300+)
    assert status_MB("NoSuchField") is None
