"""Replay one case of a run: re-render it bit-identically from its row and record it for rerun.

The case's inputs are redrawn from ``default_rng([seed, case_id])`` with the run's spec (from its manifest);
the recomputed row is compared with the stored one (every non-timing column must be equal) before the
recording is written, so a replay that does not reproduce the lake is an error, not a picture.
"""

from __future__ import annotations

import math
import os
import stat
import tempfile
from pathlib import Path

import numpy as np

from dualsight.errors import InputError, output_path
from dualsight.jobs.engine.runner import job_module
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.scene.imageio import read_image
from dualsight.scene.units import ARCSEC
from dualsight.viz.recording import log_image_case, log_star_case, open_recording
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, run_sql

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


def stored_rows(lake: Lake, dataset: str, run_id: str, case_id: int, order: str = "case_id") -> list[dict]:
    """Every stored row of ``dataset`` of case ``case_id`` of run ``run_id`` (``run`` left out), ``ORDER BY
    order`` (a column name of the dataset); InputError naming the option when the dataset or the case is absent."""
    if dataset not in lake.datasets():
        raise InputError(f"no {dataset} dataset in {lake.root}", source="--lake")
    con = connect(lake)
    cur = con.execute(f"SELECT * EXCLUDE (run) FROM {dataset} WHERE run = $run AND case_id = $case ORDER BY {order}",
                      {"run": run_id, "case": int(case_id)})
    cols = [d[0] for d in cur.description]
    rows = [dict(zip(cols, r)) for r in cur.fetchall()]
    if not rows:
        raise InputError(f"run {run_id!r} has no case {case_id} in {lake.root}", source="--case")
    return rows


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


def refuse_mismatch(stored: dict, fresh: dict, case_id: int, run_id: str, manifest: dict, what: str = ""):
    """InputError naming the first differing column and both values, when the recomputed row differs;
    ``what`` prefixes the column (e.g. ``"frame 7: "`` for a row of a sequence)."""
    diff = compare_rows(stored, fresh)
    if diff:
        c = diff[0]
        raise InputError(f"replay of case {case_id} does not reproduce the lake: {what}column {c} is {stored[c]!r} in "
                         f"the lake, {fresh[c]!r} recomputed ({len(diff)} column(s) differ: {', '.join(diff[:6])}); "
                         f"run made with {manifest.get('code_version')}", source=f"run {run_id}")


def sequence_rows(lake: Lake, run_id: str, case_id: int, kind: str, case_dataset: str,
                  frame_dataset: str) -> tuple[dict, dict, list[dict]]:
    """(manifest, the case's row of ``case_dataset``, its rows of ``frame_dataset`` by frame) of case ``case_id``
    of a sequence kind's run (``star_track``, ``rendezvous``); InputError when the run is not of ``kind`` or the
    case is out of range."""
    manifest = lake.read_manifest(run_id)
    if manifest is None or manifest.get("kind") != kind:
        raise InputError(f"no {kind} run {run_id!r} in {lake.root}", source="--run")
    if not 0 <= case_id < manifest["n_cases"]:
        raise InputError(f"case must be in [0, {manifest['n_cases'] - 1}], got {case_id}", source="--case")
    return (manifest, stored_rows(lake, case_dataset, run_id, case_id)[0],
            stored_rows(lake, frame_dataset, run_id, case_id, order="frame"))


def refuse_frame_mismatch(frames: list[dict], fresh: list[dict], case_id: int, run_id: str, manifest: dict):
    """InputError when the recomputed frame rows of a sequence differ from the stored ones: their number, or the
    first differing column of the first differing frame (:func:`refuse_mismatch`)."""
    if len(fresh) != len(frames):
        raise InputError(f"replay of case {case_id} does not reproduce the lake: {len(frames)} frame rows in the lake, "
                         f"{len(fresh)} recomputed", source=f"run {run_id}")
    for s, f in zip(frames, fresh):
        refuse_mismatch(s, f, case_id, run_id, manifest, what=f"frame {s['frame']}: ")


