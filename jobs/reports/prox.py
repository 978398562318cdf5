"""The report of a proximity run (``dualsight prox report``, and the proximity sections of ``dualsight report``):
Table 3 per true range for a sweep (``warehouse/sql/prox_table3.sql``: both estimators beside the reference's
numbers), the per-axis errors and frames of a trajectory (``prox_trajectory.sql``, ``prox_frames.sql``) and the
time per stage (``prox_stage_times.sql``), read back from the lake by SQL; and what ``dualsight prox resolvable``
prints (:func:`resolvable_report`, nav/range.py for a camera file).
"""

from __future__ import annotations

from pathlib import Path

from dualsight.errors import InputError
from dualsight.nav.range import resolvable_range
from dualsight.scene.camera import Camera
from dualsight.warehouse.query import connect, run_report

__all__ = ["build_report", "report_text", "resolvable_report"]


def build_report(lake, run_id: str, estimator: str | None = None) -> dict:
    """A prox run's report from the lake: run, job ("sweep" or "trajectory"), mode, estimator (the top-level
    numbers' one: ``estimator``, else subpixel for accurate-mode runs and paper otherwise), then for a sweep
    ``table`` (the SQL columns and rows of ``prox_table3``) and ``ranges`` (per true range: both estimators' and
    the reference's numbers), for a trajectory ``summary`` and ``frames``; and ``stage_ms``."""
    m = lake.read_manifest(run_id)
    if m is None or not str(m.get("kind", "")).startswith("prox"):
        raise InputError(f"no prox run {run_id!r} in {lake.root}", source="--run")
    if "prox_cases" not in lake.datasets():
        raise InputError(f"no prox_cases dataset in {lake.root}", source="--lake")
    con = connect(lake)
    job = m["spec"]["job"]
    est = estimator or ("subpixel" if m["spec"]["mode"] == "accurate" else "paper")
    rep = {"run": run_id, "job": job, "mode": m["spec"]["mode"], "estimator": est}
    if job == "sweep":
        cols, rows = run_report(con, "prox_table3", run=run_id)
        table = [dict(zip(cols, r)) for r in rows]
        rep["table"] = (cols, rows)
        rep["ranges"] = [{"true_range_m": r["true_range_m"], "cases": r["cases"],
                          "avg_est_range_m": r[f"{est}_avg_est_m"], "avg_abs_error_m": r[f"{est}_avg_abs_err_m"],
                          "avg_rel_error_pct": r[f"{est}_avg_rel_err_pct"],
                          "within_min_max_pct": r[f"{est}_within_pct"],
                          "paper": {k[6:]: v for k, v in r.items() if k.startswith("paper_")},
                          "subpixel": {k[9:]: v for k, v in r.items() if k.startswith("subpixel_")},
                          "reference": {k[4:]: v for k, v in r.items() if k.startswith("ref_")}}
                         for r in table]
    else:
        cols, rows = run_report(con, "prox_trajectory", run=run_id)
        rep["summary"] = dict(zip(cols, rows[0]))
        fcols, frows = run_report(con, "prox_frames", run=run_id)
        rep["frames"] = [dict(zip(fcols, r)) for r in frows]
    tc, tr = run_report(con, "prox_stage_times", run=run_id)
    rep["stage_ms"] = dict(zip(tc, tr[0]))
    return rep


def _fmt(v, nd=3):
    return "-" if v is None or (isinstance(v, float) and v != v) else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def report_text(rep: dict) -> str:
    """The text report: Table 3 per true range (sweep) or the per-axis errors (trajectory), and the stage times."""
    lines = [f"proximity {rep['job']} run {rep['run']} (renderer: {rep['mode']})", ""]
    if rep["job"] == "sweep":
        lines.append("Table 3 per true range: reference | paper estimator (Eq. 1) | subpixel estimator")
        hdr = (f"{'range m':>8} {'n':>5} | {'ref est':>7} {'rel%':>6} {'in%':>6} | {'est':>7} {'abs m':>7} "
               f"{'rel%':>6} {'in%':>6} | {'est':>7} {'abs m':>7} {'rel%':>6} {'in%':>6}")
        lines += [hdr, "-" * len(hdr)]
        for r in rep["ranges"]:
            p, s, f = r["paper"], r["subpixel"], r["reference"]
            lines.append(f"{r['true_range_m']:8.3f} {r['cases']:5d} | {_fmt(f.get('avg_est_m'), 3):>7} "
                         f"{_fmt(f.get('avg_rel_err_pct'), 2):>6} {_fmt(f.get('within_pct'), 1):>6} | "
                         f"{_fmt(p['avg_est_m']):>7} {_fmt(p['avg_abs_err_m']):>7} {_fmt(p['avg_rel_err_pct'], 2):>6} "
                         f"{_fmt(p['within_pct'], 1):>6} | {_fmt(s['avg_est_m']):>7} {_fmt(s['avg_abs_err_m']):>7} "
                         f"{_fmt(s['avg_rel_err_pct'], 2):>6} {_fmt(s['within_pct'], 1):>6}")
    else:
        s = rep["summary"]
        lines.append(f"frames {s['frames']} (found {s['frames_found']}), true range {_fmt(s['min_range_m'], 2)}-"
                     f"{_fmt(s['max_range_m'], 2)} m, direction error {_fmt(s['mean_direction_err_arcsec'], 1)} arcsec")
        lines.append(f"{'estimator':>10} {'|dx| m':>8} {'|dy| m':>8} {'|dz| m':>8} {'range rel %':>12}")
        for e in ("paper", "subpixel"):
            lines.append(f"{e:>10} {_fmt(s[f'{e}_mean_abs_err_x_m'], 4):>8} {_fmt(s[f'{e}_mean_abs_err_y_m'], 4):>8} "
                         f"{_fmt(s[f'{e}_mean_abs_err_z_m'], 4):>8} {_fmt(s[f'{e}_mean_rel_range_err_pct'], 2):>12}")
    st = rep["stage_ms"]
    lines += ["", f"time per case: render {_fmt(st['render_ms'])} ms, blobber {_fmt(st['blob_paper_ms'])} ms (paper) + "
              f"{_fmt(st['blob_subpixel_ms'])} ms (subpixel), total {_fmt(st['total_ms'])} ms"]
    return "\n".join(lines)


def resolvable_report(camera_file: Path | None, size_m: float) -> tuple[dict, str]:
    """The nearest and farthest resolvable range of an object of size ``size_m`` (m) for the camera of
    ``camera_file`` (default: the reference's Table 1 camera), as (JSON object, text)."""
    cam = Camera.from_toml(camera_file) if camera_file else Camera.pinhole(1024, 768, 4.65e-6, 6e-3)
    r = resolvable_range(cam, size_m)
    out = {"size_m": size_m, "nearest_fits_frame_m": r.near_fit_m, "nearest_fills_frame_m": r.near_fill_m,
           "farthest_2x2_px_m": r.far_m, "reference_convention_nearest_m": r.reference_near_m}
    text = (f"object {size_m} m, camera {cam.width}x{cam.height} px, f = {cam.fx:.1f} px:\n"
            f"  nearest (object fits the frame's short side): {r.near_fit_m:.4f} m\n"
            f"  object fills the whole frame (long side):      {r.near_fill_m:.4f} m\n"
            f"  farthest (object covers 2 x 2 pixels):         {r.far_m:.2f} m\n"
            f"  the reference's 8.4 cm convention (h/2 over the full sensor height): {r.reference_near_m:.4f} m")
    return out, text
