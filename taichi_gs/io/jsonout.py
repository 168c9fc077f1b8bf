"""Strict JSON out: every JSON file and ``--json`` line goes through :func:`dumps`.

JSON has no NaN or Infinity (Python's ``json`` writes them by default, and strict readers such as
``jq``, JavaScript or Go then fail), so non-finite numbers become ``null``; inside an object the
key ``<name>_null_reason`` says why. Callers that know the cause (e.g. "fewer than 3 frames
matched") pass it in ``reasons``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import write_text

NULL_REASON_SUFFIX = "_null_reason"


def _default_reason(value: float) -> str:
    return f"not a finite number ({value!r} in the computation)"


def finite_or_null(obj: Any, reasons: dict[str, str] | None = None) -> Any:
    """``obj`` with numpy scalars/arrays made plain and non-finite floats replaced by None; in a
    dict, key ``k`` that became None gains a sibling ``k_null_reason`` (``reasons[k]`` if given)."""
    reasons = reasons or {}
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        for key, value in obj.items():
            clean = finite_or_null(value, reasons)
            out[key] = clean
            if clean is None and _is_nonfinite(value):
                out[f"{key}{NULL_REASON_SUFFIX}"] = reasons.get(str(key), _default_reason(float(value)))
        return out
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v, reasons) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_or_null(obj.tolist(), reasons)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _is_nonfinite(value: Any) -> bool:
    return isinstance(value, (float, np.floating)) and not math.isfinite(value)


def dumps(obj: Any, indent: int | None = None, reasons: dict[str, str] | None = None) -> str:
    """Strict JSON text (``allow_nan=False``) of ``obj`` after :func:`finite_or_null`."""
    return json.dumps(finite_or_null(obj, reasons), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: Any, indent: int | None = 2, reasons: dict[str, str] | None = None) -> None:
    """Write :func:`dumps` of ``obj`` (plus a newline) atomically."""
    write_text(path, dumps(obj, indent=indent, reasons=reasons) + "\n")
