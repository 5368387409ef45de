"""The results table: Parquet (pyarrow), one row per case in case order."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dob_hil.errors import ConfigError


def write_table(rows: list[dict[str, Any]], path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    ordered = sorted(rows, key=lambda r: int(r["index"]))
    pq.write_table(pa.Table.from_pylist(ordered), path)


def read_table(path: Path) -> list[dict[str, Any]]:
    import pyarrow.parquet as pq

    try:
        rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
    except (OSError, ValueError) as exc:
        raise ConfigError(str(path), f"not a results table: {exc}") from None
    return rows
