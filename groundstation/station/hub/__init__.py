"""The session hub and its parts (sources, vehicle, flight); see ``session.Session``."""
