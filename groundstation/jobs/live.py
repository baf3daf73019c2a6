"""The live twin of ``analyze_flight``: the same inputs, chain, detector and record, per sample.

``LiveAnalyzer.on_sample(s)`` returns a flight-record row (``groundstation.jobs.record``) for each
IMU sample of the primary instance; its inputs are built by the functions ``detection_inputs``
uses (``groundstation.jobs.inputs``), its holds by ``Held`` (``hold_last`` on the latest value), so
a log streamed sample by sample gives the rows and alarms ``analyze_flight`` gives it at once.
A live stream is not in time order: the decoder times the IMU, compass and ATTITUDE on the
vehicle's boot clock, which runs up to seconds behind arrival on a radio link, and GPS_RAW_INT,
SYS_STATUS and VFR_HUD at arrival less the delay last measured on that clock, so a sample can
arrive after samples it precedes (a burst after a gap).  ``ReorderBuffer`` releases the samples
in time order once the stream has moved past them by the lateness it has seen (zero on a clean
link), which is the order a log reader sorts them into.
``GpsOutageWatch`` is the per-sample rule of ``groundstation.jobs.navigation.gps_outages``.
"""
from __future__ import annotations

import heapq
import itertools
import math
import time
from collections import deque
from types import SimpleNamespace

import numpy as np

from estimators.detection import DetectionSettings, InterferenceDetector
from estimators.field_consistency import FieldConsistency
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.heading import HeadingChain

from groundstation.io.decode import preferred_source
from groundstation.jobs.alarm_explain import SCORE_NAMES, ExplainHistory
from groundstation.jobs.field_forward import field_at_steps
from groundstation.jobs.inputs import (ATTITUDE_TIMEOUT_S, GPS_COLUMNS, GPS_TIMEOUT_S, MOTOR_TIMEOUT_S,
                                       RATE_WINDOW, FieldPolicy, Held, StepState, earth_prior_mG, field_policy,
                                       gps_rows, imu_rate_hz, mission_legs, step_inputs, vector_test_inputs)
from groundstation.jobs.navigation import OUTAGE_MIN_S
from groundstation.jobs.record import EVIDENCE, RECORD_COLUMNS, record_rows
from groundstation.samples import (AttitudeSample, BatterySample, GpsSample, ImuSample, MagSample, ParamSample,
                                   Sample, StatusSample, ThrottleSample)

__all__ = ["LiveAnalyzer", "GpsOutageWatch", "ReorderBuffer", "HeldReading", "MAX_REORDER_S"]

MAX_REORDER_S = 3.0         # samples later than this are processed out of order
STALL_WAIT_S = 0.1          # with no newer sample, one waits at least this long (wall time) for it
REORDER_MEMORY_S = 60.0     # the reorder delay forgets a lateness over this long (wall time)


class HeldReading(Held):
    """The compass held live (``Held``) with the time of its reading under
    ``field_forward.reading_times``' rule: a re-sent reading (the same field as sent, ``raw``)
    does not move it."""

    def __init__(self, timeout_s: float) -> None:
        super().__init__(3, timeout_s)
        self._read_t = math.nan
        self._raw: tuple | None = None

    def update(self, t_s: float, value, raw) -> None:
        if self._t is not None and float(t_s) < self._t:
            return
        raw = tuple(float(v) for v in np.asarray(raw, dtype=float).reshape(3))
        if raw != self._raw:
            self._read_t = float(t_s)
        self._raw = raw
        super().update(t_s, value)

    def reading_time_at(self, t_s: float) -> float:
        """The held field's reading time under ``at``'s rule (NaN when ``at`` gives NaN)."""
        return self._read_t if self.fresh(t_s) else math.nan


