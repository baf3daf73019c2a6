"""numba's cache of the estimators' kernels follows their source (estimators.kernel_cache): a
kernel that calls a kernel of another file is compiled again when that file changes, where numba
alone (it checks only the caller's own file) would load the caller with the old callee inside."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from estimators.kernel_cache import keep_consistent

CALLER = """from numba import njit
from pkg.callee import value

@njit(cache=True)
def caller():
    return value() + 0
"""
INIT = """from pathlib import Path
from estimators.kernel_cache import keep_consistent
{call}
"""


def _package(tmp: Path, guarded: bool) -> Path:
    pkg = tmp / "pkg"
    pkg.mkdir()
    call = "keep_consistent(Path(__file__).resolve().parent)" if guarded else ""
    (pkg / "__init__.py").write_text(INIT.format(call=call))
    (pkg / "caller.py").write_text(CALLER)
    (pkg / "callee.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef value():\n    return 1\n")
    return pkg


def _run(tmp: Path) -> int:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp), str(Path(__file__).resolve().parents[1])])
    out = subprocess.run([sys.executable, "-c", "from pkg.caller import caller; print(caller())"],
                         cwd=tmp, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return int(out.stdout.split()[-1])


def _edit_callee(pkg: Path) -> None:
    path = pkg / "callee.py"
    path.write_text(path.read_text().replace("return 1", "return 2"))
    st = path.stat()                      # a later modification time, as an editor's save gives
    os.utime(path, (st.st_atime + 5, st.st_mtime + 5))


def test_a_changed_callee_file_recompiles_its_callers(tmp_path):
    bare, guarded = tmp_path / "bare", tmp_path / "guarded"
    bare.mkdir()
    guarded.mkdir()
    pkgs = {name: _package(folder, name == "guarded") for name, folder in (("bare", bare), ("guarded", guarded))}
    assert _run(bare) == 1 and _run(guarded) == 1
    for pkg in pkgs.values():
        _edit_callee(pkg)
    assert _run(guarded) == 2
    assert _run(bare) == 1        # numba alone: the caller's cache still holds the old callee


def test_the_cache_is_cleared_only_when_a_source_changed(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    kept = cache / "a.f-1.py311.nbi"
    kept.write_text("index")
    (cache / "a.cpython-311.pyc").write_text("bytecode")
    assert keep_consistent(tmp_path)                      # no stamp yet: cleared
    assert not kept.exists() and (cache / "a.cpython-311.pyc").exists()
    kept.write_text("index")
    assert not keep_consistent(tmp_path) and kept.exists()    # nothing changed: kept
    (tmp_path / "a.py").write_text("x = 2\n")
    assert keep_consistent(tmp_path) and not kept.exists()
