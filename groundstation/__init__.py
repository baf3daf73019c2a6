"""MagStation ground station: ingest, replay, session hub, server, scene and CLI."""
import os

# pymavlink picks its MAVLink 1 or 2 dialect from this at import time; 2 reads both.
os.environ.setdefault("MAVLINK20", "1")
