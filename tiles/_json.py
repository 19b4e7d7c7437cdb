"""The JSON form of attributes: plain types only, strict JSON (no NaN).

Zarr attributes and the truth files are strict JSON, which has no NaN or
infinity: non-finite floats are written as zarr v3 spells them (``"NaN"``,
``"Infinity"``, ``"-Infinity"``) and read back with :func:`float_from_json`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
from pathlib import PurePath
from typing import Any

import numpy as np

from rsmb.ops._errors import ParameterError

_JSON_TO_NONFINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


def jsonable(obj: Any) -> Any:
    """Convert ``obj`` recursively to plain JSON types (strict JSON, no NaN).

    NumPy scalars become Python numbers, arrays and tuples become lists, paths
    become strings, dataclasses dicts, dates ISO 8601 strings, NumPy dtypes their
    name, sets sorted lists, dict keys strings.  Non-finite floats become the strings
    ``"NaN"``, ``"Infinity"`` and ``"-Infinity"`` (zarr v3's spelling).

    Raises
    ------
    ParameterError
        For an object with no JSON form; the message gives its location.
    """
    return _jsonable(obj, "attrs")


def _jsonable(obj: Any, where: str) -> Any:
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.generic):
        return _jsonable(obj.item(), where)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        if math.isfinite(obj):
            return float(obj)
        return "NaN" if math.isnan(obj) else ("Infinity" if obj > 0 else "-Infinity")
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist(), where)
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, np.dtype):
        return obj.name
    if isinstance(obj, (_dt.datetime, _dt.date, _dt.time)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        fields = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
        return _jsonable(fields, where)
    if isinstance(obj, dict):
        return {str(k): _jsonable(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, (set, frozenset)):
        return sorted((_jsonable(v, where) for v in obj), key=repr)
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    raise ParameterError(
        f"{where}: expected a JSON-serialisable value, got {type(obj).__name__}"
    )


def float_from_json(value: float | str | None) -> float | None:
    """Inverse of :func:`jsonable` for one number: ``"NaN"``, ``"Infinity"`` and
    ``"-Infinity"`` become floats; None and numbers pass through.

    Raises
    ------
    ParameterError
        For any other string.
    """
    if not isinstance(value, str):
        return value
    if value not in _JSON_TO_NONFINITE:
        raise ParameterError(
            f"value: expected a number, None, 'NaN', 'Infinity' or '-Infinity', got {value!r}"
        )
    return _JSON_TO_NONFINITE[value]
