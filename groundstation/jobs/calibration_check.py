"""A calibration object from a file, a request or the history, checked before it is used:
``m_cal = matrix (m_raw - offsets_mG)`` with finite, plausible numbers."""
from __future__ import annotations

import numpy as np

__all__ = ["check_calibration", "calibration_arrays", "MAX_OFFSET_MG"]

MAX_OFFSET_MG = 1e5          # 100 G: far beyond any magnetometer's range
MAX_MATRIX_CONDITION = 1e3   # a fitted soft-iron matrix is near a rotation times ~1 (ratio <= 2.5)
MATRIX_SCALE_RANGE = (1e-2, 1e2)


def check_calibration(calibration: dict) -> tuple[np.ndarray, np.ndarray]:
    """(offsets_mG (3,), matrix (3, 3)) of a calibration object (``m_cal = matrix (m_raw - offsets)``).

    Raises:
        ValueError: saying what is wrong: offsets or matrix missing, not three / 3x3 numbers, not
            finite, offsets beyond MAX_OFFSET_MG, matrix singular or of absurd scale.
    """
    off, mat = calibration.get("offsets_mG"), calibration.get("matrix")
    if off is None:
        raise ValueError("the calibration has no offsets_mG")
    if mat is None:
        raise ValueError("the calibration has no matrix")
    try:
        off = np.asarray(off, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("offsets_mG must be three numbers") from None
    try:
        mat = np.asarray(mat, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("matrix must be 3x3 numbers") from None
    if off.shape != (3,):
        raise ValueError("offsets_mG must be three numbers")
    if mat.shape != (3, 3):
        raise ValueError("matrix must be 3x3 numbers")
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(mat))):
        raise ValueError("offsets_mG and matrix must be finite numbers")
    if np.max(np.abs(off)) > MAX_OFFSET_MG:
        raise ValueError(f"offsets_mG beyond +-{MAX_OFFSET_MG:g} mG are not a magnetometer's")
    sv = np.linalg.svd(mat, compute_uv=False)
    if sv[-1] <= sv[0] / MAX_MATRIX_CONDITION or sv[0] == 0:
        raise ValueError(f"matrix is singular (singular values {', '.join(f'{v:.3g}' for v in sv)}): "
                         "it would map every field onto a plane or a point")
    if not MATRIX_SCALE_RANGE[0] <= sv[-1] <= sv[0] <= MATRIX_SCALE_RANGE[1]:
        raise ValueError(f"matrix scale {sv[-1]:.3g}..{sv[0]:.3g} is outside "
                         f"{MATRIX_SCALE_RANGE[0]:g}..{MATRIX_SCALE_RANGE[1]:g}")
    return off, mat


def calibration_arrays(calibration: dict | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``check_calibration``'s arrays, or None when there is no usable calibration."""
    if not calibration:
        return None
    try:
        return check_calibration(calibration)
    except ValueError:
        return None
