"""Reports of a ``hil_star`` run, read back from the lake with the warehouse SQL after the engine ran it.

* :func:`fetch`: every image row and identified-star row (``warehouse/sql/hil_star_rows.sql``,
  ``hil_star_star_rows.sql``);
* :func:`to_json`: one image as the CLI's JSON object (angles in deg / arcsec; keys in jobs/cli/hil_star.py);
* :func:`text_report`: per image a summary line and the reference's Table 6 (``hil_star_table6.sql``), then
  one line per image (``hil_star_images.sql``);
* :func:`write_overlays`: the reference's Figure 11 per image, drawn by re-reading the image and re-running
  the (deterministic) background subtraction and detection; identities, predictions and the attitude
  come from the lake rows.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path

import numpy as np

from dualsight.catalogs.auto_limit import describe_mag_limit
from dualsight.errors import ImageError, output_path
from dualsight.warehouse.cells import table_cells
from dualsight.scene.attitude import unit_to_radec
from dualsight.scene.pointing import roll_deg
from dualsight.scene.starfield_geometry import catalog_in_image
from dualsight.scene.units import ARCSEC

__all__ = ["fetch", "fetch_objects", "objects_json", "target_json", "to_json", "track_json", "summary_line", "table6_text", "text_report", "write_overlays", "licence_credit"]


def fetch(con, run_id: str) -> tuple[list[dict], dict[int, list[dict]]]:
    """(image rows in case order, {case_id: identified-star rows in detection order}) of one run."""
    from dualsight.warehouse.query import run_report

    cols, rows = run_report(con, "hil_star_rows", run=run_id)
    images = [dict(zip(cols, r)) for r in rows]
    cols, rows = run_report(con, "hil_star_star_rows", run=run_id)
    stars: dict[int, list[dict]] = {}
    for r in rows:
        d = dict(zip(cols, r))
        stars.setdefault(d["case_id"], []).append(d)
    return images, stars


def fetch_objects(con, run_id: str) -> dict[int, list[dict]]:
    """{case_id: ``hil_star_objects`` rows, brightest first} of one run (``warehouse/sql/hil_star_object_rows.sql``);
    empty for a run made before the dataset existed."""
    from dualsight.warehouse.query import run_report

    try:
        cols, rows = run_report(con, "hil_star_object_rows", run=run_id)
    except Exception as e:                      # noqa: BLE001 -- no such view: a run without the dataset
        if "hil_star_objects" not in str(e):
            raise
        return {}
    out: dict[int, list[dict]] = {}
    for r in rows:
        d = dict(zip(cols, r))
        out.setdefault(d["case_id"], []).append(d)
    for v in out.values():
        v.sort(key=lambda d: -(d["flux"] or 0.0))
    return out


def objects_json(objects: list[dict]) -> list[dict]:
    """The ``unknown_objects`` list of one image's JSON: ICRS RA/Dec (deg), its 1-sigma (arcsec), pixel position,
    pixels, magnitude, the nearest catalog star (HIP, V, distance px) and whether it is the target."""
    return [{"ra_deg": _deg(o["ra_rad"]), "dec_deg": _deg(o["dec_rad"]), "sigma_arcsec": _as(o["sigma_rad"]),
             "x_px": round(o["x_px"], 3), "y_px": round(o["y_px"], 3), "pixels": o["npix"],
             "mag": None if o["mag"] is None else round(o["mag"], 2), "flux_adu": round(o["flux"], 1),
             "saturated": o["saturated"], "nearest_hip": o["nearest_hip"],
             "nearest_vmag": None if o["nearest_vmag"] is None else round(o["nearest_vmag"], 2),
             "nearest_sep_px": None if o["nearest_sep_px"] is None else round(o["nearest_sep_px"], 2),
             "is_target": o["is_target"]} for o in objects]


def target_json(r: dict) -> dict:
    """The ``--target`` keys of one image row: RA/Dec (deg), pixels, 1-sigma (arcsec), magnitude, and for a resolved
    target its range with min and max (m); null with ``target_reason`` when no target was found."""
    def m(k):
        v = r.get(k)
        return None if v is None else round(float(v), 3)

    return {"target": r.get("target"), "target_kind": r.get("target_kind"), "target_reason": r.get("target_reason"),
            "target_ra_deg": _deg(r.get("target_ra_rad")), "target_dec_deg": _deg(r.get("target_dec_rad")),
            "target_sigma_arcsec": _as(r.get("target_sigma_rad"), nd=3), "target_pixels": r.get("target_pixels"),
            "target_x_px": m("target_x_px"), "target_y_px": m("target_y_px"),
            "target_mag": None if r.get("target_mag") is None else round(r["target_mag"], 2),
            "target_range_m": m("target_range_m"), "target_range_min_m": m("target_range_min_m"),
            "target_range_max_m": m("target_range_max_m")}


def _as(v, scale=1.0 / ARCSEC, nd=2):
    return None if v is None else round(float(v) * scale, nd)


def _deg(v, nd=6):
    return None if v is None else round(math.degrees(float(v)), nd)


def to_json(r: dict, stars: list[dict], overlay: str | None = None, objects: list[dict] | None = None) -> dict:
    """One image (a ``hil_star`` row, its ``hil_star_stars`` rows and, when given, its ``hil_star_objects`` rows)
    as the CLI's JSON object."""
    out = {
        "image": r["image"], "path": r["path"], "error": r["error"], "status": r["status"],
        "identified": bool(r["identified"]), "method": r["method"],
        "nonfinite_pixels": r.get("nonfinite_pixels"), "stars_detected": r.get("stars_detected"), "stars_used": r.get("stars_used"),
        "stars_identified": r.get("stars_identified"), "T": r.get("T"),
        "ra_deg": _deg(r.get("ra_rad")), "dec_deg": _deg(r.get("dec_rad")),
        "roll_deg": None if r.get("roll_deg") is None else round(r["roll_deg"], 4),
        "residual_median_arcsec": _as(r.get("residual_median_rad")),
        "residual_max_arcsec": _as(r.get("residual_max_rad")),
        "truth_source": r["truth_source"],
        "ra_true_deg": _deg(r.get("ra_true_rad")), "dec_true_deg": _deg(r.get("dec_true_rad")),
        "roll_true_deg": None if r.get("roll_true_deg") is None else round(r["roll_true_deg"], 4),
        "boresight_error_arcsec": _as(r.get("boresight_error_rad")),
        "boresight_error_radec_arcsec": _as(r.get("boresight_error_radec_rad")),
        "attitude_error_arcsec": _as(r.get("attitude_error_rad")),
        "axis_error_arcsec": (None if r.get("err_x_rad") is None else
                              {a: _as(r[f"err_{a}_rad"]) for a in "xyz"}),
        "truth_residual_median_arcsec": _as(r.get("truth_residual_median_rad")),
        "truth_stars": r.get("truth_stars"), "truth_stars_found": r.get("truth_stars_found"),
        "truth_ids_agree": r.get("truth_ids_agree"), "truth_ids_disagree": r.get("truth_ids_disagree"),
        "altaz_ra_deg": _deg(r.get("altaz_ra_rad")), "altaz_dec_deg": _deg(r.get("altaz_dec_rad")),
        "altaz_error_deg": _deg(r.get("altaz_error_rad"), 4),
        "runtime_ms": None if r.get("t_total_ns") is None else round(r["t_total_ns"] / 1e6, 2),
        "overlay": overlay,
    }
    if r.get("alt_method"):
        out["alt"] = {"method": r["alt_method"], "status": r.get("alt_status"), "identified": r.get("alt_identified"),
                      "T": r.get("alt_T"),
                      "stars_identified": r.get("alt_stars_identified"),
                      "boresight_error_arcsec": _as(r.get("alt_boresight_error_rad")),
                      "residual_median_arcsec": _as(r.get("alt_residual_median_rad"))}
    if r.get("truth_note"):
        out["truth_note"] = r["truth_note"]
    if r.get("time_utc") is not None:                   # hil star --track
        out.update(track_json(r))
    if objects is not None:                              # unknown objects (jobs/kinds/hil_star_objects.py)
        out.update(zp_mag=None if r.get("zp_mag") is None else round(r["zp_mag"], 3),
                   zp_scatter_mag=None if r.get("zp_scatter_mag") is None else round(r["zp_scatter_mag"], 3),
                   zp_stars=r.get("zp_stars"), unknown_mag_limit=r.get("unknown_mag_limit"),
                   unknown_faint=r.get("unknown_faint"),
                   unknown_objects=(None if r.get("unknown_objects") is None else
                                    objects_json([o for o in objects if not o["is_target"] or
                                                  o["mag"] is None or r.get("unknown_mag_limit") is None or
                                                  o["mag"] <= r["unknown_mag_limit"]])))
    if r.get("target") is not None:                      # hil star --target
        out.update(target_json(r))
    out["stars"] = [{"hip": s["hip"], "vmag": round(s["vmag"], 2), "x_px": round(s["x_px"], 3),
                     "y_px": round(s["y_px"], 3), "pred_x_px": round(s["pred_x_px"], 3),
                     "pred_y_px": round(s["pred_y_px"], 3), "error_arcsec": _as(s["residual_rad"]),
                     "truth_error_arcsec": _as(s["truth_residual_rad"]), "truth_match": s["truth_match"],
                     "truth_id_agrees": s["truth_id_agrees"]} for s in stars]
    return out