class LiveAnalyzer:
    """Per-sample form of ``analyze_flight`` for a live link (see module docstring).

    ``accepts(s)`` says whether a sample is of the primary magnetometer/IMU instance (the
    lowest instance number seen, as the log readers keep for ArduPilot's RAW_IMU + SCALED_IMU2
    streams); feed those to ``on_sample``.  ``set_calibration`` / ``set_mission`` may be called
    any time.  WMM declination is fixed at the first GPS fix (date: ``start_unix_s`` or now).
    """

    def __init__(self, calibration: dict | None = None, mission: list | None = None,
                 start_unix_s: float | None = None, settings: DetectionSettings | None = None,
                 mag_calibration_applied: bool | None = None) -> None:
        self.settings = settings or DetectionSettings()
        self.start_unix_s = start_unix_s
        self.calibration = calibration
        self.legs = mission_legs(mission)
        self.chain = HeadingChain()          # the default AHRS: the attitude shown and the detector's reference
        self.detector = InterferenceDetector(self.settings)
        self.earth_field = None
        self.params: dict[str, float] = {}
        self.autopilot: str | None = None
        self._applied = mag_calibration_applied
        self._policy: FieldPolicy | None = None
        self._primary: dict[str, int] = {}
        self._mag = HeldReading(GPS_TIMEOUT_S)
        self._att = Held(3, ATTITUDE_TIMEOUT_S)
        self._gps = Held(len(GPS_COLUMNS), GPS_TIMEOUT_S)
        self._current = Held(1, MOTOR_TIMEOUT_S)
        self._throttle = Held(1, MOTOR_TIMEOUT_S)
        self._current_range = [np.inf, -np.inf]
        self.vector: FieldConsistency | None = None      # made at the first GPS fix (WMM prior) or IMU step
        self.explain_history = ExplainHistory()          # per-step inputs of the alarm explanations
        self._imu_t: deque = deque(maxlen=RATE_WINDOW + 1)
        self._steps = StepState()
        self.last_row: np.ndarray | None = None
        self.last_step = None
        self.alarm_active = False
        self.alarm_kinds: list[str] = []

    # ------------------------------------------------------------------ configuration
    @property
    def policy(self) -> FieldPolicy:
        """The field rule for what has arrived so far (``groundstation.jobs.inputs.field_policy``)."""
        if self._policy is None:
            applied = self._applied if self._applied is not None else (True if self.autopilot == "ardupilot" else None)
            self._policy = field_policy(self.calibration, self.params, self.autopilot, applied)
        return self._policy

    def set_calibration(self, calibration: dict | None) -> None:
        self.calibration = calibration
        self._policy = None

    def restarted(self, calibration: dict | None) -> "LiveAnalyzer":
        """A fresh analyzer (heading chain and detector learn again) for a new calibration of
        the same source: what is known of the source (parameters, autopilot, primary sensors,
        WMM at the first fix) carries over."""
        new = LiveAnalyzer(calibration, None, self.start_unix_s, self.settings, self._applied)
        new.legs = self.legs
        new.params, new.autopilot, new._primary = dict(self.params), self.autopilot, dict(self._primary)
        new.earth_field = self.earth_field
        if self.earth_field is not None:
            new.vector = FieldConsistency(self.settings.vector, earth_prior_mG(self.earth_field))
        new.chain.declination_deg = self.chain.declination_deg
        new.explain_history = self.explain_history        # the alarms so far stay explained
        return new

    def set_mission(self, mission: list | None) -> None:
        self.legs = mission_legs(mission)

    def accepts(self, s: Sample) -> bool:
        if isinstance(s, (MagSample, ImuSample)):
            kind = type(s).__name__
            self._primary[kind] = primary = preferred_source(self._primary.get(kind), s.instance)
            return s.instance == primary
        return True

    def _start(self, s: GpsSample) -> None:
        """Declination from the WMM at the first fix (detection itself does not need the WMM:
        the field checks compare against the offset learned over the clean start)."""
        start = self.start_unix_s if self.start_unix_s else time.time() - s.t_s
        try:
            ef = earth_field(s.lat_deg, s.lon_deg, s.alt_m, decimal_year_from_unix(start + s.t_s))
        except ValueError:
            return
        self.chain.declination_deg = ef.declination_deg
        self.earth_field = ef
        if self.vector is None:
            self.vector = FieldConsistency(self.settings.vector, None)
        self.vector.set_prior(earth_prior_mG(ef))

    # ------------------------------------------------------------------ samples
    def on_sample(self, s: Sample) -> np.ndarray | None:
        """Feed one sample (time order); returns the record row of an IMU sample, else None."""
        rows = self.on_samples([s])
        return rows[0] if len(rows) else None

    def on_samples(self, samples: list[Sample]) -> np.ndarray:
        """Feed samples in time order; returns the record rows of their IMU samples (k, C).

        The heading chain and the detector step per sample; the inputs between them
        (``step_inputs``) and the rows (``record_rows``) are computed for all the IMU samples of
        the call at once, with the functions ``detection_inputs`` uses on a whole log."""
        steps: list[tuple] = []
        for s in samples:
            if isinstance(s, ImuSample):
                steps.append(self._chain_step(s))
            else:
                self._other(s)
        if not steps:
            return np.zeros((0, len(RECORD_COLUMNS)))
        return self._detect(steps)

    def _other(self, s: Sample) -> None:
        if isinstance(s, MagSample):
            m = self.policy.apply(np.asarray(s.mag_body_mG, dtype=float))[0]
            if np.all(np.isfinite(m)):
                self._mag.update(s.t_s, m, s.mag_body_mG)
                self.chain.update_mag(s.t_s, m)
        elif isinstance(s, GpsSample):
            if self.earth_field is None:
                self._start(s)
            row = np.array([[s.t_s, s.lat_deg, s.lon_deg, s.alt_m, *s.vel_ned_mps, s.fix_type]], dtype=float)
            self._gps.update(s.t_s, gps_rows(row, self.legs, self.settings)[0])
        elif isinstance(s, AttitudeSample):
            self._att.update(s.t_s, (s.roll_rad, s.pitch_rad, s.yaw_rad))
        elif isinstance(s, BatterySample):
            self._current.update(s.t_s, (s.current_A,))
            if np.isfinite(s.current_A):
                self._current_range = [min(self._current_range[0], s.current_A), max(self._current_range[1], s.current_A)]
        elif isinstance(s, ThrottleSample):
            self._throttle.update(s.t_s, (100.0 * s.throttle,))
        elif isinstance(s, ParamSample):
            self.params[s.name] = s.value
            self._policy = None
        elif isinstance(s, StatusSample) and s.kind == "autopilot":
            self.autopilot = s.text
            self._policy = None

    def _chain_step(self, s: ImuSample) -> tuple:
        """The heading chain's step and what is held at its time."""
        gyro = np.asarray(s.gyro_rad_s, dtype=float)
        accel = np.asarray(s.accel_mps2, dtype=float)
        st = self.chain.update_imu(s.t_s, gyro, accel)
        sh = st                              # one attitude: the one shown is the detector's
        t = st.t_s
        return (t, st.roll_rad, st.pitch_rad, st.yaw_rad, st.mag_heading_rad, st.heading_true_rad, bool(st.valid),
                gyro, self._mag.at(t)[0], self._att.at(t)[0], self._gps.at(t)[0], self.chain.declination_deg,
                np.asarray(st.gyro_bias_rad_s, dtype=float), self._motor_at(t),
                sh.roll_rad, sh.pitch_rad, sh.heading_true_rad, bool(sh.valid), self._att.time_at(t),
                self._mag.reading_time_at(t))

    def _motor_at(self, t: float) -> float:
        """The motor signal (``motor_signal_table``'s rule on what has arrived: a current that
        varies, else throttle %)."""
        if self.motor_signal == "current_A":
            return float(self._current.at(t)[0, 0])
        return float(self._throttle.at(t)[0, 0])

    def _detect(self, steps: list[tuple]) -> np.ndarray:
        cols = list(zip(*steps))
        t = np.asarray(cols[0], dtype=float)
        chain = SimpleNamespace(roll_rad=np.asarray(cols[1]), pitch_rad=np.asarray(cols[2]),
                                yaw_rad=np.asarray(cols[3]), mag_heading_rad=np.asarray(cols[4]),
                                heading_true_rad=np.asarray(cols[5]), valid=np.asarray(cols[6], dtype=bool))
        gyro, mag, att, gps = (np.vstack(cols[k]) for k in (7, 8, 9, 10))
        mag = field_at_steps(mag, t - np.asarray(cols[19], dtype=float), gyro - np.vstack(cols[12]))
        history = np.asarray(self._imu_t, dtype=float)
        rate = imu_rate_hz(np.concatenate([history, t]), start=len(history))
        self._imu_t.extend(t.tolist())
        x = step_inputs(t, chain, mag, att[:, :2], gps, rate, gyro, self.policy, self.settings, self._steps,
                        att_t=np.asarray(cols[18], dtype=float))
        chain.gyro_bias_rad_s = np.vstack(cols[12])
        motor = np.asarray(cols[13], dtype=float)
        z_vector, residual = self._vector_steps(t, chain, mag, att, gyro, motor, rate, x)
        k = len(t)
        zs = np.full((k, 4), np.nan)
        combined = np.zeros(k, bool)
        trigger = np.zeros((k, 3), bool)
        score = np.full(k, np.nan)
        args = zip(t.tolist(), x["e"].tolist(), x["d"].tolist(), x["trusted"].tolist(), x["strength"].tolist(),
                   x["incl"].tolist(), x["heading"].tolist(), x["yaw_rate"].tolist(), z_vector.tolist())
        for i, a in enumerate(args):
            step = self.detector.update(*a)
            combined[i] = step.combined
            trigger[i] = [name in step.evidence for name in EVIDENCE]
            score[i] = np.fmax(np.fmax(np.fmax(step.z_heading, step.z_path), step.z_field), step.z_vector)
            zs[i] = (step.z_heading, step.z_path, step.z_field, step.z_vector)
            self.last_step = step
        self.explain_history.append(t_s=t, rx=residual[:, 0], ry=residual[:, 1], rz=residual[:, 2], motor=motor,
                                   lat_deg=gps[:, 3], lon_deg=gps[:, 4], alt_m=gps[:, 8],
                                   **{name: zs[:, j] for j, name in enumerate(SCORE_NAMES)})
        self.alarm_active = bool(combined[-1])
        self.alarm_kinds = list(self.detector.alarm_kinds) if self.alarm_active else []
        shown = SimpleNamespace(roll_rad=np.asarray(cols[14]), pitch_rad=np.asarray(cols[15]),
                                heading_true_rad=np.asarray(cols[16]), valid=np.asarray(cols[17], dtype=bool))
        rows = record_rows(t, chain, dict(x, gps_held=gps, att_held=att), np.asarray(cols[11], dtype=float),
                           combined, trigger, score, attitude=shown)
        self.last_row = rows[-1]
        return rows


    def _vector_steps(self, t, chain, mag, att, gyro, motor, rate, x) -> tuple[np.ndarray, np.ndarray]:
        """The field-vector test on these steps (``field_consistency``'s per-sample form): its
        score and residual [mG, body] per step."""
        if self.vector is None:
            self.vector = FieldConsistency(self.settings.vector, None)
        roll, pitch, ok, gyro_c = vector_test_inputs(chain, x, gyro, x["steep"])
        field_on = self.policy.field_on
        z = np.full(len(t), np.nan)
        residual = np.full((len(t), 3), np.nan)
        for i in range(len(t)):
            step = self.vector.update(float(t[i]), mag[i], float(roll[i]), float(pitch[i]), bool(ok[i]), gyro_c[i],
                                      float(motor[i]), float(rate[i]), field_on)
            z[i], residual[i] = step.z, step.residual_mG
        return z, residual

    @property
    def motor_signal(self) -> str:
        """The motor field's signal so far (``motor_signal_table``'s names)."""
        return "current_A" if self._current_range[1] - self._current_range[0] > 0.5 else "throttle_pct"


