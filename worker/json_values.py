"""Plain JSON values from the pipeline's results (metrics, summaries, placements)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def jsonable(obj: Any, max_array: int | None = None) -> Any:
    """``obj`` with numpy scalars and arrays as plain numbers and lists, non-finite floats
    as None, dict keys as strings. Arrays of more than ``max_array`` elements become a
    shape note (``"array[100, 3]"``) and unknown objects their ``str`` when ``max_array``
    is given (summaries); otherwise arrays are kept whole and unknown objects as they are.
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v, max_array) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, max_array) for v in obj]
    if isinstance(obj, np.ndarray):
        if max_array is not None and obj.size > max_array:
            return f"array{list(obj.shape)}"
        return jsonable(obj.tolist(), max_array)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if max_array is None or obj is None or isinstance(obj, str):
        return obj
    return str(obj)
