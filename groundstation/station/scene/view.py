"""The viser 3-D view of a session, framed for what the operator is doing.

Two activities, each with its own camera (set for every browser as it connects and whenever the
activity changes, fitted to the browser's aspect ratio; ``camera_for_box``):
  * calibration (the wizard is running or has a result): the vehicle, the raw field points
    coloured by residual with the fitted ellipsoid, and the corrected points on a unit sphere,
    side by side;
  * flight: the route against the preset line, the line scaled to fill the view (A left, B
    right, cross-track exaggerated), or without a line the route fitted to the view north up;
    the vehicle rides on the route at its last position.
The vehicle (orange, dark red nose) follows the station's attitude estimate; a translucent grey
ghost shows the autopilot's own when the two differ by more than 2 deg.  Route points are violet,
red while an alarm was on; the preset line is cyan; an amber marker stands where an ended alarm was
explained as a magnetic anomaly fixed in place.  All updates of a frame go in one
``server.atomic()`` block at UPDATE_HZ; the cloud and route are decimated for display only.
"""
from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np
import viser

from estimators.detection import ned_from_lla

from groundstation.station.hub.session import Session
from groundstation.station.scene.coverage import CoverageSphere
from groundstation.station.scene.geometry import (S_FLIP, UNIT_SPHERE, RouteFrame, attitude_wxyz, camera_for_box,
                                                  quat_mul, residual_colors, yaw_wxyz)

log = logging.getLogger(__name__)
UPDATE_HZ = 15.0
# a browser's reported pose is checked against the framing sent from this long after sending until
# this long: before, its report may predate ours; after, a different pose is the user's drag
REFRAME_CHECK_S = (0.5, 4.0)
CLOUD_DISPLAY_POINTS = 6000
ROUTE_DISPLAY_POINTS = 6000
# calibration layout (viser units): vehicle, raw cloud, corrected sphere left to right
CAL_VEHICLE_AT = np.array([0.0, 2.8, 0.0])
CAL_CENTER = np.array([0.0, 0.0, 0.0])
SPHERE_CENTER = np.array([0.0, -2.8, 0.0])
# the middle label goes below its cloud, the outer two above theirs: apart in a narrow view too
RAW_LABEL_AT = np.array([0.0, 0.0, -1.5])
CAL_BOX = (np.array([0.0, 0.0, 0.2]), np.array([1.4, 4.1, 1.6]))         # centre, half extents
# flight layout: the route area centred on the origin
ROUTE_LENGTH = 8.0                 # the preset line (or the route's width) spans this many units
ROUTE_MAX_CROSS = 2.0              # cross-track drawn at most this far from the line
ROUTE_MIN_SPAN_M = 20.0            # a hover's GPS noise is not blown up
CROSS_UNITS_PER_M = 0.3            # cross-track exaggeration against a preset line
FLIGHT_BOX = (np.array([0.0, 0.0, 0.2]), np.array([2.0, 4.4, 0.4]))
FLIGHT_VEHICLE_SCALE = 0.4          # the model ~8 % of the route's width (full size it hid a fifth of it)
ELEVATION_DEG = {"calibration": 22.0, "flight": 55.0}
VEHICLE_ORANGE = (240, 130, 20)
NOSE_RED = (170, 20, 20)
ROUTE_VIOLET = (120, 50, 190)
ALARM_RED = (230, 0, 0)
LINE_CYAN = (0, 190, 225)
ANOMALY_AMBER = (255, 170, 0)

__all__ = ["Scene", "CLOUD_DISPLAY_POINTS", "ROUTE_DISPLAY_POINTS"]


