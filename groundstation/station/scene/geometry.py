"""Geometry of the 3-D view: attitudes in viser axes, the route's drawing frame, camera framing.

Viser world: x forward/north, y left/west, z up (NED/FRD with y and z flipped, ``S_FLIP``).
The camera of each activity looks north (+x) from the south and above, so screen right is -y.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["S_FLIP", "rotation_ned", "quat_wxyz", "attitude_wxyz", "yaw_wxyz", "quat_mul", "residual_colors",
           "UNIT_SPHERE", "RouteFrame", "camera_for_box"]

S_FLIP = np.diag([1.0, -1.0, -1.0])            # NED/FRD <-> viser (x fwd/north, y left/west, z up)


def rotation_ned(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body (FRD) -> NED rotation matrix, ZYX Euler."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([
        [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
        [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
        [-sp, sr * cp, cr * cp]])


def quat_wxyz(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def attitude_wxyz(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Viser orientation of a model drawn in viser axes (x fwd, y left, z up) for an attitude."""
    return quat_wxyz(S_FLIP @ rotation_ned(roll, pitch, yaw) @ S_FLIP)


def yaw_wxyz(angle_rad: float) -> np.ndarray:
    """Rotation about viser +z (counter-clockwise seen from above)."""
    return np.array([math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b (apply b, then a)."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def residual_colors(residual: np.ndarray) -> np.ndarray:
    """0 -> blue, 0.05 (5 % of F) and above -> red, through green."""
    x = np.clip(residual / 0.05, 0.0, 1.0)
    r = np.clip(2 * x - 0.5, 0, 1)
    g = 1 - np.abs(2 * x - 1) * 0.8
    b = np.clip(1.5 - 2 * x, 0, 1)
    return (np.stack([r, g, b], axis=1) * 255).astype(np.uint8)


def _wire_sphere(n_lat: int = 8, n_lon: int = 12, k: int = 32) -> np.ndarray:
    """Unit-sphere wireframe as (S, 2, 3) line segments (parallels and meridians)."""
    segs = []
    t = np.linspace(0, 2 * np.pi, k + 1)
    for lat in np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)[1:-1]:
        ring = np.stack([np.cos(lat) * np.cos(t), np.cos(lat) * np.sin(t), np.full_like(t, np.sin(lat))], 1)
        segs.append(np.stack([ring[:-1], ring[1:]], 1))
    p = np.linspace(-np.pi / 2, np.pi / 2, k + 1)
    for lon in np.linspace(0, 2 * np.pi, n_lon, endpoint=False):
        arc = np.stack([np.cos(p) * np.cos(lon), np.cos(p) * np.sin(lon), np.sin(p)], 1)
        segs.append(np.stack([arc[:-1], arc[1:]], 1))
    return np.concatenate(segs).astype(np.float32)


UNIT_SPHERE = _wire_sphere()


@dataclass(frozen=True)
class RouteFrame:
    """North/east metres -> viser units of the route area (centred on the world origin, the
    along-track axis on screen left to right).

    With a preset line A->B: along-track scaled so A..B spans ``length`` units (A left, B right),
    cross-track (+ right of A->B, drawn towards the camera) exaggerated by ``cross_scale`` units
    per metre.  Without one: north up (+x), east right (-y), uniformly scaled to fit.
    """
    origin_ne: np.ndarray            # metres: where along = 0 (line A, or the route's centre)
    axis_ne: np.ndarray | None       # unit A->B (north, east), None: map view
    along_offset_m: float
    scale: float                     # units per metre along
    cross_scale: float               # units per metre across (line) or = scale (map)

    @staticmethod
    def for_line(a_ne, b_ne, route_ne: np.ndarray, length: float, max_cross: float,
                 cross_units_per_m: float) -> "RouteFrame":
        a, b = np.asarray(a_ne, float), np.asarray(b_ne, float)
        span = float(np.linalg.norm(b - a)) or 1.0
        u = (b - a) / span
        cross_scale = cross_units_per_m
        if len(route_ne):
            rel = route_ne - a
            worst = float(np.nanmax(np.abs(rel[:, 0] * -u[1] + rel[:, 1] * u[0]), initial=0.0))
            if worst * cross_scale > max_cross:
                cross_scale = max_cross / worst
        return RouteFrame(a, u, span / 2, length / span, cross_scale)

    @staticmethod
    def for_map(route_ne: np.ndarray, width: float, height: float, min_span_m: float) -> "RouteFrame":
        lo, hi = route_ne.min(axis=0), route_ne.max(axis=0)
        ext = np.maximum(hi - lo, 1e-9)
        scale = min(width / max(ext[1], min_span_m), height / max(ext[0], min_span_m))
        return RouteFrame((hi + lo) / 2, None, 0.0, scale, scale)

    def to_viser(self, ne: np.ndarray) -> np.ndarray:
        rel = np.asarray(ne, float).reshape(-1, 2) - self.origin_ne
        if self.axis_ne is None:
            x, y = rel[:, 0] * self.scale, -rel[:, 1] * self.scale
        else:
            u = self.axis_ne
            along = (rel @ u - self.along_offset_m) * self.scale
            right = (rel[:, 0] * -u[1] + rel[:, 1] * u[0]) * self.cross_scale
            x, y = -right, -along
        return np.stack([x, y, np.zeros(len(rel))], axis=1)

    @property
    def north_angle_rad(self) -> float:
        """Rotation about +z that takes viser north (+x) to this frame's north direction."""
        if self.axis_ne is None:
            return 0.0
        un, ue = self.axis_ne
        return math.atan2(-un, ue)


def camera_for_box(center, half_extents, elevation_deg: float, fov_v_rad: float, aspect: float,
                   margin: float = 1.1) -> tuple[np.ndarray, np.ndarray]:
    """(position, look_at) of a camera looking north and down by ``elevation_deg`` at a box, far
    enough that every corner is on screen (perspective, vertical fov, width/height ``aspect``)."""
    c = np.asarray(center, float)
    h = np.asarray(half_extents, float)
    el = math.radians(elevation_deg)
    d = np.array([math.cos(el), 0.0, -math.sin(el)])          # view direction
    up = np.array([math.sin(el), 0.0, math.cos(el)])
    right = np.array([0.0, -1.0, 0.0])
    tv = math.tan(fov_v_rad / 2)
    th = tv * max(aspect, 0.1)
    need = 0.0
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                p = h * np.array([sx, sy, sz]) * margin
                w = float(p @ d)
                need = max(need, abs(float(p @ right)) / th - w, abs(float(p @ up)) / tv - w)
    dist = max(need, 1.0)
    return c - dist * d, c
