"""Where `review_log`'s CPU time goes, without a profiler (issue 29).

    .venv/bin/python benchmarks/review_parts.py --fleet /tmp/fleet

``review_log`` on the first 8 flights of the 3 × 4 simulated fleet of ``benchmarks/field_vector.py
--part review`` (seed 0; made in ``--fleet`` unless it is there), with the process CPU time spent
inside a few functions added up by wrapping them: the in-flight WMM fit (``fit_wmm``), its
jackknife and reference-field terms (``_with_jackknife``, ``_with_field_model``), the solver calls
it makes itself (``solve``: the main fit and the marginal covariance, and the jackknife's and the
field term's refits where those call it) and the field-vector test (``field_consistency``).  cProfile
charges every Python call, so it inflates the per-step loop of the field-vector test against the
numpy of the fit: its shares are not these.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PARTS = (("estimators.wmm_fit", "fit_wmm", "fit_wmm (all)"),
         ("estimators.wmm_fit", "_with_jackknife", "  jackknife"),
         ("estimators.wmm_fit", "_with_field_model", "  reference-field term"),
         ("estimators.wmm_fit", "solve", "  solve() called by wmm_fit"),
         ("groundstation.jobs.inputs", "field_consistency", "field_consistency (field-vector test)"))


def _wrap(module, name: str, label: str, spent: Counter, depth: Counter) -> None:
    """Add the process CPU time of the outermost calls of ``module.name`` to ``spent[label]``
    (wherever it was imported by name)."""
    real = getattr(module, name)

    def timed(*args, **kw):
        depth[label] += 1
        t0 = time.process_time()
        try:
            return real(*args, **kw)
        finally:
            depth[label] -= 1
            if depth[label] == 0:
                spent[label] += time.process_time() - t0

    for mod in list(sys.modules.values()):
        if getattr(mod, name, None) is real:
            setattr(mod, name, timed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleet", type=Path, help="keep (or reuse) the simulated fleet in this folder")
    args = ap.parse_args(argv)
    import importlib

    from groundstation.jobs.fleet import discover_logs
    from groundstation.jobs.review_row import ReviewSettings, review_log
    from groundstation.sim.fleet import FleetSettings, simulate_fleet
    spent, depth = Counter(), Counter()
    for module, name, label in PARTS:
        _wrap(importlib.import_module(module), name, label, spent, depth)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.fleet or Path(tmp)
        if not (folder / "fleet.truth.json").exists():
            simulate_fleet(folder, FleetSettings(vehicles=3, flights=4, seed=0, drift_vehicles=1, payload_vehicles=1),
                           workers=1)
        logs = discover_logs([folder])[:8]
        t0 = time.process_time()
        for p in logs:
            review_log(p, ReviewSettings())
        total = time.process_time() - t0
    print(f"review_log: {len(logs)} logs, {total:.2f} CPU s, {len(logs) / total:.2f} logs per CPU-s")
    for _, _, label in PARTS:
        print(f"  {label:40s} {spent[label]:6.2f} CPU s  {100 * spent[label] / total:3.0f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
