"""Expected Earth magnetic field from the World Magnetic Model (WMM2025, NOAA `wmm-calculator`).

We use NOAA's own package rather than our own spherical-harmonic code: it ships the official
coefficients and is maintained by the model's authors.  WMM gives nT; we return mG
(1 mG = 100 nT), the project's internal magnetic unit.
"""
from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from geomaglib import util as geoid_util
from wmm import uncertainty as _wmm_uncertainty
from wmm import wmm_calc

NT_PER_MG = 100.0

# WMM2025's error model, 1σ of the model against the observed field (crustal field included) per NED
# component, as wmm-calculator ships it (WMM2025 technical report, Chulliat et al. 2025: X 137, Y 89, Z 141 nT)
WMM_ERROR_NED_mG: tuple[float, float, float] = tuple(
    float(_wmm_uncertainty.err_model[k]) / NT_PER_MG for k in ("X", "Y", "Z"))


@dataclass(frozen=True)
class EarthField:
    """WMM field at one place and date.  ``field_ned_mG`` is (north, east, down)."""
    declination_deg: float
    inclination_deg: float
    field_strength_mG: float
    field_ned_mG: np.ndarray


def decimal_year_from_unix(unix_s: float) -> float:
    """Decimal year (e.g. 2026.89) of a UNIX time in seconds."""
    t = _dt.datetime.fromtimestamp(float(unix_s), tz=_dt.timezone.utc)
    start = _dt.datetime(t.year, 1, 1, tzinfo=_dt.timezone.utc)
    end = _dt.datetime(t.year + 1, 1, 1, tzinfo=_dt.timezone.utc)
    return t.year + (t - start).total_seconds() / (end - start).total_seconds()


@lru_cache(maxsize=256)
def _field_cached(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float,
                  msl: bool = True) -> EarthField:
    model = wmm_calc()
    alt_km = alt_m / 1000.0
    if msl:
        # wmm-calculator 1.4.4's own msl=True flag is lost inside setup_env (the converted height
        # is overwritten), so convert MSL -> ellipsoidal height here with its geoid (geomaglib).
        alt_km = float(geoid_util.alt_to_ellipsoid_height(alt_km, lat_deg, lon_deg)[0])
    model.setup_env(lat_deg, lon_deg, alt_km, unit="km", msl=False)
    model.setup_time(dyear=decimal_year)
    e = model.get_all()
    ned_mG = np.array([float(e["x"][0]), float(e["y"][0]), float(e["z"][0])]) / NT_PER_MG
    ned_mG.setflags(write=False)
    return EarthField(float(e["dec"][0]), float(e["inc"][0]), float(e["f"][0]) / NT_PER_MG, ned_mG)


def earth_field(lat_deg: float, lon_deg: float, alt_m: float, decimal_year: float,
                ellipsoidal_height: bool = False) -> EarthField:
    """WMM field (declination, inclination, strength, NED vector in mG) at a position and date.

    The model is valid 2025.0-2030.0; dates outside are clamped to that span (with the
    secular variation extrapolated by the model this is at most a fraction of a degree).
    Position is rounded to ~100 m and date to ~4 days for caching; the field changes far
    less than the sensor noise over such steps.  ``alt_m`` is above mean sea level (as GPS logs
    give it) unless ``ellipsoidal_height`` (height above the WGS84 ellipsoid, as in NOAA's test values).
    """
    if not (np.isfinite(lat_deg) and np.isfinite(lon_deg)):
        raise ValueError("earth_field needs a finite latitude and longitude")
    year = float(np.clip(decimal_year, 2025.0, 2029.999))
    alt = float(alt_m) if np.isfinite(alt_m) else 0.0
    return _field_cached(round(float(lat_deg), 3), round(float(lon_deg), 3), round(alt, -1), round(year, 2),
                         not ellipsoidal_height)


def field_along_path(lat_deg, lon_deg, alt_m, decimal_year, *, grid_deg: float = 0.01, grid_alt_m: float = 50.0,
                     grid_years: float = 0.01) -> np.ndarray:
    """WMM field (N,3) NED mG at each sample of a flight path (position, altitude above MSL, date).

    Vectorised over a coarse grid: the samples are snapped to cells of ``grid_deg`` (0.01° ≈ 1.1 km),
    ``grid_alt_m`` and ``grid_years``, the model is evaluated once per occupied cell (``earth_field``)
    and the cell values are mapped back.  Over such a cell the main field changes by < 0.3 mG
    (horizontal gradient ~0.01–0.03 mG/km at mid latitudes, vertical ~0.25 mG/km, secular change
    ~0.5 mG per 0.01 year at most), well below the sensor noise.  Rows with a non-finite position or
    date are NaN; a non-finite altitude counts as 0 m.
    """
    lat = np.asarray(lat_deg, float).ravel()
    n = len(lat)
    lon = np.broadcast_to(np.asarray(lon_deg, float).ravel(), (n,))
    alt = np.broadcast_to(np.asarray(alt_m, float).ravel(), (n,))
    year = np.broadcast_to(np.asarray(decimal_year, float).ravel(), (n,))
    out = np.full((n, 3), np.nan)
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(year) & (np.abs(lat) <= 90) & (np.abs(lon) <= 360)
    if not ok.any():
        return out
    cells = np.column_stack([np.round(lat[ok] / grid_deg), np.round(lon[ok] / grid_deg),
                             np.round(np.where(np.isfinite(alt[ok]), alt[ok], 0.0) / grid_alt_m),
                             np.round(year[ok] / grid_years)])
    unique, inverse = np.unique(cells, axis=0, return_inverse=True)
    values = np.array([earth_field(c[0] * grid_deg, c[1] * grid_deg, c[2] * grid_alt_m, c[3] * grid_years).field_ned_mG
                       for c in unique])
    out[ok] = values[np.ravel(inverse)]
    return out