class GpsOutageWatch:
    """Per-sample rule of ``gps_outages``: the 3-D fix is lost when the IMU keeps streaming for
    more than OUTAGE_MIN_S after the last good fix; a gap in all the data (an IMU gap longer than
    OUTAGE_MIN_S: a telemetry dropout) is not an outage.

    ``on_sample`` returns ("lost", last_fix_t) or ("back", outage_s) when that happens, else None.
    """

    def __init__(self) -> None:
        self.last_fix_t: float | None = None
        self.lost = False
        self._last_imu_t: float | None = None
        self._dropout = False          # a gap in all the data since the last fix

    def on_sample(self, s: Sample) -> tuple[str, float] | None:
        if isinstance(s, GpsSample) and s.fix_type >= 3 and np.isfinite(s.lat_deg) and np.isfinite(s.lon_deg):
            out = ("back", s.t_s - self.last_fix_t) if self.lost else None
            self.last_fix_t, self.lost, self._dropout = s.t_s, False, False
            return out
        if not isinstance(s, ImuSample):
            return None
        if self._last_imu_t is not None and s.t_s - self._last_imu_t > OUTAGE_MIN_S:
            self._dropout = True
        self._last_imu_t = s.t_s
        if (not self.lost and not self._dropout and self.last_fix_t is not None
                and s.t_s - self.last_fix_t > OUTAGE_MIN_S):
            self.lost = True
            return ("lost", self.last_fix_t)
        return None


