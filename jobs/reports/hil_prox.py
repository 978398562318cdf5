"""Reports of a ``hil_prox`` run, read back from the lake with the warehouse SQL after the engine ran it.

* :func:`fetch`: the image rows (``hil_prox_case_rows.sql``), the image x threshold rows
  (``hil_prox_rows.sql``) and the sweep (``hil_prox_sweep.sql``, the reference's Figure 8 numbers);
* :func:`json_document`: the CLI's ``--json`` object;
* :func:`text_report`: the per-image table at one threshold (``hil_prox_images.sql``) and the sweep table;
* the threshold choices over a run's rows (:func:`best_threshold`, :func:`oracle_threshold`,
  :func:`stable_threshold`, :func:`cross_validated_error`): nav/threshold_choice.py over the rows' arrays.

Figure 8 from the same rows: viz/threshold_sweep.py's ``hil_prox_figure``.
"""

from __future__ import annotations

import numpy as np

from dualsight.warehouse.cells import table_cells
from dualsight.nav import threshold_choice as tc

__all__ = ["fetch", "oracle_threshold", "stable_threshold", "cross_validated_error", "best_threshold",
           "json_document", "text_report"]


def _dicts(cols, rows) -> list[dict]:
    return [dict(zip(cols, r)) for r in rows]


def fetch(con, run_id: str) -> dict:
    """{"cases": [...], "rows": [...], "sweep": [...]} of one run (dicts, SQL column names)."""
    from dualsight.warehouse.query import run_report

    return {"cases": _dicts(*run_report(con, "hil_prox_case_rows", run=run_id)),
            "rows": _dicts(*run_report(con, "hil_prox_rows", run=run_id)),
            "sweep": _dicts(*run_report(con, "hil_prox_sweep", run=run_id))}


def oracle_threshold(sweep: list[dict]) -> dict | None:
    """The sweep row with the smallest average relative error (``nav.threshold_choice.oracle_threshold``):
    chosen WITH the truth, so its error is an optimistic bound (None without truth)."""
    t = tc.oracle_threshold([s["threshold"] for s in sweep],
                            [np.nan if s.get("avg_rel_error_pct") is None else s["avg_rel_error_pct"] for s in sweep])
    return _row_at(sweep, t)


def _row_at(sweep: list[dict], threshold: float | None) -> dict | None:
    return next((s for s in sweep if s["threshold"] == threshold), None) if threshold is not None else None