def recording_path(path) -> Path:
    """``path`` as the file a recording may be written to, checked before any case is recomputed: its folder
    exists and is a folder that takes a new file (a probe file is created and removed), and the path is not a
    folder, device or pipe.  Otherwise one InputError naming the path (the recorder would fail, or block on a
    pipe, only after the work)."""
    path = Path(path)
    if path.parent.exists() and not path.parent.is_dir():
        raise InputError("is a file, not a folder; give a .rrd file in an existing writable folder",
                         source=str(path.parent))
    output_path(path)                                     # the folder exists (none is created)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as e:
        raise InputError(f"cannot be written ({e.strerror or e}); give a .rrd file in a writable folder",
                         source=str(path)) from None
    if mode is not None and not stat.S_ISREG(mode):
        raise InputError("is not a regular file (a folder, device or pipe); give a .rrd file to write the "
                         "recording to", source=str(path))
    try:
        fd, probe = tempfile.mkstemp(dir=path.parent, prefix=".dualsight-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise InputError(f"cannot write a recording in this folder ({e.strerror or e}); give a .rrd file in a "
                         "writable folder", source=str(path)) from None
    if mode is not None and not os.access(path, os.W_OK):
        raise InputError("cannot be overwritten (permission denied); give a .rrd file in a writable folder",
                         source=str(path))
    return path


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
    refuse_mismatch(stored, fresh, case_id, run_id, manifest)
    return manifest, spec, ctx, out, fresh


def replay_star_case(lake: Lake, run_id: str, case_id: int, output: Path | None = None, rec=None) -> Path:
    """Re-render a star case, verify it against its row (image digest and every metric), and log it into
    ``rec`` (an open recording) or a new recording at ``output``."""
    from dualsight.jobs.kinds import star                     # Taichi

    if rec is None:
        output = recording_path(output or f"{run_id}-case{case_id}.rrd")
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
    hip, vmag = ctx.catalog.hip, ctx.catalog.vmag
    labels = [f"HIP {hip[i]} V{vmag[i]:.2f}" + ("" if a else "?") if i >= 0 else "-" for i, a in zip(ids, acc)]
    ok = acc & (ids == true_rows) & (ids >= 0)
    if np.isfinite(sol.A_est[0]).all():
        v = ctx.catalog.unit @ sol.A_est[0].T
        px, front = spec.camera.project(v)
        inside = front & spec.camera.in_image(np.nan_to_num(px, nan=-1.0))
        pred_xy, pred_labels = px[inside], [f"HIP {h} V{m:.2f}" for h, m in zip(hip[inside], vmag[inside])]
    else:
        pred_xy, pred_labels = np.zeros((0, 2)), []
    truth_xy = np.stack([field_.x[0][field_.inside[0]], field_.y[0][field_.inside[0]]], axis=-1)
    arcsec = 1.0 / ARCSEC
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
        f"- image digest: {fresh['image_digest']} (re-rendered frame = stored)",
        "", "Replay reproduced the lake's row bit for bit."])
    output = Path(output or f"{run_id}-case{case_id}.rrd")
    own = rec is None
    rec = open_recording(output) if own else rec
    errs = {k: (fresh[k] * arcsec if fresh[k] is not None else None)
            for k in ("err_x_rad", "err_y_rad", "err_z_rad", "err_total_rad")}
    log_star_case(rec, image=out["rendered"].images[0], det_xy=np.stack([det.x, det.y], -1), det_labels=labels,
                  det_ok=ok, pred_xy=pred_xy, pred_labels=pred_labels, truth_xy=truth_xy, info_md=info,
                  frame=case_id, attitudes={"true": out["draw"]["A_true"][0], "estimated": sol.A_est[0]},
                  scalars={k.replace("_rad", "_arcsec"): v for k, v in errs.items()}
                  | {"n_identified": fresh["n_identified"]})
    if own:
        rec.flush()
    return output


# ============================================================================================ any kind, by SQL
MAX_REPLAY = 1000


