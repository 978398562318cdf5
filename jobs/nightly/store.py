"""What the nightly keeps: the verdicts dataset ``nightly_verdicts`` and the accepted baseline.

* Verdicts: one run per night, ``nightly-<night>-verdicts``, written like any job's shard (one Parquet file
  with its identity in the metadata, a journal entry, a manifest), so the lake's read-only views, ``runs``
  and ``lake check`` see a verified dataset.  ``case_id`` is the row index.
* Baseline: ``<lake>/_nightly/baseline.json`` (written to a temporary file, fsynced, renamed) holds only the
  accepted night's run ids per job, the fresh seed and the accepted nights' throughputs; every number is
  read from the lake's datasets.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

from dualsight.errors import InputError
from dualsight.jobs.engine.runner import spec_hash, versions
from dualsight.jobs.nightly.compare import throughput
from dualsight.version import code_version
from dualsight.warehouse.lake import Lake, write_json_atomic
from dualsight.warehouse.query import connect, run_report
from dualsight.warehouse.shards import ShardInfo

DATASET = "nightly_verdicts"
SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("night", pa.string()), ("suite", pa.string()), ("job", pa.string()),
    ("kind", pa.string()), ("comparison", pa.string()), ("metric", pa.string()),
    ("baseline", pa.float64()), ("now", pa.float64()), ("test", pa.string()), ("threshold_or_p", pa.float64()),
    ("alpha", pa.float64()), ("verdict", pa.string()), ("direction", pa.string()),
    ("n_baseline", pa.int64()), ("n_now", pa.int64()), ("baseline_run", pa.string()), ("now_run", pa.string()),
    ("note", pa.string()),
])
BASELINE_VERSION = 1
MAX_HISTORY = 30
NIGHT_RE = re.compile(r"\d{8}T\d{6}Z(\.\d{1,3})?")


def night_id(lake: Lake, now: float | None = None) -> str:
    """``YYYYMMDDTHHMMSSZ`` (UTC), with ``.2``, ``.3``... when that second has a night already."""
    base = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now if now is not None else time.time()))
    taken = {rid for rid in lake.run_ids() if rid.startswith(f"nightly-{base}")}
    night, n = base, 1
    while any(r.startswith(f"nightly-{night}-") for r in taken):
        n += 1
        night = f"{base}.{n}"
    return night


def run_id(night: str, job: str, fresh: bool = False) -> str:
    return f"nightly-{night}-{job}" + (".fresh" if fresh else "")


def _f(v):
    return None if v is None or (isinstance(v, float) and not np.isfinite(v)) else float(v)


def verdict_table(rows: list[dict], night: str, suite: str) -> pa.Table:
    cols = {f.name: [] for f in SCHEMA}
    for i, r in enumerate(rows):
        vals = {"case_id": i, "night": night, "suite": suite, "job": r["job"], "kind": r["kind"],
                "comparison": r["comparison"], "metric": r["metric"], "baseline": _f(r.get("baseline")),
                "now": _f(r.get("now")), "test": r.get("test") or "", "threshold_or_p": _f(r.get("threshold")),
                "alpha": _f(r.get("alpha")), "verdict": r["verdict"], "direction": r.get("direction") or "",
                "n_baseline": r.get("n_baseline"), "n_now": r.get("n_now"), "baseline_run": r.get("baseline_run"),
                "now_run": r.get("now_run"), "note": r.get("note") or ""}
        for k, v in vals.items():
            cols[k].append(v)
    return pa.table({f.name: pa.array(cols[f.name], type=f.type) for f in SCHEMA}, schema=SCHEMA)


def write_verdicts(lake: Lake, night: str, suite: str, rows: list[dict], summary: dict) -> str:
    """Write the night's verdicts as run ``nightly-<night>-verdicts`` of dataset ``nightly_verdicts``."""
    rid = run_id(night, "verdicts")
    table = verdict_table(rows, night, suite)
    n = table.num_rows
    spec = {"night": night, "suite": suite}
    h = spec_hash(DATASET, spec, n)
    with lake.lock(rid):
        entry = lake.write_shard(ShardInfo(rid, h, 0, 0, n), {DATASET: table}, DATASET, {DATASET: SCHEMA})
        lake.reset_journal(rid, [entry])
        manifest = {"run_id": rid, "kind": DATASET, "job": "nightly", "label": f"nightly {night} verdicts",
                    "spec": spec, "spec_hash": h, "code_version": code_version(), "seed": None, "n_cases": n,
                    "shard_size": n, "n_shards": 1, "datasets": [DATASET], "primary": DATASET,
                    "versions": versions(), "created_unix": time.time(), "status": "complete", "shards_done": 1,
                    "stats": {}, "nightly": summary}
        lake.write_spec_copy(manifest)
        lake.write_manifest(manifest)
    return rid


