"""Jobs wing: offline work on whole logs.

* ``calibrate`` — ``calibrate_log(log)``: magnetometer calibration result of a log.
* ``analyze`` — ``analyze_log(log, calibration, mission)``: heading chain, WMM, velocity split,
  cross-track and interference alarms; ``inputs`` lines a log up on one time base;
  ``navigation`` reports GPS outages with the INS/GPS filter; ``report`` writes CSV and text.
* ``live`` — ``LiveAnalyzer``: the per-sample twin of analyze, for the station.

Imports: ``groundstation.io`` and estimators; never the station.
"""
