"""Which job columns carry training progress, derived from the engine's :class:`ProgressEvent` (one list).

The engine reports progress as :class:`voxnerf.training.records.ProgressEvent`; the ``jobs`` table stores every
field of it but those in :data:`NOT_STORED`, under the same names. The table's columns
(:func:`progress_columns`), the values the job store writes (:func:`progress_values`) and the API's ``JobOut``
fields (``app/schemas.py``) are all built from :data:`PROGRESS_FIELDS`, so a field added to ``ProgressEvent``
reaches the store and the REST API without being listed anywhere else (an existing database needs the new
column added by hand: ``create_all`` does not alter tables).
"""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Iterable
from typing import Any

from pydantic import BaseModel
from sqlalchemy import JSON, Float, Integer, String
from sqlalchemy.orm import MappedColumn, mapped_column

from voxnerf.training.records import ProgressEvent

NOT_STORED = frozenset({"max_iters"})  # the job's options already hold it
PROGRESS_FIELDS: tuple[str, ...] = tuple(name for name in ProgressEvent.model_fields if name not in NOT_STORED)
STAGE_MAX_CHARS = 64
_SQL_TYPES = {int: Integer, float: Float, str: lambda: String(STAGE_MAX_CHARS), list: JSON}


def _base_type(annotation: Any) -> type:
    """``float`` for ``float | None``, ``list`` for ``list[EvalRecord]``..."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        (annotation,) = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
    return typing.get_origin(annotation) or annotation


def nullable(name: str) -> bool:
    """Whether the column (and the API field) may be null: the event's field is optional, or required (a job
    has no value for it until its first event, e.g. ``stage`` of a queued job)."""
    info = ProgressEvent.model_fields[name]
    annotation = info.annotation
    optional = type(None) in typing.get_args(annotation)
    return optional or info.is_required()


def default(name: str) -> Any:
    """The column's value before any event: the event field's default (a fresh list for list fields); None
    for a field every event carries."""
    info = ProgressEvent.model_fields[name]
    return None if info.is_required() else info.get_default(call_default_factory=True)


def initial_values() -> dict[str, Any]:
    """The progress columns of a job no worker has started."""
    return {name: default(name) for name in PROGRESS_FIELDS}


NULL_READS_AS_DEFAULT = "null_reads_as_default"  # column info: rows that predate the column may hold null


def progress_columns() -> dict[str, MappedColumn]:
    """One ``mapped_column`` per stored progress field, typed after the event's field."""
    columns = {}
    for name in PROGRESS_FIELDS:
        base = _base_type(ProgressEvent.model_fields[name].annotation)
        initial = default(name)
        columns[name] = mapped_column(
            _SQL_TYPES[base](),
            nullable=nullable(name),
            default=list if isinstance(initial, list) else initial,
            info={NULL_READS_AS_DEFAULT: True},  # JobOut reads a null as the field's default
        )
    return columns


def _plain(value: Any) -> Any:
    """JSON-like data of a field value; records keep only the keys they set (as in report.json)."""
    if isinstance(value, BaseModel):
        to_json = getattr(value, "to_json_dict", None)
        return to_json() if callable(to_json) else value.model_dump()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def json_safe(value: Any) -> Any:
    """A copy of a JSON-like value with every non-finite float replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def progress_values(event: ProgressEvent, names: Iterable[str] = PROGRESS_FIELDS) -> dict[str, Any]:
    """The column values of ``event``'s stored fields among ``names``: JSON-safe (NaN never reaches the
    store), and a non-finite number in a column that cannot be null becomes the column's default."""
    values = {}
    for name in names:
        if name not in PROGRESS_FIELDS:
            continue
        value = json_safe(_plain(getattr(event, name)))
        values[name] = default(name) if value is None and not nullable(name) else value
    return values
