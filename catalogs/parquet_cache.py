"""Cached Parquet tables (the star catalog, the blobber's area tables): an atomic write and a read that
returns None for a missing, unreadable or stale file (the caller then rebuilds it).

A table is written to a temporary name in the destination folder and renamed into place (``os.replace``),
so a reader never sees a half-written file; the cache folder and content keys are
:mod:`dualsight.catalogs.cache`'s.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

__all__ = ["write_parquet_atomic", "read_parquet_or_none"]


def write_parquet_atomic(table: pa.Table, path: str | os.PathLike) -> Path:
    """Write ``table`` to ``path`` via a temporary file in the same folder and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def read_parquet_or_none(path: str | os.PathLike, metadata_key: bytes, expected: bytes) -> pa.Table | None:
    """Read a cached table, or ``None`` if it is missing, unreadable, or its schema metadata
    ``metadata_key`` is not ``expected`` (a stale or foreign file: the caller rebuilds it)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException):
        return None
    meta = table.schema.metadata or {}
    if meta.get(metadata_key) != expected:
        return None
    return table
