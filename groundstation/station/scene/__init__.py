"""The viser 3-D view (``view.Scene``) and its geometry (``geometry``)."""
from groundstation.station.scene.geometry import S_FLIP, attitude_wxyz, quat_wxyz, residual_colors, rotation_ned
from groundstation.station.scene.view import CLOUD_DISPLAY_POINTS, ROUTE_DISPLAY_POINTS, Scene

__all__ = ["Scene", "S_FLIP", "attitude_wxyz", "quat_wxyz", "residual_colors", "rotation_ned",
           "CLOUD_DISPLAY_POINTS", "ROUTE_DISPLAY_POINTS"]
