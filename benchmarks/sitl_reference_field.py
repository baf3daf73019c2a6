"""How much of the in-flight fit's error on ArduPilot SITL flights is the reference field's.

SITL makes its Earth field from ArduPilot's declination/inclination/intensity table (AP_Declination,
the table pymavlink's ``mavextra.expected_earth_field_lat_lon`` interpolates, as magfit_WMM uses);
our fit takes WMM2025.  Each recorded flight (``benchmarks/real_logs.py --sitl-recorded DIR``) is
fitted twice, by ``calibrate_compasses`` unchanged except for the reference field: our WMM along
the flight, then SITL's table at the flight's median GPS position.  What moves between the two is
the reference field's share of the error; what stays is the estimator's.

    .venv/bin/python benchmarks/sitl_reference_field.py DIR/seed11 DIR/seed15 ...
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # this checkout's code, whatever the venv holds

import groundstation.jobs.calibrate.inflight as inflight  # noqa: E402
from groundstation.io.logs import read_log  # noqa: E402
from groundstation.jobs.calibrate import calibrate_compasses  # noqa: E402

WMM_FIELD = inflight.field_for


def sitl_table_field(log, ctx, t_s):
    """SITL's own field (pymavlink's interpolated AP_Declination table) at the flight's median fix."""
    from pymavlink import mavextra
    g = np.asarray(log.gps, float).reshape(-1, 8)
    good = g[:, 7] >= 3
    v = mavextra.expected_earth_field_lat_lon(float(np.median(g[good, 1])), float(np.median(g[good, 2])))
    return np.tile([v.x, v.y, v.z], (len(np.ravel(t_s)), 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="recorded SITL flights (DIR/seed<N> with truth.json)")
    a = ap.parse_args(argv)
    print("| flight | log | compass | ours, WMM: Δ per axis mG | 1σ | ours, SITL's table: Δ per axis mG | 1σ |")
    print("|---|---|---|---|---|---|---|")
    for run in a.runs:
        flight = json.loads((run / "truth.json").read_text())["flight"]
        for kind in ("flight.BIN", "telemetry.tlog"):
            log = read_log(run / kind)
            got = {}
            for name, fn in (("wmm", WMM_FIELD), ("table", sitl_table_field)):
                inflight.field_for = fn
                try:
                    got[name] = calibrate_compasses(log)
                finally:
                    inflight.field_for = WMM_FIELD
            for r_w, r_t in zip(got["wmm"], got["table"]):
                k = r_w["compass"]
                cells = []
                for r in (r_w, r_t):
                    if r["offsets_mG"] is None:
                        cells += [r["status"], "-"]
                        continue
                    err = -np.asarray(r["offsets_mG"], float) - np.asarray(flight["ofs_mG"][k], float)
                    cells += [f"{r['status']} [{', '.join(f'{e:+.1f}' for e in err)}]",
                              "[" + ", ".join(f"{x:.1f}" for x in r["offsets_sd_mG"]) + "]"]
                print(f"| {run.name} ({flight['site']}) | {kind} | {k} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