def track_json(r: dict) -> dict:
    """The ``--track`` keys of one image row (jobs/cli/hil_star.py): time, mode, the sequence's attitude, the rate
    (deg/s, camera frame) and its 1-sigma per axis."""
    out = {"time_utc": r["time_utc"], "time_source": r.get("time_source"), "mode": r.get("track_mode"),
           "mode_reason": r.get("track_reason"), "track_stars": r.get("track_stars"),
           "track_ra_deg": None, "track_dec_deg": None, "track_roll_deg": None,
           "rate_deg_s": None, "rate_sigma_deg_s": None, "rate_source": r.get("rate_source")}
    if r.get("track_A") is not None:
        A = np.asarray(r["track_A"], np.float64).reshape(3, 3)
        ra, dec = unit_to_radec(A[2])
        out.update(track_ra_deg=round(math.degrees(float(ra)), 6), track_dec_deg=round(math.degrees(float(dec)), 6),
                   track_roll_deg=round(float(roll_deg(A)), 4))
    if r.get("rate_rad_s") is not None:
        out["rate_deg_s"] = [float(math.degrees(v)) for v in r["rate_rad_s"]]
        C = np.asarray(r["rate_cov"], np.float64).reshape(3, 3) if r.get("rate_cov") is not None else None
        if C is not None and np.all(np.isfinite(np.diag(C))):
            out["rate_sigma_deg_s"] = [float(math.degrees(math.sqrt(max(v, 0.0)))) for v in np.diag(C)]
    return out


