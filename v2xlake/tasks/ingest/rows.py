"""Row-model helpers shared by the ingest modules."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import pyarrow as pa
from pydantic import BaseModel

from v2xlake.schemas.arrow import rows_to_table


def table_of(model: type[BaseModel], rows: Sequence[BaseModel] | Sequence[dict[str, Any]]
             ) -> pa.Table:
    """``rows_to_table`` for any sequence of row models (keeps mypy's list invariance happy)."""
    return rows_to_table(model, cast(list[BaseModel], list(rows)))
