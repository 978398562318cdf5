"""The Parquet data lake: layout, atomic self-describing shards, manifests, shard journals, locks, checks.

Layout (docs/architecture.md, Conventions: "Lake")::

    <lake>/<dataset>/run=<run_id>/part-<shard:06d>.parquet   one file per (dataset, run, shard)
    <lake>/_manifests/<run_id>.json                           the run: kind, canonical spec, spec hash, plan, status
    <lake>/_manifests/<run_id>.shards.jsonl                   journal: one line per completed shard (files, sizes, rows)
    <lake>/_specs/<run_id>.json                               immutable copy of the run's identity (for repair)
    <lake>/_locks/<run_id>.lock                               held (flock) by the one process writing the run

Trust rules
    * A shard file is written to a hidden temporary name in its folder, fsynced and renamed (atomic on
      POSIX); the primary dataset is renamed last.  Nobody ever sees half a file under a final name.
    * Every shard file carries, in its Parquet key-value metadata (key ``dualsight``), the run id, the
      spec hash, the shard number and its case range ``[case_start, case_stop)`` and its row count, so a
      file is checked against what the run expects (:func:`verify_shard`), never trusted by its name.
    * A completed shard is appended to the run's journal with every file's size.  Queries read exactly
      the journalled files whose size still matches (:meth:`Lake.readable_files`); files that are not in a
      journal (copied in, written by a crashed writer) are never counted, and a damaged file or manifest
      is reported by name and left out while every other run stays readable.
    * One writer per run (``flock`` on ``_locks/<run>.lock``, released by the OS when its process dies);
      any number of runs may be written into one lake at once.

This module knows no algorithm: it moves Arrow tables and JSON.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dualsight.errors import InputError
from dualsight.warehouse.paths import RUN_ID_RE, check_run_id, os_error_text
from dualsight.warehouse.shards import META_KEY, ShardInfo, read_shard_meta, verify_shard

MANIFEST_VERSION = 2
MAX_MANIFEST_BYTES = 64 * 2**20


def parquet_options(schema: pa.Schema) -> dict:
    """Keyword arguments of ``pq.write_table`` for a shard of ``schema`` (issue 24 point 5: bytes per case).

    zstd (level 3) on every column, one row group per shard file (a shard is at most a few thousand rows: the
    summaries and the replay read whole shards).  Encodings by column type, before zstd:

    * float32/float64 columns and fixed-size lists of them: BYTE_STREAM_SPLIT (the bytes of each value split
      into streams, so that zstd sees the sign/exponent bytes together: 10-15% smaller than PLAIN here);
    * ``case_id``: DELTA_BINARY_PACKED (consecutive ids: ~0 bytes per row instead of ~2.4);
    * every other column: dictionary (statuses, small counts, constants), Parquet's default.

    Min/max statistics only on the non-float columns (``case_id``'s are what :func:`verify_shard` checks and what
    ``WHERE case_id = ...`` prunes by); the floats' would cost ~1 byte per case in the footers and prune nothing.
    """
    enc, rest = {}, []
    for path, t in _leaves(schema):
        if pa.types.is_floating(t):
            enc[path] = "BYTE_STREAM_SPLIT"
        elif path == "case_id" and pa.types.is_integer(t):
            enc[path] = "DELTA_BINARY_PACKED"
        else:
            rest.append(path)
    return {"compression": "zstd", "compression_level": 3, "column_encoding": enc, "use_dictionary": rest,
            "write_statistics": rest + [p for p in enc if p == "case_id"]}


def _leaves(schema: pa.Schema) -> list[tuple[str, pa.DataType]]:
    """(Parquet column path, leaf type) of every leaf column of ``schema`` (lists: ``name.list.element``, structs:
    ``name.field``, maps: ``name.key_value.key`` / ``.value``), in schema order."""
    out = []

    def walk(path: str, t: pa.DataType):
        if pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
            walk(f"{path}.list.element", t.value_type)
        elif pa.types.is_map(t):
            walk(f"{path}.key_value.key", t.key_type)
            walk(f"{path}.key_value.value", t.item_type)
        elif pa.types.is_struct(t):
            for i in range(t.num_fields):
                walk(f"{path}.{t.field(i).name}", t.field(i).type)
        else:
            out.append((path, t))

    for f in schema:
        walk(f.name, f.type)
    return out


class LakeError(InputError):
    """The lake cannot be written or read as asked (read-only, full, locked, damaged)."""


class RunLock:
    """Exclusive, non-blocking ``flock`` on ``<lake>/_locks/<run>.lock``; the OS drops it when the process dies."""

    def __init__(self, lake: "Lake", run_id: str):
        self.path = lake.root / "_locks" / f"{run_id}.lock"
        self.run_id = run_id
        self.fh = None

    def __enter__(self):
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fh = open(self.path, "a+")
        except OSError as e:
            raise LakeError(f"cannot write to the lake ({os_error_text(e)})", source=str(self.path.parent.parent)) \
                from None
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            fh.close()
            if e.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise LakeError(f"run {self.run_id!r} is being written by {holder}; wait for it to finish or "
                                "choose another --run", source=str(self.path)) from None
            raise LakeError(f"cannot lock the run ({os_error_text(e)})", source=str(self.path)) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {os.uname().nodename}\n")
        fh.flush()
        self.fh = fh
        return self

    def __exit__(self, *exc):
        if self.fh is not None:
            try:
                self.fh.seek(0)
                self.fh.truncate()
            except OSError:
                pass
            fcntl.flock(self.fh.fileno(), fcntl.LOCK_UN)
            self.fh.close()
            self.fh = None
        return False


@dataclass(frozen=True)
class RunHealth:
    """What :meth:`Lake.scan` found for one run: readable files per dataset and the problems."""

    run_id: str
    manifest: dict | None
    files: dict            # dataset -> [Path, ...] journalled, present, size as journalled
    problems: list         # one line each: damaged manifest, missing or changed files


@dataclass(frozen=True)
class RunRecord:
    """One run as ``dualsight runs`` lists it (:func:`run_records`).

    ``status`` is the live status (:meth:`Lake.live_status`), followed by " (damaged files)" when a shard file
    is damaged or missing (one line each in ``problems``); ``shards`` is "done/planned" ("?" when unknown).
    A run whose manifest is damaged has ``manifest`` None, ``status`` "damaged", the reason as its one
    ``problems`` line and None in the other fields."""

    run_id: str
    kind: str | None
    n_cases: int | None
    shards: str | None
    status: str
    seed: int | None
    spec_hash: str | None
    problems: tuple[str, ...]
    manifest: dict | None

    @property
    def damaged(self) -> bool:
        """Whether the run's manifest is damaged (unreadable or inconsistent)."""
        return self.manifest is None