# ============================================================================================ baseline
def baseline_path(lake: Lake) -> Path:
    return lake.root / "_nightly" / "baseline.json"


def read_baseline(lake: Lake) -> dict | None:
    """The accepted baseline, None when none was accepted; InputError (one line) when the file is damaged."""
    p = baseline_path(lake)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise InputError(f"is damaged ({type(e).__name__}); restore it, or accept a new baseline with "
                         "`dualsight nightly --accept`", source=str(p)) from None
    ok = (isinstance(doc, dict) and doc.get("version") == BASELINE_VERSION and isinstance(doc.get("jobs"), dict)
          and isinstance(doc.get("night"), str) and isinstance(doc.get("history", []), list)
          and all(isinstance(v, dict) and isinstance(v.get("fixed"), str) for v in doc["jobs"].values()))
    if not ok:
        raise InputError(f"is not a nightly baseline (version {BASELINE_VERSION}: night, "
                         "jobs {name: {fixed, fresh}}, "
                         "history); restore it or run `dualsight nightly --accept`", source=str(p))
    return doc


def accept(lake: Lake, night: str, suite: str, runs: dict, old: dict | None) -> Path:
    """Make ``night`` the baseline: its run ids per job, its throughputs appended to the history (atomic)."""
    jobs, tp = {}, {}
    for name, r in runs.items():
        if r.get("fixed") is None:
            continue
        m = lake.read_manifest(r["fixed"])
        rate, _, _ = throughput(m) if m else (None, None, None)
        jobs[name] = {"kind": r["kind"], "fixed": r["fixed"], "fresh": r.get("fresh"),
                      "fresh_seed": r.get("fresh_seed"), "throughput": rate}
        if rate:
            tp[name] = rate
    history = list((old or {}).get("history") or []) + [{"night": night, "throughput": tp}]
    doc = {"version": BASELINE_VERSION, "night": night, "suite": suite, "accepted_unix": time.time(),
           "jobs": jobs, "history": history[-MAX_HISTORY:]}
    return write_json_atomic(baseline_path(lake), doc)


def throughput_history(baseline: dict | None, job: str) -> list[float]:
    return [h.get("throughput", {}).get(job) for h in (baseline or {}).get("history", [])
            if isinstance(h, dict) and h.get("throughput", {}).get(job)]


# ============================================================================================ history
def history(lake: Lake) -> tuple[list[dict], list[dict]]:
    """(every verdict row, one summary row per night) from the nightly_verdicts dataset, by SQL."""
    if DATASET not in lake.datasets():
        raise InputError(f"no nightly verdicts in {lake.root}; run `dualsight nightly` first", source="--lake")
    con = connect(lake)
    try:
        cols, rows = run_report(con, "nightly_history")
        ncols, nrows = run_report(con, "nightly_nights")
    finally:
        con.close()
    nights = [dict(zip(ncols, r)) for r in nrows]
    for n in nights:                    # the night's outcome, from its verdict run's manifest
        try:
            info = (lake.read_manifest(run_id(n["night"], "verdicts")) or {}).get("nightly") or {}
        except InputError:
            info = {}
        n["exit"], n["accepted"] = info.get("exit"), bool(info.get("accepted"))
    return [dict(zip(cols, r)) for r in rows], nights


def trends(rows: list[dict]) -> list[dict]:
    """Verdict rows grouped per (job, comparison, metric), nights in order."""
    out: dict = {}
    for r in rows:
        key = (r["job"], r["comparison"], r["metric"])
        t = out.setdefault(key, {"job": key[0], "comparison": key[1], "metric": key[2], "points": []})
        t["points"].append({k: r[k] for k in ("night", "baseline", "now", "verdict", "threshold_or_p", "alpha",
                                               "test", "note")})
    return list(out.values())
