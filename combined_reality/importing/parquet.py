"""Parquet tables (pyarrow): one column per channel, one row per sample."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mapping import ImportMapping, MappingError
from .raw import RawTable, require_column_time

__all__ = ["read_parquet"]


def read_parquet(path: Path, mapping: ImportMapping) -> RawTable:
    import pyarrow as pa
    import pyarrow.parquet as pq

    require_column_time(mapping, "column")
    try:
        schema = pq.read_schema(path)
    except FileNotFoundError:
        raise MappingError(f"{path}: file not found.") from None
    except (OSError, pa.ArrowException) as e:
        raise MappingError(f"{path}: not a readable Parquet file ({str(e).splitlines()[0] if str(e) else e}).") \
            from None
    wanted = mapping.source_names()
    missing = [n for n in wanted if n not in schema.names]
    if missing:
        more = " ..." if len(schema.names) > 12 else ""
        raise MappingError(f"{path}: no column {', '.join(repr(n) for n in missing)} (the table has "
                           f"{', '.join(repr(n) for n in schema.names[:12])}{more}).")
    try:
        table = pq.read_table(path, columns=wanted)
    except (OSError, pa.ArrowException) as e:
        raise MappingError(f"{path}: cannot read the columns ({str(e).splitlines()[0] if str(e) else e}).") from None
    by_source = {}
    for name in wanted:
        col = table.column(name)
        if not (pa.types.is_integer(col.type) or pa.types.is_floating(col.type)):
            raise MappingError(f"{path}, column '{name}': type {col.type} is not a number.")
        if col.null_count:
            row = int(np.flatnonzero(np.asarray(col.is_null()))[0])
            raise MappingError(f"{path}, row {row + 1}, column '{name}': no value (null); every mapped channel needs "
                               f"a value in every row.")
        values = np.asarray(col.to_numpy(), dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise MappingError(f"{path}, row {int(bad[0]) + 1}, column '{name}': {values[bad[0]]} is not a finite "
                               f"number.")
        by_source[name] = values
    if table.num_rows < 2:
        raise MappingError(f"{path}: {table.num_rows} row(s); a run needs at least 2 samples.")
    return RawTable(columns={ch.name: by_source[ch.source] for ch in mapping.channels},
                    locate=lambda i: f"row {i + 1}", describe=f"Parquet, {table.num_rows} rows")
