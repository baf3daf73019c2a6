"""Which directions of the Earth field the vehicle has shown its compasses, and the next pose to take.

The field seen in the body frame is m_b = C_n^bᵀ… = Rᵀ · h (R = C_b^n from the attitude, h the
unit Earth field: WMM at the GPS fix, else a 60° inclination), so the directions covered so far
follow from the attitude alone, whatever state each compass's calibration is in.  They are binned
in the 100 equal-area cells of ``estimators.calibration.coverage_cells`` (10 bands equal in body
z, 10 sectors equal in longitude).

Next pose: the autopilot's own calibrator and Mission Planner leave the operator to guess which
sides are missing.  Here every candidate pose (level, upside down, nose/side down or up by 45° or
90°) is followed through one full turn about the vertical; the directions that turn would show are
binned, and the pose that fills the most missing cells is proposed (ties: the simpler pose).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from estimators.calibration import coverage_cells
from estimators.rotations import dcm_body_to_ned

__all__ = ["field_unit_ned", "body_field_directions", "CELL_COUNT", "next_pose", "POSES"]

CELL_COUNT = 100
DEFAULT_INCLINATION_DEG = 60.0
# (text, roll deg, pitch deg), simplest first
POSES = (
    ("hold it level", 0.0, 0.0),
    ("turn it upside down", 180.0, 0.0),
    ("tilt the nose down 45°", 0.0, -45.0),
    ("tilt the nose up 45°", 0.0, 45.0),
    ("tilt the right side down 45°", 45.0, 0.0),
    ("tilt the left side down 45°", -45.0, 0.0),
    ("point the nose straight down", 0.0, -89.0),
    ("point the nose straight up", 0.0, 89.0),
    ("lay it on its right side", 90.0, 0.0),
    ("lay it on its left side", -90.0, 0.0),
    ("upside down, nose down 45°", 180.0, -45.0),
    ("upside down, nose up 45°", 180.0, 45.0),
    ("upside down, right side down 45°", 135.0, 0.0),
    ("upside down, left side down 45°", -135.0, 0.0),
)
_SWEEP = np.radians(np.arange(0.0, 360.0, 4.0))


def field_unit_ned(field_ned_mG: np.ndarray | None) -> np.ndarray:
    """Unit Earth field (NED); a 60° inclination pointing north when the WMM field is unknown."""
    if field_ned_mG is not None and np.all(np.isfinite(field_ned_mG)) and np.linalg.norm(field_ned_mG) > 0:
        f = np.asarray(field_ned_mG, float)
        return f / np.linalg.norm(f)
    i = math.radians(DEFAULT_INCLINATION_DEG)
    return np.array([math.cos(i), 0.0, math.sin(i)])


def body_field_directions(roll_rad, pitch_rad, yaw_rad, field_unit: np.ndarray) -> np.ndarray:
    """Unit field directions in the body frame, (N, 3): Rᵀ h."""
    R = dcm_body_to_ned(roll_rad, pitch_rad, yaw_rad)
    return np.einsum("...ji,j->...i", R, field_unit)


@lru_cache(maxsize=8)
def _pose_table(field_unit: tuple[float, float, float]) -> tuple:
    """(text, roll, pitch, cells a full yaw turn in that pose shows) for every pose."""
    n, h = len(_SWEEP), np.asarray(field_unit)
    out = []
    for text, roll, pitch in POSES:
        d = body_field_directions(np.full(n, math.radians(roll)), np.full(n, math.radians(pitch)), _SWEEP, h)
        out.append((text, roll, pitch, coverage_cells(d)))
    return tuple(out)


def next_pose(covered: np.ndarray, field_unit: np.ndarray) -> dict | None:
    """The pose whose full turn about the vertical fills the most missing cells.

    Returns {"text", "roll_deg", "pitch_deg", "fills", "missing"} or None when nothing is missing
    or no pose would add a cell.
    """
    covered = np.asarray(covered, bool)
    missing = ~covered
    if not missing.any():
        return None
    best, best_gain = None, 0
    for text, roll, pitch, cells in _pose_table(tuple(round(float(v), 3) for v in field_unit)):
        gain = int(np.sum(cells & missing))
        if gain > best_gain:
            best, best_gain = (text, roll, pitch), gain
    if best is None:
        return None
    text, roll, pitch = best
    return {"text": f"{text}, then turn it one full turn about the vertical", "roll_deg": roll,
            "pitch_deg": pitch, "fills": best_gain, "missing": int(missing.sum())}
