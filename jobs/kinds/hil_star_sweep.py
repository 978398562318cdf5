"""The ``hil_star_sweep`` job kind: a grid of detection/identification settings over a user's own images,
as one resumable, parallel job (issue 11, point 6).

Spec: the ``hil_star`` spec's camera, images and truths, plus ``variants``: one complete ``hil_star``
settings table per grid point, and ``labels``: each variant's ``key=value`` text.  With V variants and N
images there are V * N cases; case ``c`` is image ``c % N`` processed with variant ``c // N``, so a
shard is a run of images of one variant (the catalogs a variant needs are loaded once per process).

Datasets: ``hil_sweep`` (the ``hil_star`` row of each case, plus ``variant``, ``variant_label`` and
``image_index``) and ``hil_sweep_stars`` (the ``hil_star_stars`` rows, with ``variant``).
The sweep's summary (:func:`summarize`) ranks the variants: with truth by solve rate minus wrong rate,
without truth by how often a variant's answer agrees with the other variants' answers for the same image.

Sweepable keys (:data:`SWEEP_KEYS`) are the ``hil star`` command-line options of the same names.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from pydantic import Field

from dualsight.config import validate
from dualsight.errors import ConfigError, InputError
from dualsight.jobs.kinds import hil_star as hs
from dualsight.jobs.kinds.hil_common import Frozen, ImageEntry
from dualsight.jobs.kinds.hil_star_spec import HilStarSpec, StarSettings, StarTruth
from dualsight.warehouse.cells import percent

NAME = "hil_star_sweep"
PRIMARY = "hil_sweep"

SWEEP_KEYS = {
    # option name: (argparse attribute, type, allowed range text)
    "k-sigma": ("k_sigma", float, "[0, 1000]"),
    "min-pixels": ("min_pixels", int, "[1, 2^32]"),
    "max-stars": ("max_stars", int, "[2, 1000]"),
    "tolerance-arcsec": ("tolerance_arcsec", float, "(0, 36000]"),
    "mag-limit": ("mag_limit", float, "[-2, 12]"),
    "background-block": ("background_block", int, "0 or [4, 4096]"),
    "method": ("method", str, "robust | paper"),
    "detector": ("detector", str, "local | global"),
}
"""The keys ``--sweep`` takes: each is a ``hil star`` option (same name, same meaning and checks)."""

MAX_VARIANTS = 1000
AGREE_ARCSEC = 60.0
"""Two answers for one image agree when their boresights are within this angle (arcsec)."""


def parse_sweeps(items: list[str]) -> list[tuple[str, list]]:
    """``["k-sigma=3,4,5", "max-stars=25,40"]`` -> ``[("k-sigma", [3.0, 4.0, 5.0]), ("max-stars", [25, 40])]``.
    One-line InputError (source ``--sweep``) for an unknown key, a bad value or a repeated key."""
    out, seen = [], set()
    for it in items:
        key, sep, vals = it.partition("=")
        key = key.strip()
        if not sep or not vals.strip():
            raise InputError(f"must be KEY=V1,V2,... got {it!r}", source="--sweep")
        if key not in SWEEP_KEYS:
            raise InputError(f"unknown key {key!r}; sweepable: {', '.join(SWEEP_KEYS)}", source="--sweep")
        if key in seen:
            raise InputError(f"key {key!r} given twice", source="--sweep")
        seen.add(key)
        typ = SWEEP_KEYS[key][1]
        try:
            values = [typ(v.strip()) for v in vals.split(",")]
        except ValueError:
            raise InputError(f"{key}: values must be {typ.__name__}s, got {vals!r}", source="--sweep") from None
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            raise InputError(f"{key}: values must be finite, got {vals!r}", source="--sweep")
        if len(set(values)) != len(values):
            raise InputError(f"{key}: repeated value in {vals!r}", source="--sweep")
        out.append((key, values))
    n = math.prod(len(v) for _, v in out)
    if n > MAX_VARIANTS:
        raise InputError(f"the grid has {n} settings; at most {MAX_VARIANTS}", source="--sweep")
    return out


def grid(sweeps: list[tuple[str, list]]) -> list[dict]:
    """Every combination, in order: a list of ``{key: value}``."""
    keys = [k for k, _ in sweeps]
    return [dict(zip(keys, combo)) for combo in itertools.product(*(v for _, v in sweeps))]


def label(point: dict) -> str:
    return ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in point.items())


# ============================================================================================ spec
class SweepSpec(Frozen):
    """A validated ``hil_star_sweep`` run (module docstring)."""

    camera: dict
    images: tuple[ImageEntry, ...] = Field(min_length=1, max_length=10_000_000)
    truths: tuple[StarTruth, ...] = ()
    variants: tuple[StarSettings, ...] = Field(min_length=1, max_length=MAX_VARIANTS)
    labels: tuple[str, ...] = Field(min_length=1, max_length=MAX_VARIANTS)

    def variant_spec(self, v: int) -> HilStarSpec:
        """The ``hil_star`` spec of variant ``v`` (validated, normalised)."""
        return hs.spec_from_dict({"camera": self.camera, "settings": self.variants[v].to_dict(),
                                  "images": [e.to_dict() for e in self.images],
                                  "truths": [t.to_dict() for t in self.truths]},
                                 source=f"sweep variant {self.labels[v]}")


def spec_from_dict(d: dict, source: str = "spec") -> SweepSpec:
    m = validate(SweepSpec, d, source=source)
    if len(m.labels) != len(m.variants):
        raise ConfigError(f"must have one label per variant ({len(m.variants)}), got {len(m.labels)}",
                          source=source, field="labels")
    first = m.variant_spec(0)          # checks camera, images and truths once; variants are normalised here
    variants = tuple(m.variant_spec(v).settings for v in range(len(m.variants)))
    return m.model_copy(update={"camera": first.camera, "variants": variants})


def build_spec(base: HilStarSpec, variants: list[StarSettings], labels: list[str]) -> dict:
    """The sweep spec dict from a ``hil_star`` spec (camera, images, truths) and the variants' settings."""
    d = base.to_dict()
    return {"camera": d["camera"], "images": d["images"], "truths": d["truths"],
            "variants": [v.to_dict() for v in variants], "labels": list(labels)}