def _range_grid(rows: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(thresholds (T,), range estimates (N, T) with NaN where no blob, truths (N,) NaN where unknown);
    rows of images that could not be read (no threshold) are left out."""
    rows = [r for r in rows if r.get("threshold") is not None]
    th = np.array(sorted({r["threshold"] for r in rows}), dtype=float)
    cases = sorted({r["case_id"] for r in rows})
    ci = {c: i for i, c in enumerate(cases)}
    est = np.full((len(cases), len(th)), np.nan)
    truth = np.full(len(cases), np.nan)
    for r in rows:   # a few rows per image and threshold: bookkeeping, not a pixel loop
        i, j = ci[r["case_id"]], int(np.searchsorted(th, r["threshold"]))
        if r.get("found") and r.get("range_m") is not None:
            est[i, j] = r["range_m"]
        if r.get("truth_range_m") is not None:
            truth[i] = r["truth_range_m"]
    return th, est, truth


def stable_threshold(rows: list[dict]) -> float | None:
    """The threshold chosen without the truth (``nav.threshold_choice.stable_threshold``) over the ``hil_prox``
    rows of one run (image x threshold, as ``hil_prox_rows.sql`` gives them).  None with fewer than 3
    thresholds."""
    th, est, _ = _range_grid(rows)
    return tc.stable_threshold(th, est)


def cross_validated_error(rows: list[dict]) -> float | None:
    """Leave-one-image-out error (%) of choosing the threshold with the truth
    (``nav.threshold_choice.cross_validated_error``) over the ``hil_prox`` rows of one run; None with fewer
    than 2 images with a truth."""
    _, est, truth = _range_grid(rows)
    return tc.cross_validated_error(est, truth)


def best_threshold(sweep: list[dict], rows: list[dict] | None = None) -> dict | None:
    """The threshold a user without truth would use (:func:`stable_threshold` over ``rows``), as its sweep
    row; without ``rows`` or with fewer than 3 thresholds, None."""
    return _row_at(sweep, stable_threshold(rows) if rows else None)


def _r(v, nd=6):
    return None if v is None else round(float(v), nd)


def _image_json(case: dict, rows: list[dict]) -> dict:
    out = {"image": case["image"], "path": case["path"], "error": case["error"],
           "truth_range_m": case["truth_range_m"], "truth_source": case["truth_source"], "results": []}
    if case["error"]:
        return out
    for row in rows:
        out["results"].append({
            "threshold": row["threshold"], "found": row["found"], "n_blobs": row["n_blobs"],
            "n_foreground": row["n_foreground"], "n_pixels": row["n_pixels"], "axis_ratio": _r(row["axis_ratio"], 4),
            "cob_px": None if row["cob_x_px"] is None else [_r(row["cob_x_px"], 3), _r(row["cob_y_px"], 3)],
            "unit": None if row["unit_x"] is None else [_r(row[f"unit_{a}"], 6) for a in "xyz"],
            "range_min_m": _r(row["range_min_m"]), "range_m": _r(row["range_m"]), "range_max_m": _r(row["range_max_m"]),
            "error_m": _r(row["range_error_m"]), "abs_error_m": _r(row["abs_error_m"]),
            "rel_error_pct": None if row["rel_error"] is None else round(100 * row["rel_error"], 3),
            "within_min_max": row["within_min_max"], "touches_edge": row["touches_edge"]})
    return out


def _by_case(rows: list[dict]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = {}
    for r in rows:
        out.setdefault(r["case_id"], []).append(r)
    return out


def json_document(data: dict, *, run_id: str | None, camera: dict, target: dict, settings: dict) -> dict:
    """The ``--json`` object: run, camera, target, settings, images (with their per-threshold results),
    sweep and best (see jobs/cli/hil_prox.py)."""
    clean = [{k: (_r(v, 6) if isinstance(v, float) else v) for k, v in s.items()} for s in data["sweep"]]
    rows = _by_case(data["rows"])
    return {"run": run_id, "camera": camera, "target": target, "settings": settings,
            "images": [_image_json(c, rows.get(c["case_id"], [])) for c in data["cases"]], "sweep": clean,
            "best": best_threshold(clean, data["rows"]), "oracle": oracle_threshold(clean),
            "cross_validated_rel_error_pct": _r(cross_validated_error(data["rows"]), 4)}


def _fmt_thresholds(th) -> str:
    return f"{th[0]:g}" if len(th) == 1 else f"{th[0]:g}..{th[-1]:g} ({len(th)})"


def text_report(con, run_id: str, data: dict, settings) -> str:
    """Per-image table at one threshold (the only one, or the sweep's best) and the sweep table."""
    from dualsight.warehouse.query import format_table, run_report

    s, sweep = settings, data["sweep"]
    best = best_threshold(sweep, data["rows"])
    oracle, cv = oracle_threshold(sweep), cross_validated_error(data["rows"])
    th = s.thresholds
    show_t = th[0] if len(th) == 1 else (best["threshold"] if best else th[len(th) // 2])
    out = [f"threshold{'s' if len(th) > 1 else ''} {_fmt_thresholds(th)}{' on the inverted image' if s.invert else ''}; "
           f"open {s.open_px}, close {s.close_px}, border {s.border_px} px{', undistorted' if s.undistort else ''}; "
           f"{s.estimator} estimator, {s.blob} blob", ""]
    cols, rows = run_report(con, "hil_prox_images", run=run_id)
    table = []
    for r in _dicts(cols, rows):
        if r["error"]:
            table.append([r["image"], "ERROR: " + r["error"]] + [None] * 9)
        elif r["threshold"] == show_t:
            table.append([r["image"], "found" if r["found"] else "no blob", r["n_pixels"], r["axis_ratio"],
                          r["truth_range_m"], r["range_min_m"], r["range_m"], r["range_max_m"], r["error_pct"],
                          r["within_min_max"], r["touches_edge"]])
    out.append(f"per image at threshold {show_t:g}" + (" (the sweep's best)" if len(th) > 1 and best else ""))
    out.append(format_table(["image", "status", "N_blob px", "axis ratio", "true m", "min m", "est m", "max m",
                             "error %", "in [min,max]", "edge"],
                            table_cells(["image", "status", "n_pixels", "axis_ratio", "true_m", "min_m", "est_m",
                                         "max_m", "error_pct", "in", "edge"], table)))
    if len(th) > 1 or any(x.get("with_truth") for x in sweep):
        out += ["", "sweep (reference Figure 8): per threshold, over the images"]
        keys = ["threshold", "found", "avg_range_m", "avg_range_min_m", "avg_range_max_m", "avg_truth_m",
                "avg_abs_error_m", "avg_rel_error_pct", "within_min_max_pct"]
        out.append(format_table(["T", "found", "avg est m", "avg min m", "avg max m", "avg true m", "avg |err| m",
                                 "avg rel err %", "within %"], table_cells(keys, [[x.get(k) for k in keys] for x in sweep])))
        if best:
            line = f"chosen threshold {best['threshold']:g} (without the truth: where the range changes least)"
            if best.get("avg_rel_error_pct") is not None:
                w = best.get("within_min_max_pct")
                line += (f": average residual {best['avg_abs_error_m']:.4g} m ({best['avg_rel_error_pct']:.2f} %), "
                         + (f"true range inside [min, max] for {w:.0f} % of the images" if w is not None else
                            "[min, max] is a point (the target's area does not depend on its orientation)"))
            out.append(line)
        if oracle:
            out.append(f"oracle threshold {oracle['threshold']:g} (chosen WITH the truth, optimistic): "
                       f"{oracle['avg_rel_error_pct']:.2f} %; leave-one-image-out error of that choice: "
                       + ("-" if cv is None else f"{cv:.2f} %"))
    return "\n".join(out)