def select_cases(lake: Lake, run_id: str, *, case: int | None = None, where: str | None = None,
                 limit: int = 20) -> tuple[dict, list[int]]:
    """(manifest, case ids) chosen by ``--case`` or by an SQL predicate over the run's primary dataset.

    The predicate runs read-only (:func:`dualsight.warehouse.query.run_sql`) in
    ``SELECT case_id FROM <primary> WHERE run = '<run>' AND (<predicate>) ORDER BY case_id LIMIT <limit>``.
    """
    manifest = lake.read_manifest(run_id)
    if manifest is None:
        raise InputError(f"no run {run_id!r} in {lake.root}", source="--run")
    if (case is None) == (where is None):
        raise InputError("give exactly one of --case N or --where \"SQL predicate\"", source="replay")
    if case is not None:
        if not 0 <= case < manifest["n_cases"]:
            raise InputError(f"must be in [0, {manifest['n_cases'] - 1}], got {case}", source="--case")
        return manifest, [int(case)]
    if not 1 <= limit <= MAX_REPLAY:
        raise InputError(f"must be in [1, {MAX_REPLAY}], got {limit}", source="--limit")
    sql = (f"SELECT case_id FROM {manifest['primary']} WHERE run = '{run_id}' AND ({where}) "
           f"ORDER BY case_id LIMIT {int(limit)}")
    _, rows = run_sql(lake, sql)
    return manifest, [int(r[0]) for r in rows]


def verify_case(lake: Lake, manifest: dict, case_id: int):
    """Recompute one case of any job kind with ``compute_shard`` and check it against its stored row.

    Returns (spec, context, stored primary row, tables of the recomputed case).
    """
    mod = job_module(manifest["kind"])
    run_id = manifest["run_id"]
    stored = _stored_row(lake, manifest["primary"], run_id, case_id)
    spec = mod.spec_from_dict(manifest["spec"], source=f"manifest of run {run_id}")
    ctx = mod.make_context(spec)
    tables = mod.compute_shard(spec, np.array([case_id], dtype=np.int64), ctx)
    fresh = tables[manifest["primary"]].to_pylist()[0]
    refuse_mismatch(stored, fresh, case_id, run_id, manifest)
    return spec, ctx, stored, tables


def replay_generic_case(lake: Lake, manifest: dict, case_id: int, output: Path, rec=None) -> Path:
    """Verify a case of any kind and record its image (re-read for real-image kinds; its digest must equal
    the row's ``image_digest``) and its row."""
    spec, ctx, stored, tables = verify_case(lake, manifest, case_id)
    image, points, labels = None, np.zeros((0, 2)), []
    images = getattr(spec, "images", None)
    if images:
        try:
            img = read_image(Path(images[case_id].path), as_gray=("image_digest" not in stored
                                                                  or manifest["kind"] == "hil_star"))
        except InputError:
            img = None
        if img is not None:
            image = img.adc_counts() if manifest["kind"] == "hil_star" else img.pixels
            d = int(to_int64(frame_digest(np.asarray(image)[None]))[0])
            if "image_digest" in stored and stored["image_digest"] is not None and d != stored["image_digest"]:
                raise InputError(f"replay of case {case_id}: column image_digest is {stored['image_digest']} in "
                                 f"the lake, {d} for the image read now", source=images[case_id].path)
    detail = [d for d in tables if d != manifest["primary"]]
    if detail:
        t = tables[detail[0]].to_pylist()
        pts = [(r["x_px"], r["y_px"]) for r in t if r.get("x_px") is not None and r.get("y_px") is not None]
        points = np.asarray(pts, dtype=float).reshape(-1, 2)
        labels = [f"HIP {r['hip']} V{r['vmag']:.1f}" if r.get("hip") is not None and r.get("vmag") is not None
                  else "" for r in t][: len(points)]
    lines = [f"# {manifest['kind']} case {case_id} of run `{manifest['run_id']}`", ""]
    lines += [f"- {k}: {v}" for k, v in stored.items() if not str(k).startswith(_TIMING)]
    lines += ["", "Replay reproduced the lake's row exactly."]
    own = rec is None
    rec = open_recording(output) if own else rec
    log_image_case(rec, image=image, points=points, labels=labels, info_md="\n".join(lines), frame=case_id)
    if own:
        rec.flush()
    return output
