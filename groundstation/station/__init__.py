"""Station wing: the live web station.

* ``app`` — ``create_app`` (FastAPI from one router per resource in ``routers/``), ``Station``
  (hub + viser + uvicorn), ``serve``; ``settings`` — ``StationSettings``; ``deps`` — the hub
  dependency and the mapping of hub errors to HTTP; ``schemas`` — API models; ``push`` — /ws.
* ``hub`` — ``Session``: one lock and one state version over ``sources`` (live link or replay),
  ``vehicle`` (identity, parameters, confirmed writes) and ``flight`` (estimation, alarms, route).
* ``wizard`` — the guided calibration; ``scene`` — the viser 3-D view; ``tables`` — growing arrays.

Imports: ``groundstation.io``, ``groundstation.jobs`` and estimators.  Only the CLI, tests and
benchmarks import the station.
"""