def summary_line(j: dict) -> str:
    """One line per image, from its JSON object."""
    if j["error"]:
        return f"{j['image']}: ERROR {j['error']}"
    head = (f"{j['image']}: {j['status']} ({j['method']}), detected {j['stars_detected']}, identified "
            f"{j['stars_identified']}, T = {j['T']}")
    if j["identified"]:
        head += (f"; boresight RA {j['ra_deg']:.4f} Dec {j['dec_deg']:+.4f} deg, roll {j['roll_deg']:.2f} deg; "
                 f"residual median {j['residual_median_arcsec']:.1f} arcsec")
        if j["boresight_error_arcsec"] is not None:
            head += f"; boresight error {j['boresight_error_arcsec']:.1f} arcsec vs {j['truth_source']} truth"
        if j["altaz_error_deg"] is not None and j["truth_source"] != "altaz":
            head += f"; alt/az pointing off by {j['altaz_error_deg']:.3f} deg"
        if j.get("unknown_objects") is not None:
            head += (f"; {len(j['unknown_objects'])} unknown objects at least V {j['unknown_mag_limit']:g} bright "
                     f"({j['unknown_faint']} fainter)")
        if j.get("target") is not None:
            if j["target_kind"] is None:
                head += f"; target: none ({j['target_reason']})"
            else:
                head += (f"; target ({j['target_kind']}) RA {j['target_ra_deg']:.5f} Dec {j['target_dec_deg']:+.5f} "
                         f"deg +- {j['target_sigma_arcsec']:.1f} arcsec, {j['target_pixels']} px")
                if j["target_range_m"] is not None:
                    head += (f", range {j['target_range_m']:.2f} m [{j['target_range_min_m']:.2f}, "
                             f"{j['target_range_max_m']:.2f}]")
    return head


