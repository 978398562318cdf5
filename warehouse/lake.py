"""The Parquet data lake: layout, atomic shard writes, run manifests, resume bookkeeping.

Layout (DESIGN.md)::

    <lake>/<dataset>/run=<run_id>/part-<shard:06d>.parquet     one file per (dataset, run, shard)
    <lake>/_manifests/<run_id>.json                             one manifest per run

A shard is written to a hidden temporary name in the same folder, flushed to disk and then renamed
(atomic on POSIX), so a reader or a resumed run never sees half a file.  A shard of a run is *complete*
when the files of all the run's datasets exist; the primary dataset is renamed last.  A resumed run
recomputes only incomplete shards; since case i always draws from ``default_rng([seed, i])`` the
recomputed rows are identical, and shard file names are fixed, so nothing is lost or duplicated.

This module knows no algorithm: it moves Arrow tables and JSON.
"""

from __future__ import annotations

import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from dualsight.errors import InputError

MANIFEST_VERSION = 1
_RUN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}$")


def default_lake() -> Path:
    """``$DUALSIGHT_LAKE`` or ``./lake``."""
    return Path(os.environ.get("DUALSIGHT_LAKE", "lake"))


def check_run_id(run_id: str) -> str:
    if not isinstance(run_id, str) or not _RUN_ID.match(run_id):
        raise InputError(f"run id {run_id!r} must match {_RUN_ID.pattern} (letters, digits, '_', '-', '.')",
                         source="--run")
    return run_id


@dataclass(frozen=True)
class Lake:
    """A lake rooted at ``root`` (created on first write)."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    # ----------------------------------------------------------------- paths
    def run_dir(self, dataset: str, run_id: str) -> Path:
        return self.root / dataset / f"run={run_id}"

    def shard_path(self, dataset: str, run_id: str, shard: int) -> Path:
        return self.run_dir(dataset, run_id) / f"part-{shard:06d}.parquet"

    def manifest_path(self, run_id: str) -> Path:
        return self.root / "_manifests" / f"{run_id}.json"

    # ----------------------------------------------------------------- shards
    def write_shard(self, run_id: str, shard: int, tables: dict[str, pa.Table], primary: str) -> dict[str, int]:
        """Write one shard of every dataset atomically; the primary dataset's file is renamed last.

        Returns rows written per dataset.
        """
        tmp_paths = []
        try:
            order = [d for d in tables if d != primary] + [primary]
            for dataset in order:
                final = self.shard_path(dataset, run_id, shard)
                final.parent.mkdir(parents=True, exist_ok=True)
                tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
                pq.write_table(tables[dataset], tmp, compression="zstd")
                with open(tmp, "rb") as fh:
                    os.fsync(fh.fileno())
                tmp_paths.append((tmp, final))
            for tmp, final in tmp_paths:
                os.replace(tmp, final)
        finally:
            for tmp, _ in tmp_paths:
                if tmp.exists():
                    tmp.unlink()
        return {d: t.num_rows for d, t in tables.items()}

    def complete_shards(self, run_id: str, datasets: list[str]) -> set[int]:
        """Shards whose files exist for every dataset of the run."""
        done = None
        for dataset in datasets:
            d = self.run_dir(dataset, run_id)
            found = set()
            if d.is_dir():
                for p in d.glob("part-*.parquet"):
                    try:
                        found.add(int(p.stem.split("-")[1]))
                    except (IndexError, ValueError):
                        continue
            done = found if done is None else done & found
        return done or set()

    def remove_stale_temps(self, run_id: str, datasets: list[str]) -> int:
        """Delete temporary files an interrupted writer left behind (never complete shards)."""
        n = 0
        for dataset in datasets:
            d = self.run_dir(dataset, run_id)
            if d.is_dir():
                for p in d.glob(".part-*.tmp-*"):
                    p.unlink(missing_ok=True)
                    n += 1
        return n

    # ----------------------------------------------------------------- manifests
    def read_manifest(self, run_id: str) -> dict | None:
        p = self.manifest_path(run_id)
        if not p.exists():
            return None
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"manifest is corrupt ({e}); the shards are intact, move the manifest away to rebuild",
                             source=str(p)) from None

    def write_manifest(self, manifest: dict) -> Path:
        p = self.manifest_path(manifest["run_id"])
        p.parent.mkdir(parents=True, exist_ok=True)
        manifest = dict(manifest, updated_unix=time.time(), manifest_version=MANIFEST_VERSION)
        tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True, default=_json_default))
        os.replace(tmp, p)
        return p

    def new_run_id(self, prefix: str) -> str:
        """``<prefix>-<UTC timestamp>``, with a numeric suffix if that id exists already."""
        base = f"{prefix}-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        rid, n = base, 1
        while self.read_manifest(rid) is not None:
            n += 1
            rid = f"{base}-{n}"
        return rid

    def refuse_other_run(self, run_id: str, kind: str, spec: dict):
        """Raise unless ``run_id`` is new or holds a run of the same kind and spec (checked before any work)."""
        check_run_id(run_id)
        m = self.read_manifest(run_id)
        if m is None:
            return
        if m.get("kind") != kind or m.get("spec") != json.loads(json.dumps(spec, default=str)):
            raise InputError(f"run {run_id!r} already exists in {self.root} as a {m.get('kind')} run with other "
                             "settings or inputs; choose another --run", source="--run")

    def list_manifests(self) -> list[dict]:
        d = self.root / "_manifests"
        out = []
        if d.is_dir():
            for p in sorted(d.glob("*.json")):
                try:
                    out.append(json.loads(p.read_text()))
                except json.JSONDecodeError:
                    continue
        return out

    def datasets(self) -> list[str]:
        """Dataset folders that hold at least one shard."""
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir()
                      if p.is_dir() and not p.name.startswith(("_", ".")) and any(p.glob("run=*/part-*.parquet")))


def _json_default(o):
    import numpy as np

    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
