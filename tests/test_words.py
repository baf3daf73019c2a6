"""Words and numbers in terminal and report text (groundstation.jobs.words and the CLI's output):
no ``None mG``, no ``-0.00``, coordinates rounded, tests and GPS fixes by name, a status said once,
report JSON without the local path."""
from __future__ import annotations

import json
import re

from groundstation.cli import main
from groundstation.jobs.words import fix_name, lat_lon, num, score_name, span_s, without_status
from groundstation.paths import RECORDINGS_DIR


def test_numbers_and_names():
    assert num(None, unit="mG") == "n/a" and num(float("nan"), unit="mG") == "n/a"
    assert num(-0.004, "{:.2f}") == "0.00" and num(-0.04, "{:.1f}", "mG") == "0.0 mG"
    assert num(-0.06, "{:.1f}") == "-0.1" and num(-0.001, "{:.0%}") == "0%"
    assert span_s(-0.3, 31.1) == "0–31 s" and span_s(12.04, None, "{:.1f}") == "12.0 s–end"
    assert lat_lon(30.259999999999998, 120.11999999999999) == "30.260000 N, 120.120000 E"
    assert lat_lon(-35.36232, -149.16572) == "35.362320 S, 149.165720 W"
    assert fix_name(6) == "RTK fixed" and fix_name(5.0) == "RTK float" and fix_name(3) == "3D fix"
    assert fix_name(None) == "n/a" and fix_name(42) == "fix type 42"
    assert score_name("field_strength_inclination") == "field strength / inclination"
    assert without_status("ambiguous", "ambiguous: rotations 1 and [0]") == "rotations 1 and [0]"
    assert without_status("ok", "fits best") == "fits best"


def test_analyze_and_calibrate_output_reads_well(tmp_path, capsys):
    demo = RECORDINGS_DIR / "demo.tlog"
    assert main(["analyze", str(demo), "--json", str(tmp_path / "r.json")]) == 0
    assert main(["calibrate", str(demo), "--json", str(tmp_path / "c.json")]) == 0
    assert main(["info", str(demo)]) == 0
    out = capsys.readouterr().out
    assert "None" not in out and "n/a mG" not in out and not re.search(r"(?<![\w.])-0\.0+(?!\d)", out)
    assert "mission A 30.260000 N, 120.120000 E -> B" in out          # not 30.259999999999998
    assert not re.search(r"\d\.\d{9,}", out) and "@" not in out
    assert "GPS fixes       RTK fixed 2301" in out
    assert not re.search(r"(\w+): \1:", out)                          # "ambiguous: ambiguous:"
    assert json.loads((tmp_path / "r.json").read_text())["file"] == "demo.tlog"
    assert [r["file"] for r in json.loads((tmp_path / "c.json").read_text())["results"]] == ["demo.tlog"]
    assert str(RECORDINGS_DIR) not in (tmp_path / "r.json").read_text() + (tmp_path / "c.json").read_text()
