"""BROAD trials and the peer orientation filters of benchmarks/ahrs.py (data loading, frames, runners).

BROAD (Laidig et al., Data 6(7):72, 2021; ../shared/data/broad, CC-BY-4.0): IMU in the sensor
frame (gyro rad/s, accelerometer m/s², magnetometer µT, sensor-calibrated) at 285.7 Hz, optical
truth ``opt_quat`` (sensor → ENU, w x y z) whose heading the authors aligned with magnetic north,
``movement`` marks the scored samples.  The dataset's own evaluation (its example_code/
process_data.py and broad_utils.py) starts every filter from the first accelerometer and
magnetometer sample, maps its output to ENU and compares it with ``opt_quat`` as it is: no heading
offset is removed.  We do the same for every estimator here.

Frames: body FRD = sensor rotated 180° about x (``SENSOR_TO_FRD``), NED = ENU with x and y swapped
and z negated (``ENU_TO_NED``); both matrices are their own inverse.

Peers: ``vqf`` (VQF, Laidig & Seel, Information Fusion 91:187, 2023: online ``VQF`` and
``offlineVQF``, defaults, earth frame ENU), ``imufusion`` (x-io Fusion's C core; optional gyro
``Bias`` at-rest offset), the ``ahrs``
package's Madgwick (earth frame NWU: gravity +z, field in the x–z plane) and Mahony (earth frame
ENU: gravity +z, field in the y–z plane), each started from the first sample as BROAD does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.rotations import quaternion_from_dcm, quaternion_multiply, earth_frame_errors_rad

SENSOR_TO_FRD = np.diag([1.0, -1.0, -1.0])
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
NWU_TO_ENU = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
BROAD_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "broad"


@dataclass
class BroadTrial:
    name: str
    rate_hz: float
    gyro_rad_s: np.ndarray       # (N, 3) sensor frame
    acc_mps2: np.ndarray         # (N, 3) sensor frame
    mag_uT: np.ndarray           # (N, 3) sensor frame
    opt_quat: np.ndarray         # (N, 4) sensor -> ENU, NaN where the optical system lost the body
    movement: np.ndarray         # (N,) bool

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(len(self.gyro_rad_s)) / self.rate_hz

    def imu_frd(self) -> np.ndarray:
        """(N, 7) [t_s, gyro rad/s, specific force m/s²] in body FRD, our estimators' input."""
        return np.c_[self.t_s, self.gyro_rad_s @ SENSOR_TO_FRD, self.acc_mps2 @ SENSOR_TO_FRD]

    def mag_frd_mG(self) -> np.ndarray:
        """(N, 4) [t_s, field mG] in body FRD (1 µT = 10 mG)."""
        return np.c_[self.t_s, self.mag_uT @ SENSOR_TO_FRD * 10.0]


def trial_paths(directory: Path = BROAD_DIR) -> list[Path]:
    return sorted(directory.glob("*.hdf5"))


def load_trial(path: Path, seconds: float | None = None) -> BroadTrial:
    """One trial; ``seconds``: only its beginning (smoke runs)."""
    import h5py
    with h5py.File(path, "r") as f:
        fs = float(f.attrs["sampling_rate"])
        n = None if seconds is None else int(seconds * fs)
        d = {k: np.asarray(f[k][:n], dtype=float) for k in ("imu_gyr", "imu_acc", "imu_mag", "opt_quat")}
        return BroadTrial(Path(path).stem, fs, d["imu_gyr"], d["imu_acc"], d["imu_mag"], d["opt_quat"],
                          np.asarray(f["movement"][:n], dtype=bool).ravel())


def quat_enu_from_dcm_ned(c_body_to_ned: np.ndarray) -> np.ndarray:
    """Sensor → ENU quaternions from our body FRD → NED matrices (…, 3, 3)."""
    return quaternion_from_dcm(ENU_TO_NED @ np.asarray(c_body_to_ned) @ SENSOR_TO_FRD)


def score_deg(q_sensor_to_enu: np.ndarray, trial: BroadTrial) -> tuple[float, float]:
    """(heading RMS, inclination RMS) [deg] over the movement phase, the dataset's metric (samples
    without optical truth are left out, as its nan-mean does)."""
    heading, incl = earth_frame_errors_rad(q_sensor_to_enu, trial.opt_quat)
    m = trial.movement
    return tuple(math.degrees(math.sqrt(np.nanmean(e[m] ** 2))) for e in (heading, incl))


