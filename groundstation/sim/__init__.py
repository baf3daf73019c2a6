"""Simulation wing: known-truth flights, recordings and a fake vehicle.

* ``flight_sim`` — closed-loop multirotor physics with magnetic interference (seed 002 sec. 2).
* ``scenarios`` — the named scenarios written as real MAVLink ``.tlog`` files + truth JSON
  (``magstation simulate``, ``python -m groundstation.sim.scenarios --make-recordings``).
* ``fake_vehicle`` — a MAVLink peer over UDP that streams a simulation, answers parameters and
  acts on calibration commands (``fake_autopilot``: its compass correction, onboard calibrator,
  fixed-yaw calibration); ``vehicle_streams`` — IMU/compass/GPS streams of up to three
  compasses (with mounting rotations) from an attitude history.
* ``truth`` — small array-level truth generators for estimator tests and benchmarks.

Imports: estimators and ``groundstation.io`` (formats); never the station.
"""
