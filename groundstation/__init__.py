"""MagStation ground station, in four wings around one sample vocabulary.

* ``samples`` — the typed sample stream and ``FlightLog`` tables, in the internal units every
  wing shares (mG, rad/s, m/s², rad, NED/FRD, t_s).  ``paths``, ``jsonsafe``,
  ``process_memory``: small shared helpers.
* ``io`` — the outside world's formats: log readers (one module per format), the MAVLink decoder,
  live links, the tlog writer, missions, the replay clock, autopilot parameter conventions.
* ``jobs`` — offline work on whole logs: calibrate, analyze (and its live twin), reports.
* ``sim`` — known-truth flights, recordings and a fake vehicle.
* ``station`` — the live web station: FastAPI app (a router per resource), the hub, the viser
  scene, the calibration wizard.

Import directions (tests/test_architecture.py): ``io`` imports no other wing; ``jobs`` and ``sim``
use ``io``; ``station`` uses ``io`` and ``jobs`` (never ``jobs.fleet``); nothing but the CLI,
tests and benchmarks imports ``station``.  ``estimators`` (pure numpy; numba compiles the
sequential loops: the field-vector test's step, the AHRS's block logic) imports none of them.
"""
import os

# pymavlink picks its MAVLink 1 or 2 dialect from this at import time; 2 reads both.
os.environ.setdefault("MAVLINK20", "1")
