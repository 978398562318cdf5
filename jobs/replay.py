"""Replay one case of a run: re-render it bit-identically from its row and record it for rerun.

The case's inputs are redrawn from ``default_rng([seed, case_id])`` with the run's spec (from its manifest);
the recomputed row is compared with the stored one (every non-timing column must be equal) before the
recording is written, so a replay that does not reproduce the lake is an error, not a picture.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dualsight.errors import InputError
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect

_TIMING = ("t_",)


def _stored_row(lake: Lake, dataset: str, run_id: str, case_id: int) -> dict:
    if dataset not in lake.datasets():
        raise InputError(f"no {dataset} dataset in {lake.root}", source="--lake")
    con = connect(lake)
    cur = con.execute(f"SELECT * EXCLUDE (run) FROM {dataset} WHERE run = $run AND case_id = $case",
                      {"run": run_id, "case": int(case_id)})
    rows = cur.fetchall()
    if not rows:
        raise InputError(f"run {run_id!r} has no case {case_id} in {lake.root}", source="--case")
    return dict(zip([d[0] for d in cur.description], rows[0]))


def compare_rows(stored: dict, fresh: dict) -> list[str]:
    """Names of the non-timing columns whose values differ (NaN equals NaN)."""
    bad = []
    for k, v in stored.items():
        if k.startswith(_TIMING) or k not in fresh:
            continue
        w = fresh[k]
        if isinstance(v, (list, tuple, np.ndarray)):
            a, b = np.asarray(v, dtype=float), np.asarray(w, dtype=float)
            if a.shape != b.shape or not np.array_equal(a, b, equal_nan=True):
                bad.append(k)
        elif isinstance(v, float) or isinstance(w, float):
            if not ((v is None and w is None) or (v is not None and w is not None
                                                    and (v == w or (math.isnan(v) and math.isnan(w))))):
                bad.append(k)
        elif v != w:
            bad.append(k)
    return bad


def recompute_case(lake: Lake, run_id: str, case_id: int, job, dataset: str, kinds: tuple[str, ...]):
    """Rebuild a run's spec from its manifest, recompute one case with its images, and check that the
    fresh row equals the stored one.  Returns (manifest, spec, context, compute_batch output, fresh row)."""
    manifest = lake.read_manifest(run_id)
    if manifest is None or manifest.get("kind") not in kinds:
        raise InputError(f"no {'/'.join(kinds)} run {run_id!r} in {lake.root}", source="--run")
    if not 0 <= case_id < manifest["n_cases"]:
        raise InputError(f"case must be in [0, {manifest['n_cases'] - 1}], got {case_id}", source="--case")
    stored = _stored_row(lake, dataset, run_id, case_id)
    spec = job.spec_from_dict(manifest["spec"], source=f"manifest of run {run_id}")
    ctx = job.make_context(spec)
    out = job.compute_batch(spec, ctx, np.array([case_id], dtype=np.int64), keep_images=True)
    fresh = out["tables"][dataset].to_pylist()[0]
    diff = compare_rows(stored, fresh)
    if diff:
        raise InputError(f"replay of case {case_id} does not reproduce the lake (columns differ: {diff}); "
                         f"was the run made with another dualsight version? ({manifest.get('versions')})",
                         source=f"run {run_id}")
    return manifest, spec, ctx, out, fresh


def replay_star_case(lake: Lake, run_id: str, case_id: int, output: Path | None = None) -> Path:
    from dualsight.jobs import star
    from dualsight.viz.recording import log_star_case, open_recording

    manifest, spec, ctx, out, fresh = recompute_case(lake, run_id, case_id, star, "star_cases", ("star",))
    det = out["rendered"].detections
    obs, ident, sol, field_ = out["obs"], out["ident"], out["sol"], out["field"]
    S = obs.valid.shape[1]
    K = len(det.x)
    ids = np.full(K, -1)
    acc = np.zeros(K, dtype=bool)
    ids[:min(K, S)] = ident.ids[0, :min(K, S)]
    acc[:min(K, S)] = ident.accepted[0, :min(K, S)]
    true_rows = out["truth"].true_row
    hip = ctx.catalog.hip
    labels = [f"HIP {hip[i]}" + ("" if a else "?") if i >= 0 else "-" for i, a in zip(ids, acc)]
    ok = acc & (ids == true_rows) & (ids >= 0)
    if np.isfinite(sol.A_est[0]).all():
        v = ctx.catalog.unit @ sol.A_est[0].T
        px, front = spec.camera.project(v)
        inside = front & spec.camera.in_image(np.nan_to_num(px, nan=-1.0))
        pred_xy, pred_labels = px[inside], [f"HIP {h}" for h in hip[inside]]
    else:
        pred_xy, pred_labels = np.zeros((0, 2)), []
    truth_xy = np.stack([field_.x[0][field_.inside[0]], field_.y[0][field_.inside[0]]], axis=-1)
    arcsec = 180 * 3600 / math.pi
    info = "\n".join([
        f"# star case {case_id} of run `{run_id}`", "",
        f"- status: **{fresh['status']}** (robust method: {fresh['status_robust']})",
        f"- stars generated / observed / identified: {fresh['n_generated']} / {fresh['n_observed']} / "
        f"{fresh['n_identified']}", f"- match threshold T: {fresh['T']}",
        f"- axis errors (arcsec): x {fresh['err_x_rad'] * arcsec:.2f}, y {fresh['err_y_rad'] * arcsec:.2f}, "
        f"z {fresh['err_z_rad'] * arcsec:.2f}" if fresh["err_x_rad"] is not None else "- no attitude",
        f"- angles (deg): {np.degrees([fresh['theta1_rad'], fresh['theta2_rad'], fresh['theta3_rad']]).round(4)}",
        "", "Blue: true stars; yellow: catalog predicted by the estimated attitude; "
        "green/red: detections identified right / not.",
        "", "Replay reproduced the lake's row bit for bit."])
    output = Path(output or f"{run_id}-case{case_id}.rrd")
    rec = open_recording(output)
    log_star_case(rec, image=out["rendered"].images[0], det_xy=np.stack([det.x, det.y], -1), det_labels=labels,
                  det_ok=ok, pred_xy=pred_xy, pred_labels=pred_labels, truth_xy=truth_xy, info_md=info)
    rec.flush()
    return output