def n_cases(spec: SweepSpec) -> int:
    return len(spec.variants) * len(spec.images)


# ============================================================================================ engine contract
@dataclass
class Context:
    spec: SweepSpec
    per_variant: dict


def make_context(spec: SweepSpec) -> Context:
    return Context(spec, {})


def _variant(ctx: Context, v: int):
    """(spec, context) of variant ``v``, built once per process; catalogs shared by equal catalog tables."""
    if v not in ctx.per_variant:
        vspec = ctx.spec.variant_spec(v)
        ctx.per_variant[v] = (vspec, hs.make_context(vspec))
    return ctx.per_variant[v]


def memory_estimate(spec: SweepSpec) -> int:
    """The largest variant's ``hil_star`` estimate (a worker holds one batch at a time) plus the others'
    catalogs, bounded by the distinct catalog settings."""
    ests = [hs.memory_estimate(spec.variant_spec(v)) for v in range(len(spec.variants))]
    return max(ests) + (len({str(s.catalog) for s in spec.variants}) - 1) * 64 * 2 ** 20


_EXTRA = [("variant", pa.int32()), ("variant_label", pa.string()), ("image_index", pa.int64())]
SCHEMA = pa.schema(list(hs.IMAGES_SCHEMA) + [pa.field(n, t) for n, t in _EXTRA])
STARS_SCHEMA = pa.schema(list(hs.STARS_SCHEMA) + [pa.field("variant", pa.int32())])
SCHEMAS = {PRIMARY: SCHEMA, "hil_sweep_stars": STARS_SCHEMA}


