"""The calibration's covered field directions in the 3-D view: the centres of the 100 equal-area
cells of ``estimators.calibration.coverage_cells`` (body FRD drawn in viser axes) on the corrected
sphere, grey until a sample points there, then green (the calibration page draws the same cells)."""
from __future__ import annotations

import numpy as np

from groundstation.station.scene.geometry import S_FLIP

__all__ = ["CoverageSphere"]


class CoverageSphere:
    """Handle of the coverage dots; ``update(cells)`` recolours them only when the cells change."""

    def __init__(self, scene, position: np.ndarray, radius: float = 1.0) -> None:
        band, sector = np.divmod(np.arange(100), 10)
        z = -1.0 + (band + 0.5) * 0.2
        lon = (sector + 0.5) * 2 * np.pi / 10 - np.pi
        r = np.sqrt(1 - z * z)
        self._points = (np.stack([r * np.cos(lon), r * np.sin(lon), z], 1) @ S_FLIP * radius).astype(np.float32)
        self._key = None
        self.cloud = scene.add_point_cloud("/coverage", self._points, colors=(200, 200, 200), point_size=0.06,
                                           point_shape="circle", position=tuple(position), visible=False)

    def update(self, cells: np.ndarray | None) -> None:
        key = None if cells is None else bytes(np.asarray(cells, bool))
        if key == self._key:
            return
        self._key = key
        self.cloud.visible = cells is not None
        if cells is not None:
            seen = np.asarray(cells, bool)[:, None]
            self.cloud.colors = np.where(seen, [[67, 160, 71]], [[200, 200, 200]]).astype(np.uint8)