def table6_text(rows: list[dict], max_rows: int | None = None) -> str:
    """The reference's Table 6 for one image from its ``hil_star_table6.sql`` rows (brightest first)."""
    from dualsight.warehouse.query import format_table

    rows = rows[:max_rows] if max_rows is not None else rows
    has_truth = any(s["truth_error_arcsec"] is not None for s in rows)
    cols = ["HIP", "V", "obs col", "obs row", "pred col", "pred row", "error (arcsec)"]
    if has_truth:
        cols += ["vs truth (arcsec)", "truth id"]
    out = []
    for s in rows:
        row = [s["hip"], f"{s['vmag']:.2f}", f"{s['x_px']:.2f}", f"{s['y_px']:.2f}", f"{s['pred_x_px']:.2f}",
               f"{s['pred_y_px']:.2f}", f"{s['error_arcsec']:.1f}"]
        if has_truth:
            row += ["-" if s["truth_error_arcsec"] is None else f"{s['truth_error_arcsec']:.1f}",
                    {True: "agrees", False: "DIFFERS", None: "-"}[s["truth_id_agrees"]]]
        out.append(row)
    return format_table(cols, out)


DETAIL_IMAGES = 20
"""Images whose summary line and Table 6 the text report prints (the per-image table lists every image)."""


def text_report(con, run_id: str, docs: list[dict], settings, camera=None) -> str:
    """Header, per image its summary line and Table 6, then the per-image table (all from the SQL reports).
    With ``camera`` the header says what the catalog depth gives that field (catalogs/auto_limit.py)."""
    from dualsight.warehouse.query import format_table, run_report

    st = settings
    tol = st.voting["tolerance_rad"] / ARCSEC
    depth = f"catalog V <= {st.catalog['mag_limit']:g}"
    if camera is not None:
        depth = describe_mag_limit(camera, float(st.catalog["mag_limit"]))
    out = [f"{depth} at epoch {st.catalog['epoch_jyear']:g}, {st.method} voting "
           f"(tolerance {tol:.0f} arcsec, {st.voting['max_stars']} brightest vote)"
           + (f"; {st.alt_method} beside it" if st.alt_method else ""), ""]
    cols, rows = run_report(con, "hil_star_table6", run=run_id)
    t6: dict[int, list[dict]] = {}
    for r in rows:
        d = dict(zip(cols, r))
        t6.setdefault(d["case_id"], []).append(d)
    for k, j in enumerate(docs[:DETAIL_IMAGES]):
        out.append(summary_line(j))
        if t6.get(k):
            out.append(table6_text(t6[k]))
        out.append("")
    if len(docs) > DETAIL_IMAGES:
        out += [f"(the summary lines and Table 6 of {len(docs) - DETAIL_IMAGES:,} more images: --json, or dualsight "
                f"sql \"SELECT * FROM hil_star_stars WHERE run = '{run_id}'\"; every image has its row below)", ""]
    cols, rows = run_report(con, "hil_star_images", run=run_id)
    keep = ["image", "status", "stars_detected", "stars_identified", "T", "ra_deg", "dec_deg", "roll_deg",
            "boresight_error_arcsec", "residual_median_arcsec", "alt_boresight_error_arcsec", "ms"]
    alt = st.alt_method or "alt"
    out.append(format_table(["image", "status", "detected", "identified", "T", "RA deg", "Dec deg", "roll deg",
                             "bore err \"", "resid med \"", f"{alt} bore err \"", "ms"],
                            table_cells(keep, [[r[cols.index(c)] for c in keep] for r in rows])))
    return "\n".join(out)


