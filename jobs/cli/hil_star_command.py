"""``dualsight hil star``, the command itself (its options: jobs/cli/hil_star.py, which imports this module when the
command runs): the images' spec from the options, the ``hil_star`` run through the engine and its report read back
from the lake (jobs/reports/hil_star.py); ``--sweep`` (a ``hil_star_sweep`` job, ranked) and ``--fit-distortion``
(jobs/kinds/fit_distortion.py; the fitted camera file written here, the summary by jobs/reports/fit_distortion.py).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.cli.args import done_message, engine_lake, run_engine
from dualsight.jobs.cli.hil_star_settings import settings_from_args
from dualsight.jobs.kinds import fit_distortion
from dualsight.jobs.kinds import hil_star as hs
from dualsight.jobs.kinds import hil_star_sweep as sw
from dualsight.jobs.kinds.hil_common import SkipNotes, expand_inputs, n_cases
from dualsight.jobs.kinds.hil_star_spec import spec_from_dict
from dualsight.jobs.kinds.hil_star_track import tracking_settings
from dualsight.jobs.kinds.hil_truth import Site, resolve_star_truths
from dualsight.jobs.reports import fit_distortion as fd_report
from dualsight.jobs.reports import hil_star as hil_report
from dualsight.nav.distortion_procedure import FULL_CONFIG, MIN_STARS
from dualsight.scene.camera import Camera, read_toml
from dualsight.scene.camera_file import write_camera_toml
from dualsight.scene.frame_times import frame_times, time_order
from dualsight.scene.skytruth import load_truth_json
from dualsight.scene.timescale import observation_epoch
from dualsight.warehouse.query import connect, run_report


def star_spec_from_args(args):
    """The validated ``hil_star`` spec of the command line (truths resolved now); every check is made
    before the lake is touched.  Its dict form is ``spec.to_dict()``."""
    camera = Camera.from_toml(args.camera)
    config = read_toml(args.config) if args.config is not None else None
    if args.method and config and "method" in config and config["method"] != args.method:
        raise InputError(f"--method {args.method} contradicts method = {config['method']!r} in {args.config}",
                         source="--method")
    if args.detector and config and "detector" in config and config["detector"] != args.detector:
        raise InputError(f"--detector {args.detector} contradicts detector = {config['detector']!r} in "
                         f"{args.config}", source="--detector")
    paths = expand_inputs(args.images)
    if not paths:
        raise InputError("no image files given", source="IMAGES")
    track = None
    if getattr(args, "times", None) is not None and not getattr(args, "track", False):
        raise InputError("goes with --track (the images as one ordered sequence)", source="--times")
    if getattr(args, "tracking", None) is not None and not getattr(args, "track", False):
        raise InputError("goes with --track (the images as one ordered sequence)", source="--tracking")
    if getattr(args, "track", False):
        if args.sweep or args.fit_distortion:
            raise InputError("solves one sequence with one set of settings; drop --sweep and --fit-distortion",
                             source="--track")
        times = frame_times(paths, args.times)
        order = time_order(times)
        paths, times = [paths[i] for i in order], [times[i] for i in order]
        track = {"times_utc": [t.iso for t in times], "time_sources": [t.source for t in times]}
        if getattr(args, "tracking", None) is not None:
            track.update(tracking_settings(args.tracking))
    epoch = args.epoch if args.epoch is not None else (observation_epoch(paths, args.time) or 2000.0)
    settings = settings_from_args(args, config, epoch)
    truth_file = load_truth_json(args.truth) if args.truth is not None else None
    site = None
    if args.lat is not None or args.lon is not None:
        if args.lat is None or args.lon is None:
            raise InputError("the tripod truth needs both --lat and --lon", source="--lat" if args.lat is None
                             else "--lon")
        site = Site(args.lat, args.lon, args.height, args.time, args.alt, args.az, args.roll, args.pressure)
    elif args.alt is not None or args.az is not None:
        raise InputError("--alt/--az need the site: give --lat and --lon too", source="--lat")
    d = hs.build_spec(paths, camera, settings, resolve_star_truths(paths, truth_file, site))
    if track is not None:
        d["track"] = track
    d.update(target_from_args(args))
    spec = spec_from_dict(d, source="hil star")
    hs.check_pair_catalog(spec, source=str(args.camera))     # a pair catalog too large to build: one line, now
    return spec


def parse_target_near(text: str) -> list[float]:
    """``--target-near RA,DEC[,RADIUS]`` (deg) -> [ra in [0, 360), dec in [-90, 90], radius in (0, 180]] (default
    radius 1 deg); InputError naming the option and the allowed ranges otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise InputError(f"must be RA,DEC or RA,DEC,RADIUS in degrees (e.g. 83.6,22.0,0.5), got {text!r}",
                         source="--target-near")
    ra, dec, rad = vals[0] % 360.0, vals[1], vals[2] if len(vals) == 3 else 1.0
    if not -90.0 <= dec <= 90.0 or not 0.0 < rad <= 180.0:
        raise InputError(f"needs DEC in [-90, 90] and RADIUS in (0, 180] deg, got {text!r}", source="--target-near")
    return [ra, dec, rad]