def initial_dcm_enu(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Sensor → ENU matrix from one accelerometer and magnetometer sample (TRIAD: up = specific
    force at rest, east = field × up), as BROAD's quatFromAccMag starts its filters."""
    up = acc / np.linalg.norm(acc)
    east = np.cross(mag, up)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    return np.array([east, north, up])


# ----------------------------------------------------------------------------- peers

def run_fusion(trial: BroadTrial, gain: float = 0.5, acc_rejection_deg: float = 0.0,
               mag_rejection_deg: float = 0.0, rejection_timeout_s: float = 0.0,
               gyro_bias: bool = False, mag_ignored_out: np.ndarray | None = None) -> np.ndarray:
    """x-io Fusion (imufusion) in its ENU convention on the sensor-frame data; gyro deg/s,
    accelerometer g.  ``gyro_bias``: run the gyro through Fusion's at-rest ``Bias`` first.
    ``mag_ignored_out`` (N,) bool, if given: Fusion's magnetic rejection at each sample
    (``magnetometer_ignored``: its own magnetic-disturbance flag)."""
    import imufusion
    s = imufusion.AhrsSettings()
    s.sample_rate = trial.rate_hz
    s.convention = imufusion.CONVENTION_ENU     # (the constructor ignores this argument in 1.3.3)
    s.gain = gain
    s.acceleration_rejection = acc_rejection_deg
    s.magnetic_rejection = mag_rejection_deg
    s.rejection_timeout = rejection_timeout_s
    ahrs = imufusion.Ahrs()
    ahrs.set_settings(s)
    bias = None
    if gyro_bias:
        bias = imufusion.Bias()
        bias.set_settings(imufusion.BiasSettings(sample_rate=trial.rate_hz))
    gyro = np.degrees(trial.gyro_rad_s)
    acc = trial.acc_mps2 / 9.80665
    mag = trial.mag_uT
    q = np.empty((len(gyro), 4))
    for i in range(len(gyro)):
        g = bias.update(gyro[i]) if bias is not None else gyro[i]
        ahrs.update(g, acc[i], mag[i])
        q[i] = ahrs.get_quaternion()
        if mag_ignored_out is not None:
            mag_ignored_out[i] = ahrs.get_internal_states().magnetometer_ignored
    return q


def run_madgwick(trial: BroadTrial, gain: float | None = None) -> np.ndarray:
    """``ahrs.filters.Madgwick`` (MARG update; default gain 0.041), earth frame NWU."""
    from ahrs.filters import Madgwick
    f = Madgwick(frequency=trial.rate_hz) if gain is None else Madgwick(frequency=trial.rate_hz, gain=gain)
    c0 = NWU_TO_ENU.T @ initial_dcm_enu(trial.acc_mps2[0], trial.mag_uT[0])
    q = np.empty((len(trial.acc_mps2), 4))
    q[0] = quaternion_from_dcm(c0)
    gyr, acc, mag = trial.gyro_rad_s, trial.acc_mps2, trial.mag_uT
    for i in range(1, len(q)):
        q[i] = f.updateMARG(q[i - 1], gyr[i], acc[i], mag[i])
    return quaternion_multiply(quaternion_from_dcm(NWU_TO_ENU), q)


def run_mahony(trial: BroadTrial, k_p: float | None = None, k_i: float | None = None) -> np.ndarray:
    """``ahrs.filters.Mahony`` (MARG update with its gyro-bias integral; defaults k_P 1.0,
    k_I 0.3), earth frame ENU."""
    from ahrs.filters import Mahony
    kw = {k: v for k, v in (("k_P", k_p), ("k_I", k_i)) if v is not None}
    f = Mahony(frequency=trial.rate_hz, **kw)
    q = np.empty((len(trial.acc_mps2), 4))
    q[0] = quaternion_from_dcm(initial_dcm_enu(trial.acc_mps2[0], trial.mag_uT[0]))
    gyr, acc, mag = trial.gyro_rad_s, trial.acc_mps2, trial.mag_uT
    for i in range(1, len(q)):
        q[i] = f.updateMARG(q[i - 1], gyr[i], acc[i], mag[i])
    return q


def run_vqf(trial: BroadTrial) -> np.ndarray:
    """VQF (Laidig & Seel 2023, PyPI ``vqf``) with its defaults: ``VQF(Ts).updateBatch`` on the
    sensor-frame data (earth frame ENU, as BROAD's truth); the 9-D quaternion."""
    import vqf
    g, a, m = (np.ascontiguousarray(x, dtype=float) for x in (trial.gyro_rad_s, trial.acc_mps2, trial.mag_uT))
    return np.asarray(vqf.VQF(1.0 / trial.rate_hz).updateBatch(g, a, m)["quat9D"])


def run_offline_vqf(trial: BroadTrial) -> np.ndarray:
    """VQF's offline mode (``vqf.offlineVQF``, forward-backward over the whole trial), defaults."""
    import vqf
    g, a, m = (np.ascontiguousarray(x, dtype=float) for x in (trial.gyro_rad_s, trial.acc_mps2, trial.mag_uT))
    return np.asarray(vqf.offlineVQF(g, a, m, 1.0 / trial.rate_hz)["quat9D"])
