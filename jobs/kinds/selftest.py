"""``selftest``: a tiny deterministic job kind for checking the engine itself (no Taichi, no catalogs).

Case ``i`` draws ``x ~ U(0, 1)`` and ``k ~ Poisson(lam)`` from ``default_rng([seed, i])``; the primary
dataset ``selftest_cases`` has one row per case (case_id, seed, x, k), the detail dataset
``selftest_items`` has ``k`` rows per case (case_id, item, y = x * item).  ``sleep_ms`` per case makes the
work last long enough to kill a run mid-way.  Used by the fault suite and the engine benchmarks
(``dualsight selftest run``); every number can be checked against numpy directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from dualsight.config import validate
from dualsight.jobs.engine.runner import default_run_id, prepare, run_job
from dualsight.jobs.engine.specs import preset_and_config

NAME = "selftest"
PRIMARY = "selftest_cases"
SCHEMAS = {
    "selftest_cases": pa.schema([("case_id", pa.int64()), ("seed", pa.int64()), ("x", pa.float64()),
                                 ("k", pa.int64())]),
    "selftest_items": pa.schema([("case_id", pa.int64()), ("item", pa.int64()), ("y", pa.float64())]),
}


class SelftestSpec(BaseModel):
    """seed: run seed; lam: mean items per case (0-50); sleep_ms: busy time per case (0-10000 ms)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    seed: int = Field(1, ge=0, le=2**63 - 1)
    lam: float = Field(3.0, ge=0, le=50)
    sleep_ms: float = Field(0.0, ge=0, le=10_000)

    def to_dict(self) -> dict:
        return self.model_dump(mode="json")


PRESETS = {"default": {"seed": 1}}
"""The presets of ``dualsight selftest run --preset NAME`` (one: the default)."""


def resolve_spec(preset: str | None, config, *, seed: int | None = None,
                 sleep_ms: float | None = None) -> tuple[dict, str]:
    """The spec dict of ``dualsight selftest run`` (the preset, the ``--config`` TOML over it, then the flags)
    and the source name its errors give."""
    d, source = preset_and_config(PRESETS, preset, config, default="default")
    if seed is not None:
        d["seed"] = seed
    if sleep_ms is not None:
        d["sleep_ms"] = sleep_ms
    return d, source


DEFAULT_CASES = 1000
"""Cases of a self-test run when none are given."""


@dataclass(frozen=True)
class SelftestRun:
    """A self-test run resolved and identified but not yet run (:func:`plan_run`, :func:`start_run`)."""

    spec: dict               # the spec dict of resolve_spec (the engine validates and canonicalises it)
    n_cases: int
    run_id: str
    spec_hash: str           # 16 hex digits (jobs/engine/runner.py spec_hash)
    source: str              # where the settings came from, for messages


def plan_run(preset: str | None = None, config=None, *, seed: int | None = None, cases: int | None = None,
             sleep_ms: float | None = None, run_id: str | None = None) -> SelftestRun:
    """Everything ``dualsight selftest run`` decides before the lake is touched, for it and ``dualsight.run``:
    the spec (:func:`resolve_spec`), the number of cases (default :data:`DEFAULT_CASES`), the run's identity
    (``prepare`` of jobs/engine/runner.py) and its id (``run_id``, default ``selftest-<spec hash>``)."""
    d, source = resolve_spec(preset, config, seed=seed, sleep_ms=sleep_ms)
    n = cases if cases is not None else DEFAULT_CASES
    _, _, _, h = prepare(NAME, d, n, source=source)
    return SelftestRun(d, n, run_id if run_id is not None else default_run_id(NAME, h), h, source)


def start_run(plan: SelftestRun, lake, *, workers: int | None = None, scheduler: str | None = None,
              shard_size: int | None = None, progress: bool = True) -> dict:
    """Run (or resume) a planned self-test into ``lake`` (a warehouse Lake) with the engine's ``run_job``;
    returns the final manifest.  Errors as ``run_job``'s."""
    return run_job(NAME, plan.spec, n_cases=plan.n_cases, lake=lake, run_id=plan.run_id, workers=workers,
                   scheduler=scheduler, shard_size=shard_size, progress=progress, source=plan.source)


def spec_from_dict(d: dict, source: str = "spec") -> SelftestSpec:
    return validate(SelftestSpec, d, source=source)


def make_context(spec: SelftestSpec):
    return None


def draw(seed: int, case_id: int, lam: float) -> tuple[float, int]:
    """(x, k) of one case: the reference the tests recompute independently."""
    rng = np.random.default_rng([seed, case_id])
    return float(rng.uniform()), int(rng.poisson(lam))


def compute_shard(spec: SelftestSpec, case_ids: np.ndarray, ctx) -> dict[str, pa.Table]:
    xs, ks = np.empty(len(case_ids)), np.empty(len(case_ids), dtype=np.int64)
    for n, i in enumerate(case_ids):
        xs[n], ks[n] = draw(spec.seed, int(i), spec.lam)
        if spec.sleep_ms:
            time.sleep(spec.sleep_ms / 1000)
    item_case = np.repeat(case_ids, ks)
    item = np.concatenate([np.arange(k) for k in ks]) if len(ks) else np.zeros(0, np.int64)
    y = np.repeat(xs, ks) * item
    return {"selftest_cases": pa.table({"case_id": case_ids.astype(np.int64), "seed": np.full(len(case_ids), spec.seed),
                                        "x": xs, "k": ks}, schema=SCHEMAS["selftest_cases"]),
            "selftest_items": pa.table({"case_id": item_case.astype(np.int64), "item": item.astype(np.int64),
                                        "y": y}, schema=SCHEMAS["selftest_items"])}


def shard_summary(tables) -> dict:
    return {"items": int(tables["selftest_items"].num_rows)}
