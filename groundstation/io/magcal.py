"""ArduPilot's onboard compass calibration on the wire: MAG_CAL_PROGRESS / MAG_CAL_REPORT fields.

``completion_mask`` of MAG_CAL_PROGRESS is 10 bytes = 80 bits, one per section of ArduPilot's
geodesic grid (AP_Math/AP_GeodesicGrid.h): an icosahedron whose 20 triangles T_i are each split
into 4 (W_0 = the middle triangle of the edge midpoints, W_1..W_3 the corner triangles), section
s = 4 i + j; bit s % 8 of byte s // 8 is set once a calibrated sample's direction falls in
section s (CompassCalibrator::update_completion_mask).  The triangle order and vertices below are
the ones that header lists.  ``section_of`` finds the section of direction vectors,
``sections_from_mask``/``mask_from_sections`` convert, ``section_centres`` gives unit vectors for
drawing.  MAG_CAL status codes (MAG_CAL_STATUS) are named in ``CAL_STATUS``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["N_SECTIONS", "CAL_STATUS", "section_of", "sections_from_mask", "mask_from_sections",
           "section_centres"]

N_SECTIONS = 80
CAL_STATUS = {0: "not started", 1: "waiting to start", 2: "running (step one)", 3: "running (step two)",
              4: "success", 5: "failed", 6: "bad orientation", 7: "bad radius"}

_G = (1.0 + 5.0 ** 0.5) / 2.0


def _icosahedron_triangles() -> np.ndarray:
    g = _G
    t = [((-g, 1, 0), (-1, 0, -g), (-g, -1, 0)), ((-1, 0, -g), (-g, -1, 0), (0, -g, -1)),
         ((-g, -1, 0), (0, -g, -1), (0, -g, 1)), ((-1, 0, -g), (0, -g, -1), (1, 0, -g)),
         ((0, -g, -1), (0, -g, 1), (g, -1, 0)), ((0, -g, -1), (1, 0, -g), (g, -1, 0)),
         ((g, -1, 0), (1, 0, -g), (g, 1, 0)), ((1, 0, -g), (g, 1, 0), (0, g, -1)),
         ((1, 0, -g), (0, g, -1), (-1, 0, -g)), ((0, g, -1), (-g, 1, 0), (-1, 0, -g)),
         ((-g, 1, 0), (-1, 0, g), (-g, -1, 0)), ((-1, 0, g), (-g, -1, 0), (0, -g, 1)),
         ((-1, 0, g), (0, -g, 1), (1, 0, g)), ((0, -g, 1), (1, 0, g), (g, -1, 0)),
         ((g, -1, 0), (1, 0, g), (g, 1, 0)), ((1, 0, g), (g, 1, 0), (0, g, 1)),
         ((g, 1, 0), (0, g, 1), (0, g, -1)), ((1, 0, g), (0, g, 1), (-1, 0, g)),
         ((0, g, 1), (0, g, -1), (-g, 1, 0)), ((0, g, 1), (-g, 1, 0), (-1, 0, g))]
    return np.array(t, dtype=float)


def _sections() -> np.ndarray:
    """(80, 3, 3): vertices (rows) of every section, in section order."""
    out = []
    for a, b, c in _icosahedron_triangles():
        ma, mb, mc = (a + b) / 2, (b + c) / 2, (c + a) / 2
        out += [(ma, mb, mc), (a, ma, mc), (ma, b, mb), (mc, mb, c)]
    return np.array(out)


_SECTIONS = _sections()
_INVERSES = np.linalg.inv(np.transpose(_SECTIONS, (0, 2, 1)))   # solves v = Σ w_k vertex_k


def section_of(vectors: np.ndarray) -> np.ndarray:
    """Section index (0..79) crossed by each direction (N, 3) (edges inclusive); −1 for zero rows."""
    v = np.asarray(vectors, dtype=float).reshape(-1, 3)
    w = np.einsum("sij,nj->nsi", _INVERSES, v)
    inside = np.all(w >= -1e-9, axis=2)
    idx = np.argmax(inside, axis=1)
    ok = inside[np.arange(len(v)), idx] & np.all(np.isfinite(v), axis=1) & (np.linalg.norm(v, axis=1) > 0)
    return np.where(ok, idx, -1)


def sections_from_mask(mask: bytes | list[int]) -> list[int]:
    """Section indices whose bit is set in a 10-byte completion mask."""
    return [s for s in range(N_SECTIONS) if s // 8 < len(mask) and (int(mask[s // 8]) >> (s % 8)) & 1]


def mask_from_sections(sections) -> list[int]:
    """The 10-byte completion mask (list of ints 0..255) with the given sections set."""
    mask = [0] * (N_SECTIONS // 8)
    for s in sections:
        if 0 <= int(s) < N_SECTIONS:
            mask[int(s) // 8] |= 1 << (int(s) % 8)
    return mask


def section_centres() -> np.ndarray:
    """(80, 3) unit vectors through each section's centroid."""
    c = _SECTIONS.mean(axis=1)
    return c / np.linalg.norm(c, axis=1, keepdims=True)
