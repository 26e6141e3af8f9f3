"""Arrow schemas derived from pydantic row models, so each table is defined exactly once.

A field may pin its Arrow type with ``Annotated[float, ArrowType(pa.float32())]``; otherwise the
Python annotation decides (int -> int64, float -> float64, str/enum -> string, list -> list).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Annotated, Any

import pyarrow as pa
from pydantic import BaseModel


@dataclass(frozen=True)
class ArrowType:
    type: pa.DataType


F32 = Annotated[float, ArrowType(pa.float32())]
F64 = Annotated[float, ArrowType(pa.float64())]
I32 = Annotated[int, ArrowType(pa.int32())]
I64 = Annotated[int, ArrowType(pa.int64())]
U8 = Annotated[int, ArrowType(pa.uint8())]
U16 = Annotated[int, ArrowType(pa.uint16())]


def _arrow_type(tp: Any) -> tuple[pa.DataType, bool]:
    """Return (arrow type, nullable) for a Python annotation."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        base, *meta = typing.get_args(tp)
        for m in meta:
            if isinstance(m, ArrowType):
                _, nullable = _arrow_type(base)
                return m.type, nullable
        return _arrow_type(base)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) != 1:
            raise TypeError(f"unsupported union {tp}")
        t, _ = _arrow_type(args[0])
        return t, True
    if origin is list:
        (item,) = typing.get_args(tp)
        t, _ = _arrow_type(item)
        return pa.list_(t), False
    if origin is dict:
        return pa.string(), False  # stored as JSON text
    if isinstance(tp, type):
        if issubclass(tp, bool):
            return pa.bool_(), False
        if issubclass(tp, Enum):
            return pa.string(), False
        if issubclass(tp, int):
            return pa.int64(), False
        if issubclass(tp, float):
            return pa.float64(), False
        if issubclass(tp, str):
            return pa.string(), False
    raise TypeError(f"no Arrow type for annotation {tp!r}")


def arrow_schema(model: type[BaseModel]) -> pa.Schema:
    hints = typing.get_type_hints(model, include_extras=True)
    fields = []
    for name in model.model_fields:
        t, nullable = _arrow_type(hints[name])
        fields.append(pa.field(name, t, nullable=nullable))
    return pa.schema(fields, metadata={"v2xlake.model": model.__name__})


def rows_to_table(model: type[BaseModel],
                  rows: Sequence[BaseModel] | Sequence[dict[str, Any]]) -> pa.Table:
    """Validate rows through the model, then build a table with the derived schema."""
    dicts = [
        (r if isinstance(r, model) else model.model_validate(r)).model_dump(mode="json")
        for r in rows
    ]
    schema = arrow_schema(model)
    return pa.Table.from_pylist(dicts, schema=schema)


def columns_to_table(model: type[BaseModel], columns: dict[str, Any]) -> pa.Table:
    """Build a table from NumPy columns (bulk tables like points) with the derived schema.

    Missing nullable columns become nulls, missing columns whose model field has a default
    (a counter added later, e.g. ``n_zero``) that default; any other missing column is an
    error, so a writer cannot silently drop a field.
    """
    schema = arrow_schema(model)
    n = len(next(iter(columns.values()))) if columns else 0
    arrays = []
    for f in schema:
        default = getattr(model.model_fields.get(f.name), "default", None)
        if f.name in columns:
            v = columns[f.name]
            arr = v.cast(f.type) if isinstance(v, pa.Array) else pa.array(v, type=f.type)
            arrays.append(arr)
        elif f.nullable:
            arrays.append(pa.nulls(n, type=f.type))
        elif isinstance(default, int | float | str | bool):
            arrays.append(pa.array([default] * n, type=f.type))
        else:
            raise KeyError(f"{model.__name__}: column {f.name!r} missing")
    extra = set(columns) - set(schema.names)
    if extra:
        raise KeyError(f"{model.__name__}: unknown columns {sorted(extra)}")
    return pa.Table.from_arrays(arrays, schema=schema)
