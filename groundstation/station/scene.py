"""The viser 3-D view of a session.

Three areas in one scene (viser world: x north, y west, z up, i.e. NED with y and z flipped):
  * the vehicle at the origin: a body whose attitude follows the station's estimate, and a
    translucent ghost of the autopilot's own attitude, shown when the two differ by > 2 deg;
  * the calibration (to the right): raw points scaled by the fitted field (so ~unit size),
    coloured by residual | |m_cal| - F | / F, the fitted ellipsoid wireframe, and the corrected
    points on a unit sphere beside them;
  * the route (to the left): flown track against the preset line, segments red while an alarm
    was active.
GUI: an alarm banner and uPlot plots (headings, forward/lateral velocity, cross-track).
All updates of one frame go in one ``server.atomic()`` block, at UPDATE_HZ.  The cloud is
decimated to CLOUD_DISPLAY_POINTS for display only (the fit uses every sample).
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import viser
from viser import uplot

from groundstation.station.hub.session import Session

UPDATE_HZ = 15.0
CLOUD_DISPLAY_POINTS = 6000
ROUTE_DISPLAY_POINTS = 6000
# Layout (viser world, camera looking north from the south; the GUI panel covers the right):
VEHICLE_AT = np.array([0.0, 7.5, 0.0])
CAL_CENTER = np.array([0.0, 2.5, 1.5])
SPHERE_CENTER = np.array([0.0, 5.0, 1.5])
ROUTE_CENTER = np.array([8.0, 4.0, 0.0])
ROUTE_SIZE = 9.0                               # the route is scaled to fit this many units
ROUTE_MIN_SPAN_M = 20.0                        # ... but a hover's GPS noise is not blown up
CROSS_UNITS_PER_M = 0.3                        # cross-track exaggeration against a preset line
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
NOT_TIME = {"x": uplot.Scale(time=False)}     # x is log seconds, not a date


def _plottable(t: np.ndarray, series: list[np.ndarray]) -> tuple | None:
    """uPlot cannot scale an axis holding NaN: keep the rows where some series is finite and
    hold each series' last finite value across its gaps (None when nothing is finite)."""
    keep = np.any([np.isfinite(c) for c in series], axis=0)
    if keep.sum() < 2:
        return None
    out = [t[keep]]
    for c in series:
        c = c[keep]
        ok = np.isfinite(c)
        if not ok.any():
            c = np.zeros_like(c)
        else:
            idx = np.where(ok, np.arange(len(c)), 0)
            np.maximum.accumulate(idx, out=idx)
            c = c[idx]
            c[: int(np.argmax(ok))] = c[int(np.argmax(ok))]
        out.append(c)
    return tuple(out)


COVERAGE_CENTER = np.array([0.0, 1.3, 3.4])           # above right of the calibration clouds


class CoverageSphere:
    """Handle of the calibration's covered field directions: the centres of the 100 equal-area
    cells (estimators.calibration.coverage_cells; body FRD drawn in viser axes), green once seen."""

    def __init__(self, scene, position: np.ndarray, radius: float = 0.6) -> None:
        band, sector = np.divmod(np.arange(100), 10)
        z = -1.0 + (band + 0.5) * 0.2
        lon = (sector + 0.5) * 2 * np.pi / 10 - np.pi
        r = np.sqrt(1 - z * z)
        self._points = (np.stack([r * np.cos(lon), r * np.sin(lon), z], 1) @ S_FLIP * radius).astype(np.float32)
        self._key = None
        self.cloud = scene.add_point_cloud("/coverage", self._points, colors=(200, 200, 200), point_size=0.07,
                                           point_shape="circle", position=tuple(position), visible=False)
        self.label = scene.add_label("/coverage_label", "directions covered", position=tuple(position + [0, 0, 0.85]),
                                     visible=False)

    def update(self, cells: np.ndarray | None) -> None:
        key = None if cells is None else bytes(np.asarray(cells, bool))
        if key == self._key:
            return
        self._key = key
        self.cloud.visible = self.label.visible = cells is not None
        if cells is not None:
            seen = np.asarray(cells, bool)[:, None]
            self.cloud.colors = np.where(seen, [[67, 160, 71]], [[200, 200, 200]]).astype(np.uint8)


def add_coverage_sphere(scene, position: np.ndarray = COVERAGE_CENTER) -> CoverageSphere:
    return CoverageSphere(scene, position)


