"""`magstation analyze --plot FILE.png`: one flight on one time axis.

Panels: heading difference (compass minus gyro-held heading, deg), the field-vector residual
|r̄| (mG) with its test score, the motor signal (current A or throttle %), and the combined alarms
as shaded spans on every panel.  matplotlib is imported here only.
"""
from __future__ import annotations

import numpy as np

from estimators.field_consistency import ON, status_text

__all__ = ["plot_flight", "PlotUnavailable", "vector_test_status"]


def vector_test_status(status: np.ndarray) -> str:
    """"on (x % of the steps)" or the most frequent reason it was off."""
    st = np.asarray(status, dtype=int)
    if not len(st):
        return "off: no IMU data"
    on = float(np.mean(st == ON))
    if on > 0:
        return f"on ({100 * on:.0f} % of the steps)"
    return status_text(int(np.bincount(st).argmax()))


class PlotUnavailable(RuntimeError):
    """matplotlib is not installed."""


def check_plotting() -> None:
    """Raise ``PlotUnavailable`` (one line) when matplotlib cannot be imported: callers check
    before the analysis, not after it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise PlotUnavailable("--plot needs matplotlib, a dependency of magstation: reinstall it "
                              "(./run, or pip install -e .)") from None


def plot_flight(fa, alarms: list[dict], path: str, title: str = "") -> None:
    """Write the PNG of a ``FlightAnalysis`` and its combined alarms to ``path``.

    Raises:
        PlotUnavailable: matplotlib is not installed.
    """
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise PlotUnavailable("--plot needs matplotlib, a dependency of magstation: reinstall it "
                              "(./run, or pip install -e .)") from None
    x = fa.x
    t = x["t"]
    residual = np.linalg.norm(x["vector"].residual_mG, axis=1)
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(10, 7))
    axes[0].plot(t, np.degrees(x["e"]), lw=0.7, color="tab:blue")
    axes[0].set_ylabel("heading diff [deg]")
    axes[1].plot(t, residual, lw=0.7, color="tab:purple", label="|residual| [mG]")
    score = axes[1].twinx()
    score.plot(t, np.clip(fa.det.z_vector, 0, 5), lw=0.7, color="tab:orange", label="vector score (1 = alarm)")
    score.set_ylabel("score", color="tab:orange")
    axes[1].set_ylabel("field residual [mG]")
    if not np.isfinite(residual).any():
        axes[1].text(0.5, 0.5, f"field-vector test {vector_test_status(x['vector'].status)}",
                     transform=axes[1].transAxes, ha="center", va="center")
    signal = x.get("motor_signal", "none")
    axes[2].plot(t, x["motor_held"], lw=0.7, color="tab:green")
    axes[2].set_ylabel({"current_A": "current [A]", "throttle_pct": "throttle [%]"}.get(signal, "no motor signal"))
    axes[2].set_xlabel("time [s]")
    end_t = float(t[-1]) if len(t) else 0.0
    for a in alarms:
        for ax in axes:
            ax.axvspan(a["start_s"], a["end_s"] if a["end_s"] is not None else end_t, color="red", alpha=0.15)
    axes[0].set_title(title + (f"  ({len(alarms)} alarm{'s' * (len(alarms) != 1)}, red)" if alarms else "  (no alarm)"))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
