"""I/O wing: everything that reads or writes the outside world's formats.

* ``logs`` — ``read_log(path)``: .tlog, .bin, .ulg, .csv into a ``FlightLog`` (one module per format).
* ``decode`` — MAVLink messages into samples (units per the MAVLink XML, converted once).
* ``link`` — live MAVLink links (UDP/TCP/serial) as a sample stream; connection-string checks.
* ``mavlink`` — the MAVLink 2 encoder and the .tlog writer.
* ``mission`` — .waypoints / .plan / a log's mission.  ``replay`` — the replay clock.
* ``params`` — autopilot parameter conventions (ArduPilot COMPASS_*, PX4 CAL_MAG*).
* ``magcal`` — ArduPilot's MAG_CAL_PROGRESS completion mask (its 80-section geodesic grid).
* ``errors`` — ``IngestError``, the one error type (a one-line message for the user).

Imports: ``groundstation.samples`` and estimators only; never jobs, sim or station.
"""
