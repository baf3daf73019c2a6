"""The command line's help: every command listed at the top, every option of every command
with a help string that gives its default, `simulate --help` listing every scenario."""
from __future__ import annotations

import argparse

from groundstation.cli import build_parser
from groundstation.cli_simulate import SCENARIO_HELP
from groundstation.sim.scenarios import SCENARIOS


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def test_top_level_help_lists_every_command():
    parser = build_parser()
    text = parser.format_help()
    for name in ("serve", "calibrate", "analyze", "simulate", "review", "info"):
        assert name in _commands(parser) and f"    {name}" in text, name
    assert "review" in text.splitlines()[2]          # the one-line description names it too


def test_every_option_has_help_with_its_default():
    missing, no_default = [], []
    for name, p in _commands(build_parser()).items():
        for a in p._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            if not a.help:
                missing.append(f"{name} {a.dest}")
            elif a.option_strings and a.default not in (None, False) and "default" not in a.help:
                no_default.append(f"{name} {a.option_strings[0]} (default {a.default!r})")
            elif a.option_strings and a.default in (None, False) and a.required is False \
                    and "default" not in a.help and a.dest not in ("replay", "tls_key", "out", "scenario"):
                no_default.append(f"{name} {a.option_strings[0]} (says nothing of what happens without it)")
    assert missing == [] and no_default == [], (missing, no_default)


def test_simulate_help_lists_every_scenario():
    text = _commands(build_parser())["simulate"].format_help()
    assert set(SCENARIO_HELP) == set(SCENARIOS) | {"fleet"}
    for name in (*SCENARIOS, "fleet"):
        assert f"\n  {name} " in text, name
    assert "--live udpout:127.0.0.1:14550" in text


def test_plot_without_matplotlib_fails_before_the_work(monkeypatch, capsys, tmp_path):
    """`analyze --plot` checks matplotlib before reading the log (not after the whole analysis)."""
    import groundstation.cli as cli
    from groundstation.jobs import flight_plot

    def missing() -> None:
        raise flight_plot.PlotUnavailable("--plot needs matplotlib, a dependency of magstation: reinstall it")

    read: list[str] = []
    monkeypatch.setattr(flight_plot, "check_plotting", missing)
    monkeypatch.setattr(cli, "load_log", lambda path: read.append(path))
    assert cli.main(["analyze", "recordings/demo.tlog", "--plot", str(tmp_path / "p.png")]) == 1
    err = capsys.readouterr().err
    assert read == [] and err.count("\n") == 1 and "needs matplotlib" in err


def test_review_and_plot_need_no_extra():
    """What `review` and `analyze --plot` import is installed by the base dependencies (./run)."""
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    base = " ".join(project["dependencies"])
    for name in ("dask[distributed]", "pyarrow", "matplotlib", "bokeh"):
        assert name in base, name
    assert "fleet" not in project.get("optional-dependencies", {})
