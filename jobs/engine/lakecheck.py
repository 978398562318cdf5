"""``dualsight lake check [--repair]``: verify every run of a lake, and recompute what is damaged.

Per run: the manifest parses and is consistent; every planned shard has every dataset's file, each
verified against the plan (:func:`dualsight.warehouse.lake.verify_shard`: metadata, spec hash, case
range, row count, exact case ids of the primary dataset); cases requested, cases found, and duplicated
case ids counted independently over the primary files.  ``--repair`` rebuilds a damaged manifest from
the run's identity copy (``_specs/<run>.json``) and resumes the run, which recomputes exactly the
shards that failed verification (the same rows: case i always draws from ``default_rng([seed, i])``).
"""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq

from dualsight.errors import InputError
from dualsight.warehouse.lake import Lake, LakeError
from dualsight.warehouse.shards import ShardInfo


def check_run(lake: Lake, run_id: str) -> dict:
    """One run's verdict: {run, kind, requested, found, duplicated (cases), shards (planned), damaged_shards,
    missing_shards (shard numbers), problems, verdict}."""
    row = {"run": run_id, "kind": None, "requested": None, "found": 0, "duplicated": 0, "damaged_shards": [],
           "missing_shards": [], "problems": [], "verdict": "ok"}
    manifest_damaged = False
    try:
        m = lake.read_manifest(run_id)
    except LakeError as e:
        row["problems"].append(e.detail)
        manifest_damaged = True
        m = lake.read_spec_copy(run_id)
    if m is None:
        row["verdict"] = "damaged" if manifest_damaged else "no manifest"
        return row
    row.update(kind=m["kind"], requested=m["n_cases"], status=m.get("status"), shards=m["n_shards"])
    ids = []
    for s in range(m["n_shards"]):
        start = s * m["shard_size"]
        info = ShardInfo(run_id, m["spec_hash"], s, start, min(m["n_cases"], start + m["shard_size"]))
        present = [lake.shard_path(d, run_id, s).exists() for d in m["datasets"]]
        if not any(present):
            row["missing_shards"].append(s)
            continue
        problem = lake.verify_shard(info, m["datasets"], m["primary"])
        if problem:
            row["damaged_shards"].append(s)
            row["problems"].append(f"shard {s}: {problem}")
            continue
        ids.append(pq.read_table(lake.shard_path(m["primary"], run_id, s), columns=["case_id"])
                   .column("case_id").to_numpy())
    allids = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
    uniq = np.unique(allids)
    row["found"] = int(len(uniq))
    row["duplicated"] = int(len(allids) - len(uniq))
    if manifest_damaged:
        row["verdict"] = "damaged manifest"
    elif row["damaged_shards"] or row["duplicated"]:
        row["verdict"] = "damaged"
    elif row["missing_shards"]:
        row["verdict"] = "incomplete" if m.get("status") != "complete" else "damaged"
    return row


def check_lake(lake: Lake, *, repair: bool = False, workers: int | None = None) -> list[dict]:
    """Verify every run of ``lake`` (and repair it when asked); one dict per run."""
    if not lake.root.is_dir():
        raise InputError("no such lake folder", source=str(lake.root))
    rows = []
    for rid in lake.run_ids():
        row = check_run(lake, rid)
        if repair and row["verdict"] not in ("ok", "no manifest", "incomplete"):
            row["repair"] = _repair(lake, rid, row, workers)
            if row["repair"] == "repaired":
                after = check_run(lake, rid)
                row.update(found_after=after["found"], duplicated_after=after["duplicated"],
                           verdict="repaired" if after["verdict"] == "ok" else after["verdict"])
        rows.append(row)
    return rows


def _repair(lake: Lake, run_id: str, row: dict, workers: int | None) -> str:
    from dualsight.jobs.engine.runner import run_job

    try:
        m = lake.read_manifest(run_id)
    except LakeError:
        m = lake.read_spec_copy(run_id)
        if m is None:
            return "impossible: manifest and its identity copy are both damaged"
        with lake.lock(run_id):
            lake.write_manifest(m)
    try:
        out = run_job(m["kind"], m["spec"], n_cases=m["n_cases"], lake=lake, run_id=run_id, workers=workers,
                      progress=False, label=m.get("label"))
    except InputError as e:
        return f"failed: {e}"
    return "repaired" if out["status"] == "complete" else f"failed: status {out['status']}"


def report_text(rows: list[dict]) -> str:
    from dualsight.warehouse.query import format_table

    if not rows:
        return "no runs"
    table = format_table(["run", "kind", "cases requested", "cases found", "duplicate cases", "shards",
                          "damaged shards", "missing shards", "verdict"],
                         [(r["run"], r["kind"], r["requested"], r.get("found_after", r["found"]),
                           r.get("duplicated_after", r["duplicated"]), r.get("shards", "-"), len(r["damaged_shards"]),
                           len(r["missing_shards"]), r["verdict"]) for r in rows])
    notes = [f"  {r['run']}: {p}" for r in rows for p in r["problems"][:5]]
    notes += [f"  {r['run']}: repair {r['repair']}" for r in rows if "repair" in r]
    return table + ("\n\n" + "\n".join(notes) if notes else "")
