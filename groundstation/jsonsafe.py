"""JSON-safe values: numpy scalars and arrays to Python, NaN/inf to null (the one sanitiser)."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["jsonable", "json_default"]


def jsonable(obj):
    """A structure of dicts/lists/tuples/numpy values turned into plain JSON values (NaN -> None)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def json_default(o):
    """``json.dumps(default=...)`` hook for values the encoder does not know (hot path: no walk)."""
    if isinstance(o, (np.floating, np.integer, np.bool_, np.ndarray)):
        return jsonable(o)
    return str(o)