class _NoHalfOpenConnections(logging.Filter):
    """A connection to the 3-D view's port that closes before its request (a port probe, a
    browser's preconnect) is nothing to report: the websockets server logged it with a traceback
    until viser installed the same filter on the first request it served."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "opening handshake failed"


logging.getLogger("websockets.server").addFilter(_NoHalfOpenConnections())


class Scene:
    def __init__(self, session: Session, host: str = "127.0.0.1", port: int = 8080) -> None:
        self.session = session
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self.red_segments = 0          # route points drawn red in the last frame (tests read it)
        self.cloud_points_shown = 0
        self.route_points_shown = 0
        self.anomalies_shown = 0       # anomaly markers drawn (tests read it)
        self.frames = 0
        self.activity = "flight"
        # client id -> (activity, aspect) its camera was framed for, the pose sent and when
        self._framed: dict[int, tuple[tuple[str, float], np.ndarray, np.ndarray, float]] = {}
        self._cloud_key = self._route_key = None
        self._route_frame: RouteFrame | None = None
        self._build()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(lambda c: self._framed.pop(c.client_id, None))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="scene")
        self._thread.start()

    # ------------------------------------------------------------------------------ building
    def _build(self) -> None:
        sc = self.server.scene
        sc.set_up_direction("+z")
        sc.configure_fog(100.0, 1000.0, enabled=False)
        # no shadow maps: they add render passes to every frame for shadows nobody reads here. Without
        # a GPU (Chromium's software WebGL) the idle view cost 0.39 of a core with them, 0.08 without
        sc.configure_default_lights(enabled=True, cast_shadow=False)
        self.server.gui.configure_theme(control_width="small", show_logo=False, show_share_button=False)
        self.server.gui.add_markdown("MagStation 3-D view: the camera follows the activity (calibration or "
                                     "flight); drag to look around.")
        self.server.gui.main_panel.minimize()
        pos, look = camera_for_box(*FLIGHT_BOX, ELEVATION_DEG["flight"], math.radians(60), 16 / 9)
        self.server.initial_camera.fov = math.radians(60)
        self.server.initial_camera.position = tuple(pos)
        self.server.initial_camera.look_at = tuple(look)
        self.grid = sc.add_grid("/ground", width=12, height=8, cell_size=1.0, position=(0, 0, -1.0))
        # two models (viser 1.x frames have no scale): full size beside the calibration cloud, and
        # FLIGHT_VEHICLE_SCALE of it on the route, so the vehicle marks its place without hiding the route
        self.crafts = {"calibration": self._add_craft(sc, "/craft", 1.0, CAL_VEHICLE_AT),
                       "flight": self._add_craft(sc, "/flight_craft", FLIGHT_VEHICLE_SCALE, (0.0, 0.0, 0.3))}
        self.crafts["flight"][0].visible = False
        self.craft, self.vehicle, self.ghost = self.crafts["calibration"]
        self.vehicle_label = sc.add_label("/craft/label", "vehicle", position=(0, 0, 1.3), anchor="bottom-center")
        # above the vehicle's own label, running right from its left end: below the vehicle it met the
        # raw cloud's label, centred it ran off the left edge of a narrow view
        self.ghost_label = sc.add_label("/craft/ghost_label", "grey: autopilot's attitude",
                                        position=(0, 0.8, 1.9), anchor="bottom-left", visible=False)
        empty = np.zeros((1, 3), dtype=np.float32)
        self.cal_nodes = [
            sc.add_label("/cal_label", "raw field + fitted ellipsoid", position=tuple(CAL_CENTER + RAW_LABEL_AT),
                         anchor="top-center", visible=False),
            sc.add_label("/sphere_label", "corrected", position=tuple(SPHERE_CENTER + [0, 0, 1.3]),
                         anchor="bottom-center", visible=False),
            sc.add_line_segments("/sphere_ref", UNIT_SPHERE, colors=(150, 150, 150), thickness=1.0,
                                 thickness_units="screen", position=tuple(SPHERE_CENTER), visible=False)]
        self.cloud = sc.add_point_cloud("/cal_raw", empty, colors=(0, 0, 0), point_size=0.035,
                                        position=tuple(CAL_CENTER), visible=False)
        self.corrected = sc.add_point_cloud("/cal_corrected", empty, colors=(40, 160, 60), point_size=0.035,
                                            position=tuple(SPHERE_CENTER), visible=False)
        self.ellipsoid = sc.add_line_segments("/cal_ellipsoid", UNIT_SPHERE, colors=(240, 180, 0),
                                              thickness=1.5, thickness_units="screen",
                                              position=tuple(CAL_CENTER), visible=False)
        self.coverage = CoverageSphere(sc, SPHERE_CENTER)      # the directions covered, on the corrected sphere
        seg0 = np.zeros((1, 2, 3), dtype=np.float32)
        self.route = sc.add_point_cloud("/route", empty, colors=ROUTE_VIOLET, point_size=0.07,
                                        point_shape="circle", visible=False)
        self.line = sc.add_line_segments("/preset_line", seg0, colors=LINE_CYAN, thickness=4.0,
                                         thickness_units="screen", visible=False)
        self.anomalies = sc.add_point_cloud("/anomalies", empty, colors=ANOMALY_AMBER, point_size=0.3,
                                            point_shape="diamond", visible=False)
        self.anomaly_label = sc.add_label("/anomaly_label", "magnetic anomaly", position=(0, 0, 0),
                                          anchor="bottom-center", visible=False)
        self.line_labels = [sc.add_label(f"/line_{k}", k, position=(0, 0, 0), anchor="bottom-center", visible=False)
                            for k in ("A", "B")]

    @staticmethod
    def _add_craft(sc, name: str, k: float, at) -> tuple:
        """Vehicle model (orange body, grey arms, dark red nose, axes) and the autopilot's ghost,
        ``k`` times full size: (frame, vehicle, ghost)."""
        frame = sc.add_frame(name, show_axes=False, position=tuple(at))
        vehicle = sc.add_frame(f"{name}/vehicle", axes_length=1.0 * k, axes_radius=0.025 * k)
        sc.add_box(f"{name}/vehicle/body", color=VEHICLE_ORANGE, dimensions=(1.6 * k, 0.5 * k, 0.18 * k))
        sc.add_box(f"{name}/vehicle/arms", color=(60, 60, 60), dimensions=(0.12 * k, 2.0 * k, 0.06 * k))
        sc.add_box(f"{name}/vehicle/nose", color=NOSE_RED, dimensions=(0.3 * k, 0.3 * k, 0.22 * k),
                   position=(0.85 * k, 0, 0))
        ghost = sc.add_frame(f"{name}/ghost", show_axes=False, visible=False)
        sc.add_box(f"{name}/ghost/body", color=(200, 200, 200), dimensions=(1.6 * k, 0.5 * k, 0.15 * k), opacity=0.35)
        return frame, vehicle, ghost

    # ------------------------------------------------------------------------------ cameras
    def _on_connect(self, client: viser.ClientHandle) -> None:
        self._framed.pop(client.client_id, None)      # framed by the loop once its camera reports

    def _frame_clients(self) -> None:
        """Point every browser whose camera shows another activity at the current one."""
        for cid, client in list(self.server.get_clients().items()):
            try:
                cam = client.camera
                aspect = cam.aspect if cam.image_height else 16 / 9
                fov = cam.fov or math.radians(60)
            except AssertionError:      # its camera has not reported yet
                continue
            # framed again when the activity changes or the view's shape does (the page lays out
            # after its first camera report; a window resized): a drag alone keeps the user's view
            framing = (self.activity, round(aspect, 2))
            done = self._framed.get(cid)
            same = done is not None and done[0] == framing
            if same and not self._pose_lost(cam, *done[1:]):
                continue
            box = CAL_BOX if self.activity == "calibration" else FLIGHT_BOX
            pos, look = camera_for_box(*box, ELEVATION_DEG[self.activity], fov, aspect)
            cam.up_direction = (0.0, 0.0, 1.0)
            cam.position = tuple(pos)
            cam.look_at = tuple(look)
            self._framed[cid] = (framing, pos, look, done[3] if same else time.monotonic())

    @staticmethod
    def _pose_lost(cam, pos: np.ndarray, look: np.ndarray, sent_s: float) -> bool:
        """The browser reports a pose other than the one first sent ``sent_s`` ago, within the first
        seconds after sending (on a loaded machine the viewer's own start-up camera can land after
        ours): send it again.  Later a different pose is the user's drag, and kept."""
        age_s = time.monotonic() - sent_s
        if not REFRAME_CHECK_S[0] <= age_s <= REFRAME_CHECK_S[1]:
            return False
        scale = max(float(np.linalg.norm(pos - look)), 1e-6)
        return (float(np.linalg.norm(np.asarray(cam.position) - pos)) > 0.02 * scale
                or float(np.linalg.norm(np.asarray(cam.look_at) - look)) > 0.02 * scale)

    # ------------------------------------------------------------------------------ updating
    def _loop(self) -> None:
        period = 1.0 / UPDATE_HZ
        while not self._stop.wait(period):
            try:
                data = self.session.scene_data()
                with self.server.atomic():
                    self._update(data)
                self._frame_clients()
                self.frames += 1
            except Exception:  # a drawing error must never stop the station
                log.exception("3-D view update failed")
                time.sleep(0.5)

    def _update(self, d: dict) -> None:
        activity = "calibration" if d["calibrating"] else "flight"
        if activity != self.activity:
            self.activity = activity
            self._route_key = None
        calibrating = activity == "calibration"
        self._update_cloud(d["cloud"], d["fit"], calibrating)
        self.coverage.update(d.get("coverage") if calibrating else None)
        for node in self.cal_nodes:
            node.visible = calibrating
        self.vehicle_label.visible = calibrating
        if calibrating:
            self.route.visible = self.line.visible = self.anomalies.visible = self.anomaly_label.visible = False
            for label in self.line_labels:
                label.visible = False
            north = 0.0
        else:
            north = self._update_route(d["route"], d["line"], d["origin"], d["anomalies"])
        self.crafts["calibration"][0].visible = calibrating
        self.crafts["flight"][0].visible = not calibrating
        self._update_attitude(d["att"], d["ap_att"], north)

    def _update_attitude(self, att, ap, north_rad: float) -> None:
        frame = yaw_wxyz(north_rad)
        _, vehicle, ghost = self.crafts[self.activity]
        ok = all(map(math.isfinite, att))
        if ok:
            vehicle.wxyz = quat_mul(frame, attitude_wxyz(*att))
        differs = False
        if all(map(math.isfinite, ap)):
            ghost.wxyz = quat_mul(frame, attitude_wxyz(*ap))
            differs = not ok or max(abs(math.remainder(a - b, 2 * math.pi)) for a, b in zip(ap, att)) > math.radians(2)
        ghost.visible = differs
        self.ghost_label.visible = differs and self.activity == "calibration"

    def _update_cloud(self, cloud: np.ndarray, fit: dict | None, calibrating: bool) -> None:
        key = (len(cloud), tuple(cloud[-1]) if len(cloud) else None,       # a sliding window keeps its length
               None if fit is None else (tuple(fit["offsets_mG"]), fit["field_mG"]), calibrating)
        if key == self._cloud_key:      # nothing new: do not resend the points
            return
        self._cloud_key = key
        if len(cloud) < 3 or not calibrating:
            self.cloud.visible = self.corrected.visible = self.ellipsoid.visible = False
            self.cloud_points_shown = 0 if len(cloud) < 3 else self.cloud_points_shown
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

    def _update_route(self, route: np.ndarray, line: dict | None, origin, anomalies_ne: np.ndarray) -> float:
        """Route, line and anomaly markers in the route area; the vehicle at the last fix.
        Returns the frame's north angle (the vehicle's yaw is drawn in it)."""
        key = (len(route), route[-1, 3] if len(route) else None,
               None if line is None else (tuple(line["a"]), tuple(line["b"])), origin, len(anomalies_ne))
        if key != self._route_key:
            self._route_key = key
            self._route_frame = self._draw_route(route, line, origin)
            self._draw_anomalies(anomalies_ne, self._route_frame)
        frame, craft = self._route_frame, self.crafts["flight"][0]
        if frame is not None and len(route):
            craft.position = tuple(frame.to_viser(route[-1:, 1:3])[0] + [0, 0, 0.1])
        else:
            craft.position = (0.0, 0.0, 0.1)
        return frame.north_angle_rad if frame is not None else 0.0

    def _draw_route(self, route: np.ndarray, line: dict | None, origin) -> RouteFrame | None:
        ne = route[:, 1:3]
        if line is not None and origin is not None:
            a = np.array(ned_from_lla(line["a"][0], line["a"][1], origin[0], origin[1]), dtype=float)
            b = np.array(ned_from_lla(line["b"][0], line["b"][1], origin[0], origin[1]), dtype=float)
            frame = RouteFrame.for_line(a, b, ne, ROUTE_LENGTH, ROUTE_MAX_CROSS, CROSS_UNITS_PER_M)
            ends = frame.to_viser(np.array([a, b]))
            self.line.points = ends.reshape(1, 2, 3).astype(np.float32)
            self.line.visible = True
            for label, p in zip(self.line_labels, ends):
                label.position = tuple(p + [0, 0, 0.25])
                label.visible = True
        elif len(ne) >= 2:
            frame = RouteFrame.for_map(ne, ROUTE_LENGTH, ROUTE_LENGTH / 2, ROUTE_MIN_SPAN_M)
            self.line.visible = False
            for label in self.line_labels:
                label.visible = False
        else:
            self.route.visible = self.line.visible = False
            self.red_segments = self.route_points_shown = 0
            return None
        if len(route) >= 2:
            step = max(1, math.ceil(len(route) / ROUTE_DISPLAY_POINTS))
            idx = np.unique(np.r_[np.arange(0, len(route), step), len(route) - 1])
            alarm = route[idx, 3] > 0.5
            self.route.points = frame.to_viser(ne[idx]).astype(np.float32)
            self.route.colors = np.where(alarm[:, None], np.array(ALARM_RED), np.array(ROUTE_VIOLET)).astype(np.uint8)
            self.route.visible = True
            self.red_segments = int(alarm.sum())
            self.route_points_shown = len(idx)
        else:
            self.route.visible = False
            self.red_segments = self.route_points_shown = 0
        return frame

    def _draw_anomalies(self, anomalies_ne: np.ndarray, frame: RouteFrame | None) -> None:
        shown = frame is not None and len(anomalies_ne) > 0
        if shown:
            at = frame.to_viser(anomalies_ne) + [0.0, 0.0, 0.15]
            self.anomalies.points = at.astype(np.float32)
            self.anomaly_label.position = tuple(at[0] + [0.0, 0.0, 0.3])
        self.anomalies.visible = self.anomaly_label.visible = shown
        self.anomalies_shown = len(anomalies_ne) if shown else 0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.server.stop()