# ============================================================================================ overlays
def licence_credit(path: Path) -> str | None:
    """Credit line for figures made from an image: the ``Licence:``/``License:`` line of a README.md next
    to it, if any (e.g. the ESA frames' "ESA/Gustav Pettersson, CC BY-SA 3.0 IGO"), else None."""
    readme = Path(path).parent / "README.md"
    try:
        text = readme.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    m = re.search(r"^\s*Licen[cs]e:\s*(.+)$", text, re.MULTILINE | re.IGNORECASE)
    if not m:
        return None
    line = m.group(1).strip()
    q = re.search(r'"([^"]+)"', line)
    return ("Images: " + q.group(1)) if q else line[:120]


def _overlay_title(j: dict) -> tuple[str, list[str]]:
    lines = [f"{j['method']} voting: {j['stars_detected']} detected, {j['stars_identified']} identified, T = {j['T']}"]
    if j["identified"]:
        lines.append(f"RA {j['ra_deg']:.4f}  Dec {j['dec_deg']:+.4f}  roll {j['roll_deg']:.2f} deg;  "
                     f"residual median {j['residual_median_arcsec']:.1f} arcsec")
    if j["boresight_error_arcsec"] is not None:
        lines.append(f"boresight error vs {j['truth_source']} truth {j['boresight_error_arcsec']:.1f} arcsec")
    return j["image"], lines


def write_overlays(spec, rows: list[dict], stars: dict[int, list[dict]], folder: Path, credit: str | None = None,
                   error_scale: float = 100.0) -> dict[int, str]:
    """One Figure-11-style PNG per processed image (``<image stem>.png``); returns {case_id: path}.

    The frame is re-read and its background subtraction and detection re-run (the same code and settings
    as the run, so the same detections); an image that changed since the run is skipped with a warning."""
    from dualsight.catalogs.stars import load_star_catalog          # pyarrow
    from dualsight.jobs.kinds import hil_star as hs                 # Taichi
    from dualsight.viz.overlay import star_overlay                  # matplotlib (~0.4 s): only with overlays

    folder = output_path(folder, folder=True)
    rt = hs.runtime(spec)
    cam = rt.camera
    cat = None
    out = {}
    for r in rows:
        if r["error"]:
            continue
        k = int(r["case_id"])
        entry = spec.images[k]
        try:
            px, _ = hs.read_frame(entry, cam)
        except ImageError as e:
            print(f"dualsight: no overlay for {entry.name}: {e}", file=sys.stderr)
            continue
        resid, _, det = hs.detect_frames(px[None], rt.settings, rt.detect)
        n = int(det.counts[0])
        det_xy = np.stack([det.x[:n], det.y[:n]], axis=1)
        field_xy = field_vmag = None
        if r["identified"]:
            cat = cat or load_star_catalog(rt.catalog)
            field_xy, rows_in = catalog_in_image(np.reshape(r["A_est"], (3, 3)), cat.unit, cam)
            field_vmag = cat.vmag[rows_in]
        truth = spec.truth(k)
        truth_xy = None
        if truth.matched is not None:
            truth_xy = np.stack([np.asarray(truth.matched.col), np.asarray(truth.matched.row)], axis=1)
        ident = [(s["x_px"], s["y_px"], s["pred_x_px"], s["pred_y_px"], s["hip"], s["vmag"], s["residual_rad"] / ARCSEC)
                 for s in stars.get(k, [])]
        title, lines = _overlay_title(to_json(r, stars.get(k, [])))
        p = folder / f"{Path(entry.path).stem}.png"
        star_overlay(p, resid[0], detections=det_xy, identified=ident, field_xy=field_xy, field_vmag=field_vmag,
                     truth_xy=truth_xy, title=title, info=lines,
                     credit=credit if credit is not None else licence_credit(Path(entry.path)),
                     error_scale=error_scale)
        out[k] = str(p)
    return out