@dataclass(frozen=True)
class Lake:
    """A lake rooted at ``root``.  Nothing is created until a run is written."""

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

    def journal_path(self, run_id: str) -> Path:
        return self.root / "_manifests" / f"{run_id}.shards.jsonl"

    def lock(self, run_id: str) -> RunLock:
        return RunLock(self, check_run_id(run_id))

    def is_being_written(self, run_id: str) -> bool:
        """True while some process holds the run's lock (read-only probe, works on a read-only lake)."""
        try:
            with open(self.root / "_locks" / f"{run_id}.lock") as fh:
                try:
                    fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
                except OSError:
                    return True
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
                return False
        except OSError:
            return False

    def live_status(self, manifest: dict) -> str:
        """The manifest's status, except that "running" without a live writer reads "stopped (resume it)"."""
        st = manifest.get("status", "?")
        if st == "running" and not self.is_being_written(manifest["run_id"]):
            return "stopped (run the same command to resume)"
        return st

    # ----------------------------------------------------------------- shards
    def write_shard(self, info: ShardInfo, tables: dict[str, pa.Table], primary: str,
                    schemas: dict[str, pa.Schema] | None = None) -> dict:
        """Write one shard of every dataset atomically (the primary's file renamed last).

        Each table must match ``schemas[dataset]`` exactly when schemas are given.  Returns the journal
        entry ``{"shard", "case_start", "case_stop", "rows": {dataset: n}, "bytes": {dataset: n}}``.
        """
        tmp_paths = []
        out = {"shard": info.shard, "case_start": info.case_start, "case_stop": info.case_stop, "rows": {},
               "bytes": {}}
        try:
            order = [d for d in tables if d != primary] + [primary]
            for dataset in order:
                t = tables[dataset]
                if schemas is not None and not t.schema.equals(schemas[dataset]):
                    raise TypeError(f"dataset {dataset}: table schema differs from the declared schema")
                meta = dict(t.schema.metadata or {})
                meta[META_KEY] = json.dumps(info.meta(dataset, t.num_rows)).encode()
                t = t.replace_schema_metadata(meta)
                final = self.shard_path(dataset, info.run_id, info.shard)
                final.parent.mkdir(parents=True, exist_ok=True)
                tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
                tmp_paths.append((tmp, final))
                pq.write_table(t, tmp, **parquet_options(t.schema))
                with open(tmp, "rb") as fh:
                    os.fsync(fh.fileno())
                out["rows"][dataset] = t.num_rows
                out["bytes"][dataset] = tmp.stat().st_size
            for tmp, final in tmp_paths:
                os.replace(tmp, final)
        finally:
            for tmp, _ in tmp_paths:
                try:
                    tmp.unlink()
                except FileNotFoundError:
                    pass
        return out

    def verify_shard(self, info: ShardInfo, datasets: list[str], primary: str) -> str | None:
        """None when every dataset's file of shard ``info`` is present and exactly right, else the problem."""
        for d in datasets:
            p = self.shard_path(d, info.run_id, info.shard)
            if not p.exists():
                return f"{p.name} of {d} is missing"
            problem = verify_shard(p, info, d, primary=(d == primary))
            if problem:
                return f"{d}/{p.name} {problem}"
        return None

    def shard_entry(self, info: ShardInfo, datasets: list[str]) -> dict:
        """Journal entry of an existing, verified shard (sizes and rows read from the files)."""
        out = {"shard": info.shard, "case_start": info.case_start, "case_stop": info.case_stop, "rows": {},
               "bytes": {}}
        for d in datasets:
            p = self.shard_path(d, info.run_id, info.shard)
            out["rows"][d] = pq.read_metadata(p).num_rows
            out["bytes"][d] = p.stat().st_size
        return out

    def shard_indices_on_disk(self, run_id: str, datasets: list[str]) -> set[int]:
        """Shard numbers that have a final-named file in any dataset of the run."""
        found = set()
        for d in datasets:
            folder = self.run_dir(d, run_id)
            if folder.is_dir():
                for p in folder.glob("part-*.parquet"):
                    m = re.fullmatch(r"part-(\d{6,})\.parquet", p.name)
                    if m:
                        found.add(int(m.group(1)))
        return found

    def foreign_spec_hashes(self, run_id: str, datasets: list[str], spec_hash: str, limit: int = 50) -> set[str]:
        """Spec hashes other than ``spec_hash`` recorded in this run's shard files (a sample of ``limit`` files)."""
        out = set()
        n = 0
        for d in datasets:
            folder = self.run_dir(d, run_id)
            if not folder.is_dir():
                continue
            for p in sorted(folder.glob("part-*.parquet")):
                meta, _, problem = read_shard_meta(p)
                if meta is not None and meta.get("spec_hash") != spec_hash:
                    out.add(str(meta.get("spec_hash")))
                n += 1
                if n >= limit:
                    return out
        return out

    def remove_shard(self, run_id: str, shard: int, datasets: list[str]):
        for d in datasets:
            self.shard_path(d, run_id, shard).unlink(missing_ok=True)

    def remove_stale_temps(self, run_id: str, datasets: list[str]) -> int:
        """Delete temporary files an interrupted writer left behind (never final-named files)."""
        n = 0
        for d in datasets:
            folder = self.run_dir(d, run_id)
            if folder.is_dir():
                for p in folder.glob(".part-*.tmp-*"):
                    p.unlink(missing_ok=True)
                    n += 1
        return n

    # ----------------------------------------------------------------- journal
    def reset_journal(self, run_id: str, entries: list[dict]):
        """Replace the run's journal with ``entries`` (atomic)."""
        p = self.journal_path(run_id)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
        with open(tmp, "w") as fh:
            for e in entries:
                fh.write(json.dumps(e, sort_keys=True) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)

    def append_journal(self, run_id: str, entry: dict):
        """Append one completed shard to the run's journal (one line, flushed)."""
        with open(self.journal_path(run_id), "a") as fh:
            fh.write(json.dumps(entry, sort_keys=True) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    def read_journal(self, run_id: str) -> list[dict]:
        """Journal entries, last entry per shard; a torn or damaged line is skipped."""
        p = self.journal_path(run_id)
        out = {}
        try:
            with open(p) as fh:
                for line in fh:
                    try:
                        e = json.loads(line)
                        out[int(e["shard"])] = e
                    except (ValueError, KeyError, TypeError):
                        continue
        except (FileNotFoundError, UnicodeDecodeError, IsADirectoryError):
            return []
        return [out[k] for k in sorted(out)]

    # ----------------------------------------------------------------- manifests
    def read_manifest(self, run_id: str) -> dict | None:
        """The run's manifest, None when there is none; LakeError when it is damaged."""
        p = self.manifest_path(run_id)
        try:
            if p.stat().st_size > MAX_MANIFEST_BYTES:
                raise LakeError(f"manifest is damaged (over {MAX_MANIFEST_BYTES >> 20} MiB)", source=str(p))
            m = json.loads(p.read_text())
        except (FileNotFoundError, NotADirectoryError):
            return None
        except (ValueError, UnicodeDecodeError, IsADirectoryError, PermissionError) as e:
            raise LakeError(f"manifest is damaged ({type(e).__name__}); `dualsight lake check --repair` rebuilds "
                            "it from the shards", source=str(p)) from None
        problem = _manifest_problem(m, run_id)
        if problem:
            raise LakeError(f"manifest is damaged ({problem}); `dualsight lake check --repair` rebuilds it from "
                            "the shards", source=str(p))
        return m

    def write_manifest(self, manifest: dict) -> Path:
        """Write the manifest atomically (temporary file, fsync, rename)."""
        manifest = dict(manifest, updated_unix=time.time(), manifest_version=MANIFEST_VERSION)
        return write_json_atomic(self.manifest_path(manifest["run_id"]), manifest)

    def spec_copy_path(self, run_id: str) -> Path:
        return self.root / "_specs" / f"{run_id}.json"

    def write_spec_copy(self, manifest: dict):
        """Keep an immutable copy of the run's identity (kind, spec, hash, plan) beside the manifest, written
        once, so a damaged manifest can be rebuilt (``lake check --repair``)."""
        p = self.spec_copy_path(manifest["run_id"])
        if p.exists():
            return
        keep = {k: manifest[k] for k in ("run_id", "kind", "job", "spec", "spec_hash", "code_version", "seed",
                                         "n_cases", "shard_size", "n_shards", "datasets", "primary", "label",
                                         "created_unix") if k in manifest}
        write_json_atomic(p, keep)

    def read_spec_copy(self, run_id: str) -> dict | None:
        """The run's identity copy, or None when absent or damaged."""
        try:
            m = json.loads(self.spec_copy_path(run_id).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        m = dict(m, status="incomplete", stats={})
        return m if _manifest_problem(m, run_id) is None else None

    def run_ids(self) -> list[str]:
        """Run ids that have a manifest file (valid or not), sorted."""
        d = self.root / "_manifests"
        if not d.is_dir():
            return []
        return sorted(p.name[:-5] for p in d.glob("*.json") if not p.name.startswith(".")
                      and RUN_ID_RE.fullmatch(p.name[:-5]))

    def list_manifests(self) -> list[dict]:
        """Valid manifests, sorted by run id (damaged ones are reported by :meth:`scan`)."""
        out = []
        for rid in self.run_ids():
            try:
                m = self.read_manifest(rid)
            except LakeError:
                continue
            if m is not None:
                out.append(m)
        return out

    # ----------------------------------------------------------------- reading
    def scan(self, run_id: str) -> RunHealth:
        """Readable files of one run and its problems, without opening any Parquet file (stat only)."""
        try:
            m = self.read_manifest(run_id)
        except LakeError as e:
            return RunHealth(run_id, None, {}, [f"run {run_id}: {e}"])
        if m is None:
            return RunHealth(run_id, None, {}, [f"run {run_id}: no manifest"])
        files, problems = {}, []
        for e in self.read_journal(run_id):
            for d, size in (e.get("bytes") or {}).items():
                if d not in m["datasets"]:
                    continue
                p = self.shard_path(d, run_id, int(e["shard"]))
                try:
                    ok = p.stat().st_size == size
                except OSError:
                    ok = False
                if ok:
                    files.setdefault(d, []).append(p)
                else:
                    problems.append(f"run {run_id}: {d}/{p.name} is damaged or missing (size differs from the "
                                    "journal); left out")
        return RunHealth(run_id, m, files, problems)

    def readable_files(self) -> tuple[dict[str, list[Path]], list[str]]:
        """Every run's readable files per dataset, and the problems found (one line each)."""
        files: dict[str, list[Path]] = {}
        problems: list[str] = []
        for rid in self.run_ids():
            h = self.scan(rid)
            problems.extend(h.problems)
            for d, ps in h.files.items():
                files.setdefault(d, []).extend(ps)
        return files, problems

    def datasets(self) -> list[str]:
        """Datasets with at least one readable shard."""
        return sorted(self.readable_files()[0])

    def new_run_id(self, prefix: str) -> str:
        """``<prefix>-<UTC timestamp>``, with a numeric suffix if that id exists already."""
        base = f"{prefix}-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        rid, n = base, 1
        while self.manifest_path(rid).exists():
            n += 1
            rid = f"{base}-{n}"
        return rid


def write_json_atomic(path: Path, doc) -> Path:
    """Write ``doc`` as JSON to ``path`` atomically: a temporary file in the same folder (created if
    needed, inside the lake), fsync, rename; a reader sees the old file or the new one, never half."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w") as fh:
            fh.write(json.dumps(doc, indent=1, sort_keys=True, default=_json_default))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def run_records(lake: Lake) -> list[RunRecord]:
    """Every run that has a manifest file, sorted by run id: its manifest, live status and damaged files
    (stat only, no Parquet file is opened)."""
    out = []
    for rid in lake.run_ids():
        try:
            m = lake.read_manifest(rid)
        except LakeError as e:
            out.append(RunRecord(rid, None, None, None, "damaged", None, None, (e.detail,), None))
            continue
        if m is None:                                    # removed since it was listed
            continue
        h = lake.scan(rid)
        status = lake.live_status(m) + (" (damaged files)" if h.problems else "")
        out.append(RunRecord(rid, m.get("kind"), m.get("n_cases"), f"{m.get('shards_done', '?')}/{m.get('n_shards')}",
                             status, m.get("seed"), m.get("spec_hash"), tuple(h.problems), m))
    return out


def _manifest_problem(m, run_id: str) -> str | None:
    if not isinstance(m, dict):
        return "not a JSON object"
    need = {"run_id": str, "kind": str, "spec_hash": str, "n_cases": int, "shard_size": int, "n_shards": int,
            "datasets": list, "primary": str, "status": str}
    for k, t in need.items():
        if not isinstance(m.get(k), t) or isinstance(m.get(k), bool):
            return f"key {k!r} missing or not a {t.__name__}"
    if m["run_id"] != run_id:
        return f"run_id {m['run_id']!r} differs from its file name"
    if not all(isinstance(d, str) and re.fullmatch(r"[a-z][a-z0-9_]{0,63}", d) for d in m["datasets"]):
        return "bad dataset names"
    if m["primary"] not in m["datasets"]:
        return "primary dataset not among the datasets"
    if not (0 < m["shard_size"] and 0 < m["n_cases"] and m["n_shards"] == -(-m["n_cases"] // m["shard_size"])):
        return "inconsistent plan (n_cases, shard_size, n_shards)"
    return None


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
