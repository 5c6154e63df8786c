"""Strict JSON: non-finite numbers become ``null`` (RFC 8259 has no NaN or Infinity; Python's
``json`` would write the bare tokens ``NaN`` / ``Infinity`` that other readers reject)."""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def finite_or_none(value: Any) -> Any:
    """``value`` with every NaN / infinite float (numpy's too) replaced by None, recursively through
    dicts, lists and tuples; numpy scalars and arrays become plain Python values."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite_or_none(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps(obj: Any, **kwargs) -> str:
    """``json.dumps`` of ``obj`` with non-finite numbers as null; raises if any is left (allow_nan=False)."""
    return json.dumps(finite_or_none(obj), allow_nan=False, **kwargs)
