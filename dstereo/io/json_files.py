"""JSON out: one conversion of numpy values and paths for every file the package writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def json_default(value):
    """`json.dumps(default=...)` for numpy arrays and scalars and paths (float64 exact: `repr` digits)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")


def jsonable(value):
    """Nested dicts, lists, tuples, numpy arrays and scalars and paths as plain JSON values; NaN and infinities
    as None (strict JSON has no such numbers); dict keys as strings."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def json_text(data, indent: int = 2) -> str:
    """Strict JSON text of `data` (see `jsonable`)."""
    return json.dumps(jsonable(data), indent=indent, allow_nan=False)


def write_json(path: Path, data) -> None:
    """`data` as strict, indented JSON with a final newline."""
    Path(path).write_text(json_text(data) + "\n")