def target_from_args(args) -> dict:
    """The spec's ``target`` (the satellite file's name and components; its one-line errors name the file) and
    ``target_near`` of ``--target`` / ``--target-near``; empty without them."""
    from dualsight.jobs.kinds.hil_prox import target_spec          # pyarrow (the shapes' check)

    target = getattr(args, "target", None)
    near = getattr(args, "target_near", None)
    if target is None:
        if near is not None:
            raise InputError("goes with --target SAT.toml (the target's satellite file)", source="--target-near")
        return {}
    if args.sweep or args.fit_distortion:
        raise InputError("reports the target of one run; drop --sweep and --fit-distortion", source="--target")
    out = {"target": target_spec(target)}
    if near is not None:
        out["target_near"] = parse_target_near(near)
    return out


def run(args) -> int:
    """``dualsight hil star``: the images as a ``hil_star`` run (or ``--sweep``, ``--fit-distortion``), the report
    read back from the lake; exit status 1 when an image could not be processed."""
    if args.fit_distortion or args.output is not None or args.force:     # lens distortion from the sky
        return run_fit_distortion(args)
    t_start = time.perf_counter()
    spec = star_spec_from_args(args)
    if args.sweep:
        return run_sweep(args, spec, t_start)
    if spec.track is not None:                          # one sequence: every image in one shard, in time order
        if getattr(args, "shard_size", None) not in (None, n_cases(spec)):
            raise InputError(f"--track runs the images as one shard; omit --shard-size or give {n_cases(spec)}",
                             source="--shard-size")
        args = argparse.Namespace(**{**vars(args), "shard_size": n_cases(spec)})
    with engine_lake(args) as (lake, kept):
        manifest = run_engine("hil_star", spec.to_dict(), n_cases(spec), lake, args, label="hil star")
        run_id = manifest["run_id"]
        con = connect(lake)
        rows, stars = hil_report.fetch(con, run_id)
        objects = hil_report.fetch_objects(con, run_id)
        overlays = (hil_report.write_overlays(spec, rows, stars, args.overlay_dir, credit=args.credit)
                    if args.overlay_dir is not None else {})
        docs = [hil_report.to_json(r, stars.get(r["case_id"], []), overlays.get(r["case_id"]),
                                   objects.get(r["case_id"], [])) for r in rows]
        skipped = SkipNotes()
        nonfinite = SkipNotes(outcome="ignored", rest="more images with NaN or infinite pixels")
        for r, j in zip(rows, docs):
            if j["error"]:
                skipped(j["error"])
                continue
            if r.get("nonfinite_pixels"):
                nonfinite(f"{j['image']}: {r['nonfinite_pixels']:,} of {r['width'] * r['height']:,} pixels are NaN "
                          "or infinite")
            if j.get("truth_note") and (args.truth is not None or args.lat is not None):
                print(f"dualsight: {j['image']}: no truth ({j['truth_note']})", file=sys.stderr)
        skipped.finish(f"every image's reason: dualsight sql \"SELECT image, error FROM {hs.PRIMARY} WHERE run = "
                       f"'{run_id}' AND error IS NOT NULL ORDER BY case_id\" --lake {lake.root}" if kept else
                       "every image's reason: the \"error\" of each image in the JSON on stdout" if args.json else
                       "every image's reason: --json (or run without --no-lake to keep the rows)")
        nonfinite.finish(f"every one: dualsight sql \"SELECT image, nonfinite_pixels FROM {hs.PRIMARY} WHERE run = "
                         f"'{run_id}' AND nonfinite_pixels > 0 ORDER BY case_id\" --lake {lake.root}" if kept else
                         "every one: the \"nonfinite_pixels\" of each image in the JSON on stdout" if args.json else
                         "every one: --json (or run without --no-lake to keep the rows)")
        print(json.dumps(docs, indent=1) if args.json else
              hil_report.text_report(con, run_id, docs, spec.settings, camera=Camera.from_dict(spec.camera)))
        cols, srows = run_report(con, "hil_star_summary", run=run_id)
        summary = dict(zip(cols, srows[0]))
        con.close()
    hint = psf_width_hint(rows, spec.settings, args.camera)
    if hint:
        print(f"dualsight: {hint}", file=sys.stderr)
    n_err = summary["errors"]
    print(done_message(f"{summary['images']} images: {summary['identified']} identified, {n_err} could not be "
                       "processed", time.perf_counter() - t_start, run_id, lake, kept, tuple(hs.SCHEMAS),
                       query="hil_star"), file=sys.stderr)
    return 1 if n_err else 0