class ReorderBuffer:
    """Samples of a live stream released in time order (ties: IMU last, else arrival order).

    A sample is released once a sample more than ``delay_s`` newer has arrived (so samples of
    one time all arrive first), or it has waited longer than ``delay_s`` (at least STALL_WAIT_S)
    of wall time (the stream stopped).  ``delay_s`` follows the lateness seen (how far
    a sample's time is behind the newest time already received, x1.25), decays with a
    REORDER_MEMORY_S time constant and is capped at MAX_REORDER_S; on a link whose samples arrive
    in order it stays 0 and nothing waits.
    """

    def __init__(self) -> None:
        self.delay_s = 0.0
        self._heap: list = []
        self._seq = itertools.count()
        self._newest = -math.inf
        self._decay_at: float | None = None

    def push(self, samples, wall_s: float | None = None) -> list:
        """Add samples; return those now due, in time order."""
        wall = time.monotonic() if wall_s is None else wall_s
        self._decay(wall)
        for s in samples:
            late = self._newest - s.t_s
            if late > 0:
                self.delay_s = min(MAX_REORDER_S, max(self.delay_s, 1.25 * late))
            self._newest = max(self._newest, s.t_s)
            # at equal times the IMU step comes last: it reads the others at or before its time
            heapq.heappush(self._heap, (s.t_s, isinstance(s, ImuSample), next(self._seq), wall, s))
        return self.due(wall)

    def due(self, wall_s: float | None = None) -> list:
        wall = time.monotonic() if wall_s is None else wall_s
        out = []
        heap, limit = self._heap, self._newest - self.delay_s
        stall = max(self.delay_s, STALL_WAIT_S)
        while heap and (heap[0][0] < limit or wall - heap[0][3] > stall):
            out.append(heapq.heappop(heap)[4])
        return out

    def flush(self) -> list:
        out = [item[4] for item in sorted(self._heap, key=lambda item: item[:3])]
        self._heap = []
        return out

    def _decay(self, wall: float) -> None:
        if self._decay_at is not None and wall > self._decay_at:
            self.delay_s *= math.exp(-(wall - self._decay_at) / REORDER_MEMORY_S)
        self._decay_at = wall
