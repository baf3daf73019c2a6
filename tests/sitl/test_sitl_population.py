"""benchmarks/sitl.py --population: clean GUIDED flights of ArduPilot's firmware drawn from wide
priors (``population_flight``), their alarms on the .BIN and the session .tlog in one table, and
--analyse-kept (the kept logs analysed again).  The draws are checked without the firmware; one
short drawn flight (two legs, 8x: the mechanics, not the .tlog's timing, which needs 1x) is flown
when ../shared/sitl is there, and skips saying so when it is not."""
from __future__ import annotations

import contextlib
import io
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from harness import MISSING, SITL_BINARY

ROOT = Path(__file__).resolve().parents[2]


def _benchmark():
    """benchmarks/sitl.py loaded by its path: a plain ``import sitl`` may find another module of
    that name first (a worker that already imported tests/sitl as a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("sitl_benchmark", ROOT / "benchmarks" / "sitl.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module             # its dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def test_population_draws_are_repeatable_and_within_their_priors():
    bench = _benchmark()
    from estimators.geomag import earth_field

    flights = [bench.population_flight(0, k) for k in range(24)]
    assert [f for _, f in flights[:3]] == [bench.population_flight(0, k)[1] for k in range(3)]   # same seed, same draw
    assert bench.population_flight(1, 0)[1] != flights[0][1]
    incs = []
    for name, f in flights:
        assert name.startswith("pop0_") and f.expect in ("none", "motor")
        inc = earth_field(f.home[0], f.home[1], 0.0, 2026.9).inclination_deg
        incs.append(inc)
        assert -64.0 <= inc <= 79.0, (name, f.home, inc)
        assert 4 <= len(f.legs) <= 6 and f.legs[-1][:2] == (0.0, 0.0)                     # 3-5 points, then home
        assert all(10.0 <= leg[2] <= 40.0 and 3.0 <= leg[3] <= 12.0 for leg in f.legs)
        assert f.extra["WP_YAW_BEHAVIOR"] in (0, 1, 2)
        if f.expect == "motor":                        # what COMPASS_MOT leaves of SIM_MAG_MOT is the truth
            left = [f.extra[f"SIM_MAG_MOT_{a}"] + f.extra[f"COMPASS_MOT_{a}"] for a in "XYZ"]
            np.testing.assert_allclose(f.motor_truth, left, atol=0.011)
            assert f.extra["COMPASS_MOTCT"] == 2
        else:
            assert f.motor_truth is None and "SIM_MAG_MOT_X" not in f.extra
        if f.gps_off:
            assert 20.0 <= f.gps_off_s <= 45.0
    assert min(incs) < -30.0 and max(incs) > 50.0                       # both hemispheres, steep fields
    kinds = {f.expect for _, f in flights}, {f.gps_off for _, f in flights}
    assert kinds == ({"none", "motor"}, {True, False})


def test_a_short_population_flight_is_flown_tabled_and_analysed_again_from_its_kept_logs(tmp_path):
    if SITL_BINARY is None:
        pytest.skip(MISSING)
    bench = _benchmark()

    name, drawn = bench.population_flight(0, 0)
    short = replace(drawn, alt_m=8.0, legs=((20.0, 0.0, 8.0, 5.0), (0.0, 0.0, 8.0, 5.0)), gps_off=False)
    out: dict = {"_keep": str(tmp_path / "kept")}
    try:
        bench.run_flight(name, out, instance=None, flight=short, speedup=8)
        r = out["flights"][name]
        assert r["armed"] is True, r.get("prearm")
        assert r["flight"] is short
        for kind, least_s in (("bin", 20.0), ("tlog", 5.0)):          # the .tlog on the wall clock: 8x shorter
            assert isinstance(r[f"{kind}_combined"], list) and r[f"{kind}_duration"] > least_s, kind
        assert r["tlog_late"]["max"] >= 0.0
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            bench.print_population(out)
        row = next(line for line in printed.getvalue().splitlines() if line.startswith(f"| {name} "))
        assert drawn.site in row and f"| {len(r['bin_combined'])} " in row
        again: dict = {}
        kept = Path(out["_keep"])
        assert sorted(p.name for p in kept.iterdir()) == [f"{name}.BIN", f"{name}.tlog"]
        # --analyse-kept draws the flight again from its name: the full route, the same site and truth
        bench.analyse_kept(kept, name, again)
        a = again["flights"][name]
        assert a["flight"] == drawn
        assert [x[:2] for x in a["bin_combined"]] == [x[:2] for x in r["bin_combined"]]
        assert [x[:2] for x in a["tlog_combined"]] == [x[:2] for x in r["tlog_combined"]]
    finally:
        import shutil
        for d in out.get("_dirs", []):
            shutil.rmtree(d, ignore_errors=True)