def psf_width_hint(rows: list[dict], settings, camera_file) -> str | None:
    """One line suggesting ``psf_sigma_px`` for the camera file when the local detector measured the PSF width on
    every frame (neither the camera file nor the settings state it) and the frames agree on it
    (``kernels.detect_local.frames_psf_width``); else None."""
    from dualsight.kernels.detect_local import frames_psf_width

    dl = settings.detect_local
    if settings.detector != "local" or dl.get("psf_sigma_px") is not None or dl.get("psf_sigma_stated_px") is not None:
        return None
    w = [r["psf_sigma_px"] for r in rows if not r.get("error")]
    one = frames_psf_width(w)
    if one is None:
        return None
    med, n = one
    lo, hi = min(v for v in w if v and v > 0), max(v for v in w if v and v > 0)
    return (f"the frames' PSF width is {lo:.2f}-{hi:.2f} px (median {med:.2f}, {n} images): "
            f"psf_sigma_px = {med:.2f} in the [camera] table of {camera_file} spares the detector's width pass on "
            "every frame (~20 % of its time)")


def run_sweep(args, base, t_start: float) -> int:
    """``hil star --sweep``: the grid of settings as one ``hil_star_sweep`` job, ranked."""
    points = sw.grid(sw.parse_sweeps(args.sweep))
    config = read_toml(args.config) if args.config is not None else None
    epoch = float(base.settings.catalog["epoch_jyear"])
    variants = []
    for pt in points:
        a = argparse.Namespace(**vars(args))
        for k, v in pt.items():
            setattr(a, sw.SWEEP_KEYS[k][0], v)
        variants.append(settings_from_args(a, config, epoch))
    spec = sw.spec_from_dict(sw.build_spec(base, variants, [sw.label(p) for p in points]), source="hil star --sweep")
    with engine_lake(args) as (lake, kept):
        manifest = run_engine("hil_star_sweep", spec.to_dict(), sw.n_cases(spec), lake, args, label="hil star sweep")
        run_id = manifest["run_id"]
        con = connect(lake)
        cur = con.execute(f"SELECT * EXCLUDE (run) FROM {sw.PRIMARY} WHERE run = $run ORDER BY case_id",
                          {"run": run_id})
        names = [d[0] for d in cur.description]
        rows = [dict(zip(names, r)) for r in cur.fetchall()]
        con.close()
    summary = sw.summarize(rows, len(spec.variants), list(spec.labels))
    print(json.dumps(summary, indent=1) if args.json else sw.text(summary))
    n_err = sum(r["error"] is not None for r in rows)
    print(done_message(f"{len(points)} settings x {len(spec.images)} images, best {summary[0]['label']}",
                       time.perf_counter() - t_start, run_id, lake, kept, tuple(sw.SCHEMAS), query=sw.PRIMARY),
          file=sys.stderr)
    return 1 if n_err else 0


# ============================================================================================ --fit-distortion
def check_fit_output(args) -> Path:
    """The ``-o`` of ``--fit-distortion``, refused before any work when missing, a folder, in a missing folder,
    or an existing file without ``--force``."""
    out = args.output
    if out is None:
        raise InputError("needs -o/--output CAMERA.toml (the fitted camera file to write)", source="--fit-distortion")
    if out.is_dir():
        raise InputError("is a folder; give the camera file's name, e.g. fitted.toml", source=str(out))
    if not out.parent.is_dir():
        raise InputError(f"folder {out.parent} does not exist; create it first", source=str(out))
    if out.exists() and not args.force:
        raise InputError("exists; give --force to overwrite it", source=str(out))
    return out


