"""ArduPilot compass corrections in force over time: rebuild the raw field from the logged one.

ArduPilot streams and logs the *corrected* field (RAW_IMU / SCALED_IMU2 / SCALED_IMU3, DataFlash
MAG*), and the corrections change during a log (onboard calibration, COMPASS_LEARN, parameter
writes).  Raw must be rebuilt with the values in force at each sample, not the last ones.

Order of corrections (AP_Compass_Backend::correct_field, ArduPilot source, 4.x):

    1. mag += COMPASS_OFS                       (offsets are *added*)
    2. mag *= COMPASS_SCALE                     (only when a scale factor is set, > 0)
    3. mag  = M · mag,  M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]
                                                (DIA all zero means 1)
    4. mag += COMPASS_MOT · x,  x = throttle (0..1) when COMPASS_MOTCT = 1, battery current [A]
                                when COMPASS_MOTCT = 2; nothing when 0 or the current is unknown
                                ("motor offsets after the elliptical correction, as compassmot
                                computes them on final field outputs").

Older ArduPilot (before the scale factor existed, e.g. the 3.x drivers) added the motor offset
*before* the matrix and had no scale: ``motor_after_matrix=False``.  When DIA/ODI are identity
(every log before the 3.3 calibrator) both orders give the same numbers.

The "raw" here is ArduPilot's rotated raw: the sensor reading already rotated into the body frame
by COMPASS_ORIENTn / board orientation (AP_Compass_Backend::rotate_field runs before
correct_field).  Units: mG (ArduPilot's "milligauss"), A, throttle 0..1.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

__all__ = ["CorrectionsInForce", "RawRebuild", "values_in_force", "ardupilot_param_names",
           "corrections_from_param_changes", "motor_offset_mG", "apply_ardupilot_corrections",
           "unapply_ardupilot_corrections", "changes_summary", "correction_matrices", "CorrectionsTracker",
           "MOTCT_DISABLED", "MOTCT_THROTTLE", "MOTCT_CURRENT"]

MOTCT_DISABLED, MOTCT_THROTTLE, MOTCT_CURRENT = 0, 1, 2   # COMPASS_MOTCT


@dataclass(frozen=True)
class CorrectionsInForce:
    """ArduPilot correction values in force at each of N samples (NaN where unknown).

    offsets_mG (N,3) COMPASS_OFS*, diag (N,3) COMPASS_DIA* (0,0,0 = identity), offdiag (N,3)
    COMPASS_ODI*, scale (N,) COMPASS_SCALE* (<= 0 or NaN: not used), motor_per_unit (N,3)
    COMPASS_MOT* [mG/A or mG per full throttle], motor_type (N,) COMPASS_MOTCT (0/1/2),
    known (N,) True where offsets were known at that time.
    """
    offsets_mG: np.ndarray
    diag: np.ndarray
    offdiag: np.ndarray
    scale: np.ndarray
    motor_per_unit: np.ndarray
    motor_type: np.ndarray
    known: np.ndarray

    @staticmethod
    def constant(n: int, offsets_mG=(0.0, 0.0, 0.0), diag=(1.0, 1.0, 1.0), offdiag=(0.0, 0.0, 0.0),
                 scale: float = 0.0, motor_per_unit=(0.0, 0.0, 0.0), motor_type: int = 0) -> "CorrectionsInForce":
        """The same values at all n samples (a log whose corrections never change)."""
        rep = lambda v: np.repeat(np.asarray(v, float).reshape(1, 3), n, axis=0)
        return CorrectionsInForce(rep(offsets_mG), rep(diag), rep(offdiag), np.full(n, float(scale)),
                                  rep(motor_per_unit), np.full(n, int(motor_type)), np.ones(n, bool))


@dataclass(frozen=True)
class RawRebuild:
    """Result of ``unapply_ardupilot_corrections``.  status: "ok" | "partial" | "no_data"."""
    raw_mG: np.ndarray          # (N,3), NaN where the corrections were unknown or the input NaN
    valid: np.ndarray           # (N,) bool
    status: str
    message: str


def values_in_force(t_s: np.ndarray, change_t_s: np.ndarray, change_values: np.ndarray,
                    initial=None) -> tuple[np.ndarray, np.ndarray]:
    """Step-hold: the value set at the last change at or before each t (a change at t applies to t).

    change_t_s (K,) ascending (sorted here, stable), change_values (K, ...).  Before the first
    change ``initial`` is used when given (the value at log start), else NaN and known False.
    Returns (values (N, ...), known (N,) bool).
    """
    t = np.asarray(t_s, float).ravel()
    ct = np.asarray(change_t_s, float).ravel()
    cv = np.asarray(change_values, float)
    order = np.argsort(ct, kind="stable")
    ct, cv = ct[order], cv[order]
    shape = cv.shape[1:]
    idx = np.searchsorted(ct, t, side="right") - 1
    out = np.full((len(t),) + shape, np.nan)
    after = idx >= 0
    if len(ct):
        out[after] = cv[idx[after]]
    known = after.copy()
    if initial is not None:
        out[~after] = np.asarray(initial, float)
        known[:] = True
    return out, known


def ardupilot_param_names(instance: int) -> dict[str, list[str]]:
    """ArduPilot parameter names of compass ``instance`` (0-based): COMPASS_OFS_X, COMPASS_OFS2_X, ...
    (the convention of groundstation.io.params; COMPASS_MOTCT is shared by all compasses)."""
    n = "" if instance == 0 else str(instance + 1)
    return {"offsets": [f"COMPASS_OFS{n}_{a}" for a in "XYZ"], "diag": [f"COMPASS_DIA{n}_{a}" for a in "XYZ"],
            "offdiag": [f"COMPASS_ODI{n}_{a}" for a in "XYZ"], "scale": [f"COMPASS_SCALE{n}"],
            "motor": [f"COMPASS_MOT{n}_{a}" for a in "XYZ"], "motor_type": ["COMPASS_MOTCT"]}


def _history(t: np.ndarray, by_name: dict[str, list], names: list[str], default: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """(N, len(names)) step-held values of each name; a name never seen takes ``default``;
    known is False before the first change of any of the names."""
    cols, known = [], np.ones(len(t), bool)
    for name in names:
        rows = by_name.get(name)
        if not rows:
            cols.append(np.full(len(t), default))
            continue
        ct, cv = np.array(rows, float).T
        vals, k = values_in_force(t, ct, cv)
        cols.append(vals)
        known &= k
    return np.stack(cols, axis=1), known


def corrections_from_param_changes(t_s: np.ndarray, changes: Iterable[tuple[float, str, float]],
                                   instance: int = 0) -> CorrectionsInForce:
    """Corrections in force at each t_s for compass ``instance`` from a parameter history.

    ``changes``: (t_s, name, value) triples in any order, e.g. every PARAM_VALUE / PARM record of the
    log, SENSOR_OFFSETS mag_ofs_* as COMPASS_OFS_* of compass 0, DataFlash MAG OfsX.. as COMPASS_OFS*
    of that compass.  A value logged at t applies from t on.  Parameters never seen take ArduPilot's
    defaults (DIA 0 = identity, ODI 0, SCALE 0 = unused, MOT 0, MOTCT 0); samples before the first
    offset record are ``known`` False (their raw field cannot be rebuilt)."""
    t = np.asarray(t_s, float).ravel()
    names = ardupilot_param_names(instance)
    wanted = {n for group in names.values() for n in group}
    by_name: dict[str, list] = {}
    for ct, nm, v in changes:
        if nm in wanted:
            by_name.setdefault(nm, []).append((ct, v))
    ofs, known = _history(t, by_name, names["offsets"], np.nan)
    dia, _ = _history(t, by_name, names["diag"], 0.0)
    odi, _ = _history(t, by_name, names["offdiag"], 0.0)
    scale, _ = _history(t, by_name, names["scale"], 0.0)
    mot, _ = _history(t, by_name, names["motor"], 0.0)
    motct, _ = _history(t, by_name, names["motor_type"], 0.0)
    motct = np.where(np.isfinite(motct[:, 0]), motct[:, 0], 0.0).astype(int)
    return CorrectionsInForce(ofs, np.nan_to_num(dia), np.nan_to_num(odi), scale[:, 0], np.nan_to_num(mot),
                              motct, known & np.all(np.isfinite(ofs), axis=1))


def correction_matrices(diag: np.ndarray, offdiag: np.ndarray) -> np.ndarray:
    """(N,3,3) M from DIA/ODI; an all-zero DIA row means identity (ArduPilot's correct_field)."""
    d = np.array(diag, float)
    zero = np.all(d == 0.0, axis=1)
    d[zero] = 1.0
    o = np.asarray(offdiag, float)
    M = np.zeros((len(d), 3, 3))
    M[:, 0, 0], M[:, 1, 1], M[:, 2, 2] = d[:, 0], d[:, 1], d[:, 2]
    M[:, 0, 1] = M[:, 1, 0] = o[:, 0]
    M[:, 0, 2] = M[:, 2, 0] = o[:, 1]
    M[:, 1, 2] = M[:, 2, 1] = o[:, 2]
    return M


def _scale(scale: np.ndarray) -> np.ndarray:
    s = np.asarray(scale, float)
    return np.where(np.isfinite(s) & (s > 0.0), s, 1.0)


def motor_offset_mG(corr: CorrectionsInForce, current_A: np.ndarray | None = None,
                    throttle: np.ndarray | None = None) -> np.ndarray:
    """COMPASS_MOT · x per sample (N,3): x = throttle when MOTCT = 1, current when MOTCT = 2; zero
    when disabled or the signal is missing/NaN (ArduPilot adds nothing without a current reading)."""
    n = len(corr.motor_type)
    x = np.zeros(n)
    for kind, sig in ((MOTCT_THROTTLE, throttle), (MOTCT_CURRENT, current_A)):
        sel = corr.motor_type == kind
        if sig is not None and np.any(sel):
            s = np.asarray(sig, float).ravel()
            x[sel] = np.where(np.isfinite(s[sel]), s[sel], 0.0)
    return corr.motor_per_unit * x[:, None]


def apply_ardupilot_corrections(raw_mG: np.ndarray, corr: CorrectionsInForce, current_A=None, throttle=None,
                                motor_after_matrix: bool = True) -> np.ndarray:
    """AP_Compass_Backend::correct_field on (N,3) rotated-raw samples (the simulator's forward model)."""
    m = np.asarray(raw_mG, float).reshape(-1, 3)
    M = correction_matrices(corr.diag, corr.offdiag)
    mot = motor_offset_mG(corr, current_A, throttle)
    x = (m + corr.offsets_mG) * _scale(corr.scale)[:, None]
    if not motor_after_matrix:
        x = x + mot
    x = np.einsum("nij,nj->ni", M, x)
    return x + mot if motor_after_matrix else x


def _inverse_per_sample(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(det (N,), inverse (N,3,3)) of per-sample matrices that change only a few times in a log:
    computed once per stretch of equal matrices (a singular or non-finite one gives det 0/NaN and
    the identity as its 'inverse')."""
    n = len(M)
    if n == 0:
        return np.zeros(0), np.zeros((0, 3, 3))
    flat = M.reshape(n, 9)
    starts = np.flatnonzero(np.r_[True, np.any(flat[1:] != flat[:-1], axis=1)])
    seg = np.cumsum(np.isin(np.arange(n), starts)) - 1
    Mu = M[starts]
    det_u = np.linalg.det(np.where(np.isfinite(Mu), Mu, 0.0))
    det_u[~np.all(np.isfinite(Mu.reshape(len(Mu), 9)), axis=1)] = np.nan
    ok = np.isfinite(det_u) & (np.abs(det_u) > 1e-6)
    inv_u = np.linalg.inv(np.where(ok[:, None, None], Mu, np.eye(3)))
    return det_u[seg], inv_u[seg]


def unapply_ardupilot_corrections(corrected_mG: np.ndarray, corr: CorrectionsInForce, current_A=None,
                                  throttle=None, logged_motor_offset_mG: np.ndarray | None = None,
                                  motor_after_matrix: bool = True) -> RawRebuild:
    """Inverse of ``apply_ardupilot_corrections``: raw = M⁻¹(corrected − mot)/scale − OFS (new order)
    or (M⁻¹ corrected − mot)/scale − OFS (old order).

    ``logged_motor_offset_mG`` (N,3) overrides the COMPASS_MOT · x term with the offsets the
    vehicle logged (DataFlash MAG MOX/MOY/MOZ, or MOfsX.. in old logs).  Samples whose corrections
    are unknown, whose matrix is singular or whose input is NaN come out NaN and ``valid`` False.
    """
    c = np.asarray(corrected_mG, float).reshape(-1, 3)
    n = len(c)
    if n == 0:
        return RawRebuild(np.empty((0, 3)), np.zeros(0, bool), "no_data", "no samples")
    det, Minv = _inverse_per_sample(correction_matrices(corr.diag, corr.offdiag))
    good = corr.known & np.all(np.isfinite(c), axis=1) & np.isfinite(det) & (np.abs(det) > 1e-6)
    mot = motor_offset_mG(corr, current_A, throttle) if logged_motor_offset_mG is None \
        else np.nan_to_num(np.asarray(logged_motor_offset_mG, float).reshape(-1, 3))
    Minv = np.where(good[:, None, None], Minv, np.eye(3))
    x = c - mot if motor_after_matrix else c
    x = np.einsum("nij,nj->ni", Minv, np.where(good[:, None], x, 0.0))
    if not motor_after_matrix:
        x = x - mot
    raw = x / _scale(corr.scale)[:, None] - np.nan_to_num(corr.offsets_mG)
    raw[~good] = np.nan
    n_bad = int((~good).sum())
    if n_bad == n:
        return RawRebuild(raw, good, "no_data", f"corrections unknown or input NaN for all {n} samples")
    if n_bad:
        return RawRebuild(raw, good, "partial", f"{n_bad} of {n} samples without known corrections or finite input")
    return RawRebuild(raw, good, "ok", f"{n} samples rebuilt with the corrections in force")


def changes_summary(corr: CorrectionsInForce, t_s: Sequence[float]) -> list[tuple[float, list[float]]]:
    """[(t_s, offsets)] at each sample where the offsets in force change (for `info`)."""
    ofs = corr.offsets_mG
    t = np.asarray(t_s, float)
    if len(t) == 0:
        return []
    a, b = ofs[1:], ofs[:-1]
    same = np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)
    ch = np.nonzero(~same)[0] + 1
    idx = np.concatenate([[0], ch])
    return [(float(t[i]), [float(v) for v in corr.offsets_mG[i]]) for i in idx]


class CorrectionsTracker:
    """Per-sample twin of ``corrections_from_param_changes`` + ``unapply_ardupilot_corrections``
    for a live link: parameter values go in as they arrive (PARAM_VALUE, SENSOR_OFFSETS as
    COMPASS_OFS_*), each corrected sample is un-applied with the values in force at that moment.
    Gives the batch numbers on every sample after the first offsets arrived (tested); before
    that the raw field is unknown (NaN), where the batch form may assume the first reported values.
    """

    def __init__(self, instance: int = 0, motor_after_matrix: bool = True) -> None:
        self.names = ardupilot_param_names(instance)
        self.motor_after_matrix = motor_after_matrix
        self.values: dict[str, float] = {}

    def update(self, name: str, value: float) -> None:
        """A parameter value seen now (names of other compasses are ignored)."""
        if any(name in group for group in self.names.values()):
            self.values[name] = float(value)

    def in_force(self) -> CorrectionsInForce:
        """The corrections in force now, as a one-sample CorrectionsInForce (defaults as the batch form)."""
        get = lambda key, default: [self.values.get(n, default) for n in self.names[key]]  # noqa: E731
        ofs = get("offsets", np.nan)
        corr = CorrectionsInForce(np.array([ofs]), np.array([get("diag", 0.0)]), np.array([get("offdiag", 0.0)]),
                                  np.array(get("scale", 0.0)), np.array([get("motor", 0.0)]),
                                  np.array([int(self.values.get(self.names["motor_type"][0], 0))]),
                                  np.array([bool(np.all(np.isfinite(ofs)))]))
        return corr

    def unapply(self, corrected_mG, current_A: float | None = None, throttle: float | None = None,
                logged_motor_offset_mG=None) -> np.ndarray:
        """Raw (3,) of one corrected sample; NaN while the offsets are unknown."""
        logged = None if logged_motor_offset_mG is None else np.asarray(logged_motor_offset_mG, float).reshape(1, 3)
        rebuilt = unapply_ardupilot_corrections(
            np.asarray(corrected_mG, float).reshape(1, 3), self.in_force(),
            None if current_A is None else np.array([current_A], float),
            None if throttle is None else np.array([throttle], float), logged, self.motor_after_matrix)
        return rebuilt.raw_mG[0]
