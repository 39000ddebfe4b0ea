"""JSON-ready values: NumPy to Python, non-finite floats to None (JSON never holds NaN)."""

from __future__ import annotations

import math

import numpy as np


def json_safe(x):
    """`x` with NumPy scalars and arrays as Python values, sets as sorted lists, and
    every non-finite float as None."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, set):
        return sorted(x)
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    return x
