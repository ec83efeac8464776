"""Exact JSON of frozen records (the FitReport and what it holds), and their equality.

Floats are written as Python's repr (json's default: the shortest string that reads back to
the same double), non-finite ones as "nan" / "inf" / "-inf" (JSON has no token for them),
arrays with their dtype and shape. Decoding follows the dataclass's type hints, so a record
needs no code of its own to be saved and loaded.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any

import numpy as np

from foamlab import FoamlabError


def encode(value: Any) -> Any:
    """JSON-ready form of a record (dataclass), array, float, dict, list or tuple."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: encode(getattr(value, f.name)) for f in dataclasses.fields(value)
                if f.metadata.get("saved", True)}
    if isinstance(value, np.ndarray):
        return _encode_array(value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _encode_float(float(value))
    if isinstance(value, dict):
        return {str(k): encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [encode(v) for v in value]
    return value


def _encode_float(v: float) -> float | str:
    return v if math.isfinite(v) else repr(v)          # 'nan', 'inf', '-inf'


def _encode_array(a: np.ndarray) -> dict:
    flat = a.ravel()
    if np.iscomplexobj(a):
        values = {"re": [_encode_float(float(v)) for v in flat.real], "im": [_encode_float(float(v)) for v in flat.imag]}
    elif a.dtype.kind == "f":
        values = {"values": [_encode_float(float(v)) for v in flat]}
    else:
        values = {"values": flat.tolist()}
    return {"dtype": a.dtype.str, "shape": list(a.shape), **values}


def decode(hint: Any, data: Any) -> Any:
    """The value of type ``hint`` (a dataclass, np.ndarray, scalar or container hint) that
    ``encode`` wrote as ``data``. Raises FoamlabError on a malformed entry."""
    try:
        return _decode(hint, data)
    except (KeyError, TypeError, ValueError) as exc:
        raise FoamlabError(f"fit report: missing or malformed entry ({type(exc).__name__}: {exc})") from None


def _decode(hint: Any, data: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if data is None and type(None) in args:
            return None
        return _decode(next(a for a in args if a is not type(None)), data)
    if hint is np.ndarray:
        return _decode_array(data)
    if dataclasses.is_dataclass(hint):
        hints = typing.get_type_hints(hint)
        # a field with a default may be missing: the record was written before it was added
        values = {f.name: _decode(hints[f.name], data[f.name]) for f in dataclasses.fields(hint)
                  if f.init and f.metadata.get("saved", True) and (f.name in data or not _has_default(f))}
        return hint(**values)
    if origin is dict:
        return {k: _decode(args[1], v) for k, v in data.items()} if args else dict(data)
    if origin in (list, tuple):
        item = args[0] if args else Any
        items = [_decode(item, v) for v in data]
        return tuple(items) if origin is tuple else items
    if hint is float:
        return float(data)
    if hint in (int, bool, str):
        if not isinstance(data, hint):
            raise TypeError(f"{data!r} is not {hint.__name__}")
        return data
    return data


def _has_default(f: dataclasses.Field) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _decode_array(data: dict) -> np.ndarray:
    dtype = np.dtype(data["dtype"])
    if dtype.kind == "c":
        flat = np.array([float(v) for v in data["re"]]) + 1j * np.array([float(v) for v in data["im"]])
    elif dtype.kind == "f":
        flat = np.array([float(v) for v in data["values"]], dtype=float)
    else:
        flat = np.array(data["values"])
    return flat.astype(dtype).reshape(data["shape"])


def same(a: Any, b: Any) -> bool:
    """Field by field equality of records: arrays by dtype, shape and value (nan equal to nan),
    fields marked compare=False (working state) left out."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a) if f.compare)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype
                and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    number = (int, float, np.integer, np.floating)
    if isinstance(a, number) and isinstance(b, number) and not isinstance(a, (bool, np.bool_)):
        return not isinstance(b, (bool, np.bool_)) and (a == b or (math.isnan(a) and math.isnan(b)))
    return type(a) is type(b) and a == b