def compute_shard(spec: SweepSpec, case_ids: np.ndarray, ctx: Context) -> dict[str, pa.Table]:
    """Rows of cases ``case_ids`` (ascending): each variant's images through ``hil_star``'s batch."""
    N = len(spec.images)
    ids = np.asarray(case_ids, np.int64)
    parts, star_parts = [], []
    for v in np.unique(ids // N):
        vspec, vctx = _variant(ctx, int(v))
        imgs = [int(k) for k in ids[ids // N == v] % N]
        bs = vspec.settings.batch_size
        results = []
        for s in range(0, len(imgs), bs):
            results.extend(hs._run_batch(imgs[s:s + bs], vspec, vctx))
        t = hs.tables(results)
        base, stars = t[hs.PRIMARY], t["hil_star_stars"]
        img_idx = base.column("case_id")
        base = base.set_column(0, "case_id", pa.compute.add(img_idx, pa.scalar(int(v) * N, pa.int64())))
        n = base.num_rows
        base = (base.append_column("variant", pa.array(np.full(n, v, np.int32)))
                .append_column("variant_label", pa.array([spec.labels[int(v)]] * n, pa.string()))
                .append_column("image_index", img_idx))
        sc = stars.column("case_id")
        stars = stars.set_column(stars.schema.get_field_index("case_id"), "case_id",
                                 pa.compute.add(sc, pa.scalar(int(v) * N, pa.int64())))
        stars = stars.append_column("variant", pa.array(np.full(stars.num_rows, v, np.int32)))
        parts.append(base.cast(SCHEMA))
        star_parts.append(stars.cast(STARS_SCHEMA))
    return {PRIMARY: pa.concat_tables(parts) if parts else SCHEMA.empty_table(),
            "hil_sweep_stars": pa.concat_tables(star_parts) if star_parts else STARS_SCHEMA.empty_table()}


def shard_summary(tbls: dict[str, pa.Table]) -> dict[str, int]:
    t = tbls[PRIMARY]
    return {"cases": t.num_rows, "identified": int(pa.compute.sum(t.column("identified").fill_null(False)).as_py()
                                                    or 0)}


def progress_postfix(stats: dict) -> str:
    n = stats.get("cases", 0)
    return f"identified {100 * stats.get('identified', 0) / n:.1f}%" if n else ""


# ============================================================================================ summary
def summarize(rows: list[dict], n_variants: int, labels: list[str]) -> list[dict]:
    """One dict per variant, best first.

    rows : the run's ``hil_sweep`` rows (dicts with variant, image_index, identified, status, A_est,
        truth_source, t_total_ns, error).
    Per variant: images, solved (identified) rate, with truth the wrong rate (status confident_wrong)
    and the success rate; without truth the agreement: the share of its answers whose boresight lies
    within :data:`AGREE_ARCSEC` of the boresight most variants found for that image (the largest group
    of mutually agreeing answers, ties to the lower variant); mean ms per image.  Ranked by success rate
    with truth, otherwise by solved rate x agreement; then by time.
    """
    N = 1 + max((r["image_index"] for r in rows), default=-1)
    z = np.full((n_variants, N, 3), np.nan)
    solved = np.zeros((n_variants, N), bool)
    for r in rows:       # one row per (variant, image): bookkeeping over rows, not pixels
        if r["identified"] and r["A_est"] is not None:
            z[r["variant"], r["image_index"]] = np.asarray(r["A_est"], float)[6:9]
            solved[r["variant"], r["image_index"]] = True
    # consensus boresight per image: the answer agreeing with the most others
    cosl = math.cos(AGREE_ARCSEC * math.pi / (180 * 3600))
    dots = np.einsum("vnk,wnk->nvw", np.nan_to_num(z), np.nan_to_num(z))           # (N, V, V)
    close = (dots >= cosl) & solved.T[:, :, None] & solved.T[:, None, :]
    support = close.sum(axis=2)                                                    # (N, V)
    best = np.argmax(support, axis=1)
    agrees = close[np.arange(N), best, :].T & (support.max(axis=1) > 0)[None, :]   # (V, N)
    out = []
    for v in range(n_variants):
        rv = [r for r in rows if r["variant"] == v and r["error"] is None]
        n = len(rv)
        with_truth = [r for r in rv if r["truth_source"] != "none"]
        nt = len(with_truth)
        d = {"variant": v, "label": labels[v], "images": n,
             "solved_rate": (sum(bool(r["identified"]) for r in rv) / n) if n else None,
             "success_rate": (sum(r["status"] == "success" for r in with_truth) / nt) if nt else None,
             "wrong_rate": (sum(r["status"] == "confident_wrong" for r in with_truth) / nt) if nt else None,
             "agreement": (float(agrees[v][solved[v]].mean()) if solved[v].any() else None),
             "ms_per_image": (float(np.mean([r["t_total_ns"] for r in rv if r["t_total_ns"] is not None])) / 1e6
                              if n else None)}
        d.update(_cost(rv))
        out.append(d)

    def key(d):
        if d["success_rate"] is not None:
            score = d["success_rate"]
        else:
            score = (d["solved_rate"] or 0.0) * (d["agreement"] or 0.0)
        return (-score, d["ms_per_image"] or 0.0, d["variant"])

    return sorted(out, key=key)


#: Stages timed per image (``hil_sweep`` columns ``t_<stage>_ns``), as the sweep table names them.
STAGES = (("read", "read"), ("detect", "detect"), ("identify", "identify"), ("attitude", "attitude"),
          ("alt", "second method"))


def _cost(rv: list[dict]) -> dict:
    """Where a variant's time goes, over its images' rows ``rv``: mean blobs found (kept + dropped beyond the
    detector's cap), kept and dropped per image, the most dropped in one image, mean ms per stage and the
    slowest stage with its share of the total."""
    def mean(key, scale=1.0):
        v = [r.get(key) for r in rv if r.get(key) is not None]
        return float(np.mean(v)) * scale if v else None

    kept, dropped = mean("stars_detected"), mean("blobs_dropped")
    stage_ms = {name: mean(f"t_{col}_ns", 1e-6) for col, name in STAGES}
    total = mean("t_total_ns", 1e-6)
    known = {k: v for k, v in stage_ms.items() if v is not None}
    slow = max(known, key=known.get) if known else None
    return {"blobs_found": None if kept is None else kept + (dropped or 0.0), "blobs_kept": kept,
            "blobs_dropped": dropped,
            "max_blobs_dropped": max((r.get("blobs_dropped") or 0 for r in rv), default=None),
            "stage_ms": stage_ms, "slowest_stage": slow,
            "slowest_share": (known[slow] / total) if slow and total else None}


def why_slow(d: dict) -> str:
    """One cell saying where a variant's time goes: its slowest stage, that stage's share of the time, and the
    blobs found per image and how many of them the detector's cap dropped (the work done for nothing)."""
    if d.get("slowest_stage") is None:
        return "-"
    out = f"{d['slowest_stage']} {100 * (d['slowest_share'] or 0):.0f} %"
    if d.get("blobs_found") is not None:
        out += f"; {d['blobs_found']:.0f} blobs/image"
        if d.get("blobs_dropped"):
            dr = d["blobs_dropped"]
            out += f", {dr:.0f}" if dr >= 10 else f", {dr:.1f}"
            out += f" dropped beyond the cap (up to {d['max_blobs_dropped']} in one image)"
    return out


def text(summary: list[dict]) -> str:
    from dualsight.warehouse.query import format_table

    truth = any(d["success_rate"] is not None for d in summary)
    head = (["rank", "settings", "images", "solved"] + (["success", "wrong"] if truth else ["agreement"])
            + ["ms/image", "detect ms", "identify ms", "where the time goes"])
    ms = lambda v: "-" if v is None else (f"{v:.0f}" if v >= 100 else f"{v:.1f}")  # noqa: E731
    rows = [[i + 1, d["label"], d["images"], percent(d["solved_rate"])]
            + ([percent(d["success_rate"]), percent(d["wrong_rate"])] if truth else [percent(d["agreement"])])
            + [ms(d["ms_per_image"]), ms(d["stage_ms"]["detect"]), ms(d["stage_ms"]["identify"]), why_slow(d)]
            for i, d in enumerate(summary)]
    note = ("ranked by success rate (truth given), then time" if truth else
            f"no truth: ranked by solved rate x agreement (boresights within {AGREE_ARCSEC:g} arcsec of the "
            "answer most settings gave), then time")
    note += ("; ms are means per image (one process); blobs found = kept + dropped beyond the detector's "
             "max_blobs_per_frame (found, measured and then thrown away)")
    return format_table(head, rows) + "\n" + note


__all__ = ["NAME", "PRIMARY", "SCHEMAS", "SWEEP_KEYS", "parse_sweeps", "grid", "label", "SweepSpec",
           "spec_from_dict", "build_spec", "n_cases", "make_context", "memory_estimate", "compute_shard",
           "shard_summary", "progress_postfix", "summarize", "text"]
