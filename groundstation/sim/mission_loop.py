"""The closed-loop mission of ``flight_sim``: truth, sensors, autopilot and controller, step by step.

Seed 002 section 2: the autopilot turns a desired horizontal acceleration into roll/pitch with its
*estimated* yaw (eq. 4), so a compass error rotates the produced acceleration (eq. 5) and bends
the track; its INS rotates the accelerometer with the same estimated yaw before blending with
GPS.  Each step runs, in order: ``_sense`` (truth forces and the raw sensors), ``_autopilot``
(corrected field, seed-000 field-vector filter, tilt-compensated heading, INS), ``_control``
(position and velocity loops -> desired tilt and yaw rate) and ``_integrate`` (truth kinematics).

The state lives in plain floats on the object: the loop runs 10^4–10^5 steps per flight and the
per-sample estimator classes would cost ~0.2 ms a step.  The field-vector filter step uses exactly
the discretisation of ``estimators.attitude`` (x' = (1 − g) R(−ω dt) x + g m, g = 1 − exp(−k dt));
tests/test_simulate.py checks the two agree on the same inputs.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["MissionLoop", "wrap_pi", "G"]

G = 9.80665
K_GPS_VEL = 0.6          # autopilot INS blending gain toward GPS velocity [1/s]
K_GPS_POS = 0.8          # ... toward GPS position [1/s]
TAU_ATT_S = 0.15         # attitude loop time constant
YAW_RATE_MAX_RAD_S = math.radians(40.0)
ACC_CMD_MAX_MPS2 = 5.0
VEL_INT_MAX_MPS2 = 3.0


def wrap_pi(a: float) -> float:
    """Angle wrapped to [−π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


class MissionLoop:
    """One closed-loop mission; ``run()`` fills the output arrays, step by step."""

    def __init__(self, cfg, inputs: dict, n: int) -> None:
        """``inputs``: per-step targets and noise prepared by ``flight_sim`` (lists of floats/tuples):
        s_target, v_ff, yaw_cmd, wind, wind_z, acc_noise, mag_noise, gyro_noise, att_noise,
        interference, gps_valid, gps_row, gps_err, gps_vel_err, and the constants u, gps_dt."""
        self.cfg, self.n = cfg, n
        self.inp = inputs
        self.dt = 1.0 / cfg.rate_hz
        self.g_ap = -math.expm1(-cfg.autopilot_mag_gain_per_s * self.dt)
        self.A = [list(map(float, row)) for row in cfg.mag.matrix]
        self.Ai = [list(map(float, row)) for row in np.linalg.inv(cfg.mag.matrix)]
        self.off = tuple(map(float, cfg.mag.offsets_mG))
        self.cmot = tuple(map(float, cfg.mag.motor_mG_per_A))
        self.f_ned = tuple(map(float, cfg.field_ned_mG))
        self.decl = math.radians(cfg.declination_deg)
        self.out = {k: np.zeros((n, 3)) for k in ("rates", "gyro", "acc", "mag", "pos", "vel", "epos", "evel")}
        self.out_att = np.zeros((n, 6))
        self.current = np.zeros(n)
        # truth and autopilot state; start in a steady hover, the velocity integrator holding the wind
        self.pn = self.pe = self.vn = self.ve = 0.0
        self.roll = self.pitch = 0.0
        self.yaw = math.radians(cfg.leg_bearing_deg)
        self.epn = self.epe = self.evn = self.eve = 0.0
        self.int_n = -cfg.drag_per_s * float(cfg.mean_wind_mps[0])
        self.int_e = -cfg.drag_per_s * float(cfg.mean_wind_mps[1])
        self.alt = -cfg.flight_alt_m
        self.h = None                       # autopilot field-vector filter state (body field)
        self.p_b = self.q_b = self.r_b = 0.0

    def run(self) -> "MissionLoop":
        for i in range(self.n):
            self._sense(i)
            self._autopilot(i)
            self._control(i)
            self._integrate(i)
        return self

    # ------------------------------------------------------------------ steps
    def _sense(self, i: int) -> None:
        """Truth attitude, thrust, current and forces; raw magnetometer, accelerometer, gyro."""
        cos, sin = math.cos, math.sin
        cfg, inp = self.cfg, self.inp
        cr, sr, cp, sp = cos(self.roll), sin(self.roll), cos(self.pitch), sin(self.pitch)
        cy, sy = cos(self.yaw), sin(self.yaw)
        r00, r01, r02 = cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy
        r10, r11, r12 = cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy
        r20, r21, r22 = -sp, sr * cp, cr * cp
        self.trig = (cr, sr, cp, sp)
        thrust = (G - inp["wind_z"][i]) / max(r22, 0.5)   # altitude held; vertical gusts countered by thrust
        cur = cfg.mag.hover_current_A * (thrust / G) ** 1.5
        self.current[i] = self.cur = cur
        w = inp["wind"][i]
        an = -thrust * r02 + cfg.drag_per_s * (w[0] - self.vn)   # eq. (1): tilted thrust + drag
        ae = -thrust * r12 + cfg.drag_per_s * (w[1] - self.ve)
        fd = -G                                                  # specific force f = a − g (NED)
        na = inp["acc_noise"][i]
        ab = (r00 * an + r10 * ae + r20 * fd + na[0],
              r01 * an + r11 * ae + r21 * fd + na[1],
              r02 * an + r12 * ae + r22 * fd + na[2])
        self.an, self.ae, self.ab = an, ae, ab
        fN, fE, fD = self.f_ned
        cmx, cmy, cmz = self.cmot
        mbx = r00 * fN + r10 * fE + r20 * fD + cur * cmx
        mby = r01 * fN + r11 * fE + r21 * fD + cur * cmy
        mbz = r02 * fN + r12 * fE + r22 * fD + cur * cmz
        q, mn, A, off = inp["interference"][i], inp["mag_noise"][i], self.A, self.off
        self.m = (A[0][0] * mbx + A[0][1] * mby + A[0][2] * mbz + off[0] + q[0] + mn[0],
                  A[1][0] * mbx + A[1][1] * mby + A[1][2] * mbz + off[1] + q[1] + mn[1],
                  A[2][0] * mbx + A[2][1] * mby + A[2][2] * mbz + off[2] + q[2] + mn[2])
        self.out["mag"][i] = self.m
        self.out["acc"][i] = ab
        gn = inp["gyro_noise"][i]
        self.gyro = (self.p_b + gn[0], self.q_b + gn[1], self.r_b + gn[2])   # rates of the last step
        self.out["gyro"][i] = self.gyro

    def _field_filter(self, c: tuple[float, float, float]) -> None:
        """One step of the autopilot's field-vector filter (seed 000 eq. 9/10) on the corrected field."""
        if self.h is None:
            self.h = c
            return
        dt, g_ap = self.dt, self.g_ap
        hx, hy, hz = self.h
        tx, ty, tz = self.gyro[0] * dt, self.gyro[1] * dt, self.gyro[2] * dt
        ang = math.sqrt(tx * tx + ty * ty + tz * tz)
        if ang < 1e-4:
            sc, vs = 1.0 - ang * ang / 6.0, 0.5 - ang * ang / 24.0
        else:
            sc, vs = math.sin(ang) / ang, (1.0 - math.cos(ang)) / (ang * ang)
        ca = math.cos(ang)
        dot = tx * hx + ty * hy + tz * hz
        kx, ky, kz = ty * hz - tz * hy, tz * hx - tx * hz, tx * hy - ty * hx
        self.h = ((1 - g_ap) * (ca * hx - sc * kx + vs * dot * tx) + g_ap * c[0],
                  (1 - g_ap) * (ca * hy - sc * ky + vs * dot * ty) + g_ap * c[1],
                  (1 - g_ap) * (ca * hz - sc * kz + vs * dot * tz) + g_ap * c[2])

    def _autopilot(self, i: int) -> None:
        """Corrected field, heading (seed 000 eqs. 11–13 + declination) and the INS blended with GPS."""
        cos, sin = math.cos, math.sin
        inp, dt, Ai, off, cm = self.inp, self.dt, self.Ai, self.off, self.cmot
        comp_cur = self.cfg.autopilot_motor_comp * self.cur
        dx, dy, dz = self.m[0] - off[0], self.m[1] - off[1], self.m[2] - off[2]
        self._field_filter((Ai[0][0] * dx + Ai[0][1] * dy + Ai[0][2] * dz - comp_cur * cm[0],
                            Ai[1][0] * dx + Ai[1][1] * dy + Ai[1][2] * dz - comp_cur * cm[1],
                            Ai[2][0] * dx + Ai[2][1] * dy + Ai[2][2] * dz - comp_cur * cm[2]))
        hx, hy, hz = self.h
        atn = inp["att_noise"][i]
        er, ep = self.roll + atn[0], self.pitch + atn[1]
        cer, ser, cep, sep = cos(er), sin(er), cos(ep), sin(ep)
        Hx = hx * cep + hy * sep * ser + hz * sep * cer         # seed 000 eq. (11)
        Hy = hy * cer - hz * ser                                # eq. (12)
        yaw_est = wrap_pi(math.atan2(-Hy, Hx) + self.decl)      # eq. (13) + declination
        self.out_att[i] = (self.roll, self.pitch, self.yaw, er, ep, yaw_est)
        self.yaw_est = yaw_est
        # INS: accelerometer rotated to NED with the *estimated* attitude, blended with GPS
        ce, se = cos(yaw_est), sin(yaw_est)
        ab = self.ab
        e00, e01, e02 = cep * ce, ser * sep * ce - cer * se, cer * sep * ce + ser * se
        e10, e11, e12 = cep * se, ser * sep * se + cer * ce, cer * sep * se - ser * ce
        self.evn += (e00 * ab[0] + e01 * ab[1] + e02 * ab[2]) * dt
        self.eve += (e10 * ab[0] + e11 * ab[1] + e12 * ab[2]) * dt
        if inp["gps_valid"][i]:
            rr, gdt = inp["gps_row"][i], inp["gps_dt"]
            gverr, gerr = inp["gps_vel_err"], inp["gps_err"]
            self.evn += K_GPS_VEL * (self.vn + gverr[rr, 0] - self.evn) * gdt
            self.eve += K_GPS_VEL * (self.ve + gverr[rr, 1] - self.eve) * gdt
            self.epn += K_GPS_POS * (self.pn + gerr[rr, 0] - self.epn) * gdt
            self.epe += K_GPS_POS * (self.pe + gerr[rr, 1] - self.epe) * gdt
        self.epn += self.evn * dt
        self.epe += self.eve * dt
        self.out["epos"][i] = (self.epn, self.epe, self.alt)
        self.out["evel"][i] = (self.evn, self.eve, 0.0)

    def _control(self, i: int) -> None:
        """Position controller toward the moving target on the line -> desired tilt, yaw rate."""
        cfg, inp, dt = self.cfg, self.inp, self.dt
        ux, uy = inp["u"]
        st, vf = inp["s_target"][i], inp["v_ff"][i]
        vsp_n = vf * ux + cfg.pos_gain_per_s * (st * ux - self.epn)
        vsp_e = vf * uy + cfg.pos_gain_per_s * (st * uy - self.epe)
        spd = math.hypot(vsp_n, vsp_e)
        vmax = cfg.speed_mps + 2.0
        if spd > vmax:
            vsp_n, vsp_e = vsp_n * vmax / spd, vsp_e * vmax / spd
        en, ee = vsp_n - self.evn, vsp_e - self.eve
        ki = cfg.vel_int_gain_per_s2
        self.int_n = min(max(self.int_n + ki * en * dt, -VEL_INT_MAX_MPS2), VEL_INT_MAX_MPS2)
        self.int_e = min(max(self.int_e + ki * ee * dt, -VEL_INT_MAX_MPS2), VEL_INT_MAX_MPS2)
        adn, ade = cfg.vel_gain_per_s * en + self.int_n, cfg.vel_gain_per_s * ee + self.int_e
        amag = math.hypot(adn, ade)
        if amag > ACC_CMD_MAX_MPS2:
            adn, ade = adn * ACC_CMD_MAX_MPS2 / amag, ade * ACC_CMD_MAX_MPS2 / amag
        # seed 002 eq. (4): desired tilt from the desired acceleration with the *estimated* yaw
        ce, se = math.cos(self.yaw_est), math.sin(self.yaw_est)
        a_fwd = ce * adn + se * ade
        a_rgt = -se * adn + ce * ade
        self.pitch_d = -math.atan2(a_fwd, G)
        self.roll_d = math.atan2(a_rgt * math.cos(self.pitch_d), G)
        self.yaw_rate = min(max(1.5 * wrap_pi(inp["yaw_cmd"][i] - self.yaw_est), -YAW_RATE_MAX_RAD_S),
                            YAW_RATE_MAX_RAD_S)

    def _integrate(self, i: int) -> None:
        """Truth: first-order attitude, Euler kinematics -> body rates, translation (eq. 1)."""
        dt = self.dt
        cr, sr, cp, sp = self.trig
        droll = (self.roll_d - self.roll) / TAU_ATT_S
        dpitch = (self.pitch_d - self.pitch) / TAU_ATT_S
        yrate = self.yaw_rate
        self.p_b = droll - yrate * sp
        self.q_b = dpitch * cr + yrate * cp * sr
        self.r_b = -dpitch * sr + yrate * cp * cr
        self.out["rates"][i] = (self.p_b, self.q_b, self.r_b)
        self.out["pos"][i] = (self.pn, self.pe, self.alt)
        self.out["vel"][i] = (self.vn, self.ve, 0.0)
        self.roll += droll * dt
        self.pitch += dpitch * dt
        self.yaw = wrap_pi(self.yaw + yrate * dt)
        self.vn += self.an * dt
        self.ve += self.ae * dt
        self.pn += self.vn * dt
        self.pe += self.ve * dt
