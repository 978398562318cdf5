"""Self-describing shard files: the identity every Parquet shard carries, and its verification.

Every shard file holds, in its Parquet key-value metadata under :data:`META_KEY`, the run id, spec hash,
shard number, dataset, case range ``[case_start, case_stop)`` and row count it was written with
(:meth:`ShardInfo.meta`).  :func:`verify_shard` checks a file against what its run expects, so a file is never
trusted by its name.  Reads only Parquet footers (and the ``case_id`` column of primary shards).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

META_KEY = b"dualsight"


@dataclass(frozen=True)
class ShardInfo:
    """What one shard of a run must be: identity and case range ``[case_start, case_stop)``."""

    run_id: str
    spec_hash: str
    shard: int
    case_start: int
    case_stop: int

    def meta(self, dataset: str, rows: int) -> dict:
        return {"run_id": self.run_id, "spec_hash": self.spec_hash, "shard": self.shard, "dataset": dataset,
                "case_start": self.case_start, "case_stop": self.case_stop, "rows": rows}


def read_shard_meta(path: Path) -> tuple[dict | None, pq.FileMetaData | None, str | None]:
    """(dualsight metadata, Parquet footer, problem) of a shard file; problem is None when readable."""
    try:
        md = pq.read_metadata(path)
    except (OSError, pa.ArrowException) as e:
        return None, None, f"unreadable Parquet ({str(e).splitlines()[0][:120]})"
    kv = md.metadata or {}
    if META_KEY not in kv:
        return None, md, "no dualsight metadata (not written by dualsight)"
    try:
        meta = json.loads(kv[META_KEY])
    except (ValueError, UnicodeDecodeError):
        return None, md, "damaged dualsight metadata"
    return meta, md, None


def verify_shard(path: Path, expect: ShardInfo, dataset: str, *, primary: bool) -> str | None:
    """None when ``path`` is exactly shard ``expect`` of ``dataset``; otherwise what is wrong (one line).

    Checks: the footer reads; run id, spec hash, shard number and case range in the metadata; the row
    count in the footer equals the recorded one; ``case_id`` lies in the case range (footer statistics);
    for the primary dataset (one row per case) the case ids are exactly ``case_start .. case_stop-1``.
    """
    meta, md, problem = read_shard_meta(path)
    if problem:
        return problem
    for key in ("run_id", "spec_hash", "shard", "case_start", "case_stop", "dataset"):
        want = getattr(expect, key) if key != "dataset" else dataset
        if meta.get(key) != want:
            return f"belongs to another run or plan ({key} {meta.get(key)!r}, expected {want!r})"
    if md.num_rows != meta.get("rows"):
        return f"has {md.num_rows} rows, its metadata says {meta.get('rows')}"
    try:
        if primary:
            ids = pq.read_table(path, columns=["case_id"]).column("case_id").to_numpy()
            if not np.array_equal(ids, np.arange(expect.case_start, expect.case_stop)):
                return f"case ids are not exactly {expect.case_start}..{expect.case_stop - 1}"
        elif md.num_rows:
            col = md.schema.to_arrow_schema().get_field_index("case_id")
            for g in range(md.num_row_groups):
                st = md.row_group(g).column(col).statistics if col >= 0 else None
                if st is not None and st.has_min_max and not (expect.case_start <= st.min and
                                                              st.max < expect.case_stop):
                    return f"case ids {st.min}..{st.max} outside {expect.case_start}..{expect.case_stop - 1}"
    except (OSError, pa.ArrowException) as e:
        return f"unreadable Parquet ({str(e).splitlines()[0][:120]})"
    return None
