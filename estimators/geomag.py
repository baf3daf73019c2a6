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
from wmm import wmm_calc

NT_PER_MG = 100.0


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