class Scene:
    def __init__(self, session: Session, host: str = "127.0.0.1", port: int = 8080) -> None:
        self.session = session
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.red_segments = 0          # route points drawn red in the last frame (tests read it)
        self.cloud_points_shown = 0
        self.frames = 0
        self._cloud_key = self._route_key = None
        self._build()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="scene")
        self._thread.start()

    # ------------------------------------------------------------------------------ building
    def _build(self) -> None:
        sc, gui = self.server.scene, self.server.gui
        sc.set_up_direction("+z")
        sc.configure_fog(100.0, 1000.0, enabled=False)
        self.server.initial_camera.position = (-6.5, 1.8, 6.5)
        self.server.initial_camera.look_at = (3.0, 1.8, 0.0)
        sc.add_grid("/ground", width=30, height=30, cell_size=1.0, position=(4, 4, -1.0))
        self.vehicle = sc.add_frame("/vehicle", axes_length=1.2, axes_radius=0.03, position=tuple(VEHICLE_AT))
        sc.add_box("/vehicle/body", color=(60, 110, 200), dimensions=(1.6, 0.5, 0.15))
        sc.add_box("/vehicle/arms", color=(70, 70, 70), dimensions=(0.12, 2.0, 0.06))
        sc.add_box("/vehicle/nose", color=(230, 80, 40), dimensions=(0.25, 0.25, 0.2), position=(0.85, 0, 0))
        self.ghost = sc.add_frame("/ghost", show_axes=False, position=tuple(VEHICLE_AT))
        sc.add_box("/ghost/body", color=(200, 200, 200), dimensions=(1.6, 0.5, 0.15), opacity=0.35)
        sc.add_label("/vehicle_label", "vehicle (grey ghost: autopilot)", position=tuple(VEHICLE_AT + [0, 0, 1.4]))

        self.cal_labels = [
            sc.add_label("/cal_label", "raw field + fitted ellipsoid", position=tuple(CAL_CENTER + [0, 0, 1.6]),
                         visible=False),
            sc.add_label("/sphere_label", "corrected", position=tuple(SPHERE_CENTER + [0, 0, 1.6]), visible=False)]
        sc.add_line_segments("/sphere_ref", UNIT_SPHERE, colors=(150, 150, 150), thickness=1.0,
                             thickness_units="screen", position=tuple(SPHERE_CENTER))
        empty = np.zeros((1, 3), dtype=np.float32)
        self.cloud = sc.add_point_cloud("/cal_raw", empty, colors=(0, 0, 0), point_size=0.03,
                                        position=tuple(CAL_CENTER), visible=False)
        self.corrected = sc.add_point_cloud("/cal_corrected", empty, colors=(40, 160, 60), point_size=0.03,
                                            position=tuple(SPHERE_CENTER), visible=False)
        self.ellipsoid = sc.add_line_segments("/cal_ellipsoid", UNIT_SPHERE, colors=(240, 180, 0),
                                              thickness=1.5, thickness_units="screen",
                                              position=tuple(CAL_CENTER), visible=False)

        self.coverage = add_coverage_sphere(sc)
        self.route_label = sc.add_label("/route_label", "route vs preset line (blue), red: alarm",
                                        position=tuple(ROUTE_CENTER + [0, 0, 1.0]))
        seg0 = np.zeros((1, 2, 3), dtype=np.float32)
        self.route = sc.add_point_cloud("/route", empty, colors=(30, 30, 30), point_size=0.05,
                                        point_shape="circle", position=tuple(ROUTE_CENTER), visible=False)
        self.line = sc.add_line_segments("/preset_line", seg0, colors=(40, 120, 255), thickness=2.0,
                                         thickness_units="screen", position=tuple(ROUTE_CENTER), visible=False)

        self.banner = gui.add_html(self._banner_html(False, ""))
        with gui.add_folder("Plots"):
            x = np.zeros(1)
            self.plot_heading = gui.add_uplot(
                (x, x, x), (uplot.Series(label="t (s)"),
                            uplot.Series(label="magnetic hdg", stroke="red", width=2),
                            uplot.Series(label="attitude hdg", stroke="blue", width=2)),
                title="Heading (deg)", aspect=2.0, scales=NOT_TIME)
            self.plot_vel = gui.add_uplot(
                (x, x, x), (uplot.Series(label="t (s)"),
                            uplot.Series(label="forward", stroke="green", width=2),
                            uplot.Series(label="lateral", stroke="purple", width=2)),
                title="Velocity (m/s)", aspect=2.0, scales=NOT_TIME)
            self.plot_xt = gui.add_uplot(
                (x, x), (uplot.Series(label="t (s)"), uplot.Series(label="cross-track", stroke="black", width=2)),
                title="Cross-track (m)", aspect=2.0, scales=NOT_TIME)

    @staticmethod
    def _banner_html(active: bool, text: str) -> str:
        if active:
            return ('<div id="alarm-banner" style="background:#c00;color:#fff;padding:8px;font-weight:bold;'
                    f'border-radius:4px">MAGNETIC INTERFERENCE ALARM {text}</div>')
        return ('<div id="alarm-banner" style="background:#1a7f37;color:#fff;padding:8px;border-radius:4px">'
                'No interference alarm</div>')

    # ------------------------------------------------------------------------------ updating
    def _loop(self) -> None:
        period = 1.0 / UPDATE_HZ
        last_alarm = None
        while not self._stop.wait(period):
            try:
                data = self.session.scene_data()
                with self.server.atomic():
                    self._update(data)
                    key = (data["alarm"], data["alarm_text"])
                    if key != last_alarm:
                        last_alarm = key
                        self.banner.content = self._banner_html(*key)
                self.frames += 1
            except Exception:  # a drawing error must never stop the station
                time.sleep(0.5)

    def _update(self, d: dict) -> None:
        roll, pitch, yaw = d["att"]
        if all(map(math.isfinite, (roll, pitch, yaw))):
            self.vehicle.wxyz = attitude_wxyz(roll, pitch, yaw)
        ap = d["ap_att"]
        if all(map(math.isfinite, ap)):
            self.ghost.wxyz = attitude_wxyz(*ap)
            differs = not all(map(math.isfinite, (roll, pitch, yaw))) or max(
                abs(math.remainder(a - b, 2 * math.pi)) for a, b in zip(ap, (roll, pitch, yaw))) > math.radians(2)
            self.ghost.visible = differs
        self._update_cloud(d["cloud"], d["fit"])
        self.coverage.update(d.get("coverage"))
        for label in self.cal_labels:
            label.visible = self.cloud.visible
        # the calibration clouds stand in front of the route: hide the route while calibrating
        if d["calibrating"]:
            self.route.visible = self.line.visible = self.route_label.visible = False
            self._route_key = None
        else:
            self.route_label.visible = True
            self._update_route(d["route"], d["line"], d["origin"])
        self._update_plots(d["history"])

    def _update_cloud(self, cloud: np.ndarray, fit: dict | None) -> None:
        key = (len(cloud), None if fit is None else (tuple(fit["offsets_mG"]), fit["field_mG"]))
        if key == self._cloud_key:      # nothing new: do not resend the points
            return
        self._cloud_key = key
        if len(cloud) < 3:
            self.cloud.visible = self.corrected.visible = self.ellipsoid.visible = False
            self.cloud_points_shown = 0
            return
        step = max(1, math.ceil(len(cloud) / CLOUD_DISPLAY_POINTS))
        pts = cloud[::step]
        if fit is not None:
            center = np.asarray(fit["offsets_mG"], dtype=float)
            field = float(fit["field_mG"] or np.median(np.linalg.norm(pts - center, axis=1)))
        else:
            center = (cloud.max(axis=0) + cloud.min(axis=0)) / 2
            field = float(np.median(np.linalg.norm(pts - center, axis=1))) or 1.0
        matrix = np.asarray(fit["matrix"], dtype=float) if fit is not None and fit.get("matrix") else None
        rel = (pts - center) / field
        corrected = rel @ matrix.T if matrix is not None else rel
        residual = np.abs(np.linalg.norm(corrected, axis=1) - 1.0)
        self.cloud.points = (rel @ S_FLIP).astype(np.float32)
        self.cloud.colors = residual_colors(residual)
        self.cloud.visible = True
        self.cloud_points_shown = len(pts)
        if fit is not None:
            self.corrected.points = (corrected @ S_FLIP).astype(np.float32)
            self.corrected.visible = True
            inv = np.linalg.inv(matrix) if matrix is not None else np.eye(3)
            ell = UNIT_SPHERE.reshape(-1, 3) @ inv.T
            self.ellipsoid.points = (ell @ S_FLIP).reshape(-1, 2, 3).astype(np.float32)
            self.ellipsoid.visible = True
        else:
            self.corrected.visible = self.ellipsoid.visible = False

    def _update_route(self, route: np.ndarray, line: dict | None, origin) -> None:
        """Route in the preset line's frame: along-track scaled to ROUTE_SIZE, cross-track
        exaggerated (CROSS_UNITS_PER_M) so metre-level deviations over a long leg show."""
        key = (len(route), route[-1, 3] if len(route) else None, None if line is None else
               (tuple(line["a"]), tuple(line["b"])), origin)
        if key == self._route_key:
            return
        self._route_key = key
        pts_ne = route[:, 1:3]
        if line is not None and origin is not None:
            from groundstation.station.hub.flight import local_ne_m
            a = np.array(local_ne_m(line["a"][0], line["a"][1], origin))
            b = np.array(local_ne_m(line["b"][0], line["b"][1], origin))
            length = float(np.linalg.norm(b - a)) or 1.0
            u = (b - a) / length
            scale = ROUTE_SIZE / max(length, ROUTE_MIN_SPAN_M)

            def to_viser(ne: np.ndarray) -> np.ndarray:
                rel = ne - a
                along = (rel @ u - length / 2) * scale
                cross = (rel[:, 0] * u[1] - rel[:, 1] * u[0]) * -1.0   # + right of A->B
                # viser y is left: right-of-line goes to -y
                return np.stack([along, -cross * CROSS_UNITS_PER_M, np.zeros(len(ne))], axis=1)

            self.line.points = to_viser(np.array([a, b])).reshape(1, 2, 3).astype(np.float32)
            self.line.visible = True
        elif len(pts_ne) >= 2:
            center = (pts_ne.max(axis=0) + pts_ne.min(axis=0)) / 2
            scale = ROUTE_SIZE / max(float(np.max(pts_ne.max(axis=0) - pts_ne.min(axis=0))), ROUTE_MIN_SPAN_M)

            def to_viser(ne: np.ndarray) -> np.ndarray:
                ne = (ne - center) * scale
                return np.stack([ne[:, 0], -ne[:, 1], np.zeros(len(ne))], axis=1)

            self.line.visible = False
        else:
            self.route.visible = self.line.visible = False
            self.red_segments = 0
            return
        if len(route) >= 2:
            # drawn as a dense point cloud: per-point colours update live (the viser 1.1 client
            # does not redraw per-segment colours changed on a line-segments node)
            step = max(1, math.ceil(len(route) / ROUTE_DISPLAY_POINTS))
            idx = np.unique(np.r_[np.arange(0, len(route), step), len(route) - 1])
            alarm = route[idx, 3] > 0.5
            colors = np.where(alarm[:, None], np.array([220, 0, 0]), np.array([30, 30, 30])).astype(np.uint8)
            self.route.points = to_viser(pts_ne[idx]).astype(np.float32)
            self.route.colors = colors
            self.route.visible = True
            self.red_segments = int(alarm.sum())
        else:
            self.route.visible = False
            self.red_segments = 0

    def _update_plots(self, hist: np.ndarray) -> None:
        if len(hist) < 2:
            return
        t = hist[:, 0]
        col = [hist[:, i].copy() for i in range(1, 6)]
        # headings unwrapped (no 0/360 saw-tooth), the newest attitude heading in [0, 360), the
        # magnetic heading drawn as attitude + their wrapped difference (the two stay together)
        mag, att = col[0], col[1]
        ok = np.isfinite(att)
        if ok.any():
            u = np.degrees(np.unwrap(np.radians(att[ok])))
            att[ok] = u - 360.0 * np.floor(u[-1] / 360.0)
            base = att.copy()
            idx = np.where(ok, np.arange(len(att)), 0)
            np.maximum.accumulate(idx, out=idx)
            base = base[idx]
            base[: int(np.argmax(ok))] = base[int(np.argmax(ok))]
            mag[:] = base + (mag - base + 180.0) % 360.0 - 180.0
        for handle, series in ((self.plot_heading, col[0:2]), (self.plot_vel, col[2:4]),
                               (self.plot_xt, col[4:5])):
            data = _plottable(t, series)
            if data is not None:
                handle.data = data

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.server.stop()