def write_fitted_camera(rep, output: Path, camera_file: Path, images: list) -> Path:
    """The camera file of a ``--fit-distortion`` fit ``rep`` (``nav.distortion_procedure.FitReport``):
    ``[camera]`` + ``[distortion_fit]``, comments with what was fitted and the rms (scene/camera_file.py's
    writer: tomli-w, a temporary name renamed)."""
    fit, cam0 = rep.fit, rep.camera_in
    src = read_toml(camera_file).get("camera", {})
    n_img = rep.n_images
    where = str(Path(images[0]).parent) if images else "?"
    comment = "\n".join([
        f"Fitted by `dualsight hil star --fit-distortion` from {fit.n_stars} identified stars in {fit.n_frames} "
        f"solved frames",
        f"  ({n_img} images in {where}; input camera file {camera_file}).",
        f"Fitted: {fd_report.what_was_fitted(cam0)}.",
        "  " + fd_report.fit_line(fit) + ".",
        f"rms residual {rep.rms_before_px:.3f} px before (input camera, attitudes re-fitted), {fit.rms_px:.3f} px "
        f"after; {int((~fit.inlier).sum())} stars rejected as outliers (> {FULL_CONFIG.reject_sigma:g} sigma).",
        f"Re-solved with this camera: {int(rep.final.solved.sum())}/{n_img} frames, "
        f"{int(rep.final.stars.sum())} stars identified."]
        + ([f"psf_sigma_px: the stars' PSF width the detector measured on these frames (their median, "
            f"{rep.camera.psf_sigma_px:g} px)."] if rep.camera.psf_sigma_px is not None
           and rep.camera_in.psf_sigma_px is None else []))
    table = {"method": "nav/distortion_fit.py: Levenberg-Marquardt, OpenCV radial model, Huber + rejection",
             "input_camera": str(camera_file), "images": n_img, "frames_used": fit.n_frames,
             "stars_used": fit.n_stars, "stars_rejected": int((~fit.inlier).sum()),
             "fitted": ["fx=fy", "k1", "k2"], "std": fit.std, "rms_before_px": rep.rms_before_px,
             "rms_after_px": fit.rms_px, "sigma_px": fit.sigma_px, "reject_sigma": FULL_CONFIG.reject_sigma,
             "min_stars": MIN_STARS, "frames_solved_after": int(rep.final.solved.sum())}
    notes = f"k1, k2, fx = fy fitted from {fit.n_stars} stars in {fit.n_frames} frames (hil star --fit-distortion)"
    return write_camera_toml(rep.camera, output, extra={"distortion_fit": table}, name=src.get("name"),
                             notes=notes, comment=comment)


def run_fit_distortion(args) -> int:
    """``hil star --fit-distortion``: focal length and lens distortion from the sky (jobs/kinds/fit_distortion.py).

    Refusals (one line ``dualsight: error: ...``, exit status 2, nothing written): ``--fit-distortion`` without
    ``-o``; ``-o`` or ``--force`` without ``--fit-distortion``; ``--sweep`` or ``--overlay-dir`` with it; ``-o``
    naming an existing file without ``--force``, a folder, or a file in a missing folder (these before any work);
    too few stars identified by a whole-field pass.  Unreadable images are named on stderr and left out (exit
    status 1 after writing, as ``hil star``).  ``--lake``, ``--run``, ``--workers`` ... are not used.  Progress
    (one line per pass) goes to stderr, the summary to stdout; ``--json`` prints one JSON object instead
    (jobs/reports/fit_distortion.py: ``summary_json``) and no progress."""
    if not args.fit_distortion:
        raise InputError("-o/--output and --force go with --fit-distortion", source="hil star")
    if getattr(args, "sweep", None):
        raise InputError("fits one camera with one set of settings; drop --sweep", source="--fit-distortion")
    if args.overlay_dir is not None:
        raise InputError("draws no overlays; run hil star with the fitted camera for them", source="--fit-distortion")
    out = check_fit_output(args)
    spec = star_spec_from_args(args)
    n = len(spec.images)
    skipped = SkipNotes()
    rep = fit_distortion.fit_from_spec(
        spec, progress=None if args.json else (lambda event, value: print(fd_report.progress_line(event, value, n),
                                                                          file=sys.stderr)),
        warn=skipped)
    skipped.finish("every image's reason: the JSON's \"errors\" on stdout" if args.json else
                   "every image's reason: --json (its \"errors\")")
    try:
        write_fitted_camera(rep, out, args.camera, [e.path for e in spec.images])
    except OSError as e:
        raise InputError(f"cannot write the camera file ({e.strerror or e})", source=str(out)) from None
    print(json.dumps(fd_report.summary_json(rep, out), indent=1) if args.json else fd_report.summary_text(rep, out))
    return 1 if any(rep.errors) else 0
