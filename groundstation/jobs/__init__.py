"""Jobs wing: offline work on whole logs.

* ``calibrate`` — ``calibrate_compasses(log)``: a calibration result per compass (windows, in-flight
  WMM fit, motor field, orientation, consistency); ``calibrate_log(log)`` the primary compass's.
  ``compass_raw`` rebuilds each compass's raw field with the corrections in force at each sample
  (shared with analyze); ``log_summary`` is what ``info`` says about the compasses.
* ``analyze`` — ``analyze_log(log, calibration, mission)``: heading chain, WMM, velocity split,
  cross-track and interference alarms, every compass against the WMM (``compass_report``); ``inputs`` lines a log up on one time base;
  ``navigation`` reports GPS outages with the INS/GPS filter; ``report`` writes CSV and text.
* ``live`` — ``LiveAnalyzer``: the per-sample twin of analyze, for the station.

Imports: ``groundstation.io`` and estimators; never the station.
"""
