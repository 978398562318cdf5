"""The ``dualsight hil`` command group: the flight algorithms on real images (hardware in the loop).

    dualsight hil star IMAGES... --camera FILE [--truth FILE]
                      [--lat DEG --lon DEG [--height M] [--time UTC] [--alt DEG] [--az DEG] [--roll DEG]]
                      [--method robust|paper] [--mag-limit M] [--tolerance-arcsec A] [--max-stars N]
                      [--config FILE.toml] [--json] [--overlay-dir DIR]
                      [--lake DIR] [--run ID] [--no-lake] [--workers N] [--scheduler ADDR] [--shard-size N]
    dualsight hil prox ...   (jobs/cli/hil_prox.py)

Both are job kinds of the one engine (jobs/engine/runner.py: ``hil_star``, ``hil_prox``): the images are the cases,
split into shards of images, run in-process, on local workers or on a Dask cluster, written to the lake and
resumable; the default run id is ``hil-star-<spec hash>`` (a hash of the spec, which holds every image's
size and modification time, and of the code version), so the same images, settings and code resume (or just
re-report) the same run.  Everything printed comes back from the lake through the warehouse SQL
(``warehouse/sql/hil_star_*.sql``); ``--no-lake`` runs into a temporary lake that is deleted afterwards.

``hil star`` identifies every image lost in space (no prior attitude) with the star chain of the
simulations and prints, per image, the boresight RA/Dec and roll, the stars detected / identified, the match
threshold T, and the reference's Table 6 (catalog id, magnitude, observed-versus-predicted error per
identified star); with ``--overlay-dir`` it draws the reference's Figure 11 per image.  Lake datasets:
``hil_star`` (one row per image) and ``hil_star_stars`` (one row per identified star).

``--json`` prints ONE JSON list with one object per image, in input order, keys:
    image, path, error (null or the reason the image could not be processed), status, identified (bool),
    method, stars_detected, stars_used, stars_identified, T, ra_deg, dec_deg, roll_deg,
    residual_median_arcsec, residual_max_arcsec, truth_source ("file", "altaz" or "none"),
    ra_true_deg, dec_true_deg, roll_true_deg, boresight_error_arcsec, boresight_error_radec_arcsec,
    attitude_error_arcsec, axis_error_arcsec {x, y, z}, truth_residual_median_arcsec, truth_stars,
    truth_stars_found, truth_ids_agree, truth_ids_disagree, altaz_ra_deg, altaz_dec_deg, altaz_error_deg,
    runtime_ms, overlay, alt {method, identified, T, stars_identified, boresight_error_arcsec,
    residual_median_arcsec}, stars [{hip, vmag, x_px, y_px, pred_x_px, pred_y_px, error_arcsec,
    truth_error_arcsec, truth_match, truth_id_agrees}]
(null where not applicable; definitions in nav/hil_score.py).

Exit status: 0 when every image was processed (identified or not), 1 when an image could not be read
(it still gets a row with ``error`` set, a message on stderr, and the other images run), 2 for bad
options (nothing is written).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.reports import fit_distortion as fd_report
from dualsight.nav.distortion_procedure import FULL_CONFIG, MIN_STARS
from dualsight.scene.camera import read_toml
from dualsight.scene.camera_file import write_camera_toml


def register(subparsers) -> None:
    """Add the ``hil`` command group to the top-level sub-parsers of ``dualsight``."""
    from dualsight.jobs.cli import hil_prox as cli_hil_prox

    hil = subparsers.add_parser("hil", help="hardware in the loop: the flight algorithms on real images")
    hsub = hil.add_subparsers(dest="hil_action", metavar="ACTION")
    add_star_parser(hsub)
    cli_hil_prox.add_parser(hsub)
    hil.set_defaults(func=lambda a: (hil.print_help(), 0)[1])


def add_star_parser(hsub) -> argparse.ArgumentParser:
    from dualsight.jobs.cli.args import add_engine_args, add_image_args

    p = hsub.add_parser("star", help="lost-in-space identification and attitude of real star images",
                        description="Identify real star images lost in space with the simulations' star chain; "
                                    "score them against a truth file or the tripod's time/site/alt-az.")
    add_image_args(p)
    p.add_argument("--truth", type=Path, default=None,
                   help="truth file in the format of shared/data/real/esa_tetra3/truth.json (keyed by file name)")
    g = p.add_argument_group("tripod truth (astropy AltAz -> ICRS; the reference's night-sky test)")
    g.add_argument("--lat", type=float, default=None, help="site latitude, deg north")
    g.add_argument("--lon", type=float, default=None, help="site longitude, deg east")
    g.add_argument("--height", type=float, default=0.0, help="site height above the ellipsoid, m (default 0)")
    g.add_argument("--time", default=None,
                   help="UTC time of the images, ISO (alt/az truth and catalog epoch; default: from each file name)")
    g.add_argument("--alt", type=float, default=None, help="mount altitude, deg (default: from each file name)")
    g.add_argument("--az", type=float, default=None,
                   help="mount azimuth, deg from north through east (default: from each file name)")
    g.add_argument("--roll", type=float, default=0.0, help="camera roll on the mount, deg (default 0 = level)")
    g.add_argument("--pressure", type=float, default=0.0,
                   help="site pressure, hPa, to include refraction (default 0: geometric)")
    s = p.add_argument_group("method")
    s.add_argument("--method", choices=["robust", "paper"], default=None,
                   help="voting method (default robust: VotingConfig.robust(); paper: the reference's); "
                        "the other one runs beside it unless --no-compare")
    s.add_argument("--no-compare", action="store_true", help="do not run the other voting method")
    s.add_argument("--detector", choices=["local", "global"], default=None,
                   help="star detector (default local: tiled background, matched filter, hot-pixel test, PSF-fit "
                        "centroids; global: smooth background, one threshold, moment centroids: ~5x faster, "
                        "4 vs 22 ms per 1024x1024 frame, less accurate on faint stars; for throughput, with "
                        "--no-compare)")
    s.add_argument("--mag-limit", type=float, default=None,
                   help="catalog magnitude limit, Johnson V (default: auto, from the camera's field: about 35 "
                        "catalog stars per field on average, at most V 8; catalogs/auto_limit.py)")
    s.add_argument("--epoch", type=float, default=None,
                   help="catalog epoch, Julian year, to which proper motion moves the stars (default: the "
                        "images' date from --time or their file names, to 0.1 yr; else 2000.0)")
    s.add_argument("--tolerance-arcsec", type=float, default=20.0, help="voting tolerance (default 20)")
    s.add_argument("--max-stars", type=int, default=25, help="brightest detections that vote (default 25)")
    s.add_argument("--k-sigma", type=float, default=5.0, help="detection threshold, noise sigmas (default 5)")
    s.add_argument("--min-pixels", type=int, default=3, help="smallest blob, px (default 3: no hot pixels)")
    s.add_argument("--background-block", type=int, default=32,
                   help="background median block, px (default 32; 0 = one global level)")
    s.add_argument("--limit-arcsec", type=float, default=None,
                   help="status limit per axis (default 100 with --truth, 7200 with alt/az truth)")
    s.add_argument("--config", type=Path, default=None,
                   help="TOML overriding the settings: method, background_block_px, max_obs, batch_size, "
                        "[catalog], [detect], [voting], [alt_voting]")
    o = p.add_argument_group("output")
    o.add_argument("--json", action="store_true", help="print one JSON list, one object per image")
    o.add_argument("--overlay-dir", type=Path, default=None,
                   help="write one Figure-11-style PNG per image (<image stem>.png) here")
    o.add_argument("--credit", default=None,
                   help="attribution on the overlays (default: the Licence line of a README.md next to the images)")
    w = p.add_argument_group("tuning by sweep (jobs/kinds/hil_star_sweep.py)")
    w.add_argument("--sweep", action="append", default=None, metavar="KEY=V1,V2,...",
                   help="run every combination of these settings over the images as one job and rank them "
                        "(repeatable; keys: k-sigma, min-pixels, max-stars, tolerance-arcsec, mag-limit, "
                        "background-block, method, detector); with --truth by success rate, else by agreement")
    f = p.add_argument_group("lens distortion from the sky (jobs/kinds/fit_distortion.py)")
    f.add_argument("--fit-distortion", action="store_true",
                   help="fit k1, k2 and the focal length (fx = fy) to the solved frames' identified stars and "
                        "write the fitted camera file to -o (in-process; nothing is written to the lake)")
    f.add_argument("-o", "--output", type=Path, default=None, help="camera file written by --fit-distortion")
    f.add_argument("--force", action="store_true", help="let --fit-distortion overwrite an existing -o file")
    add_engine_args(p, prefix="hil-star")
    p.set_defaults(func=cmd_hil_star)
    return p


def settings_from_args(args, config: dict | None, epoch: float):
    """The ``hil_star`` settings of the command line's method options over the ``--config`` table."""
    from dualsight.jobs.kinds import hil_star as hs

    return hs.settings_from_table(config, source=str(args.config) if args.config else "hil star",
                                  method=args.method, compare=not args.no_compare, detector=args.detector,
                                  background_block_px=args.background_block, limit_arcsec=args.limit_arcsec,
                                  mag_limit=args.mag_limit, epoch_jyear=epoch,
                                  tolerance_arcsec=args.tolerance_arcsec, max_stars=args.max_stars,
                                  k_sigma=args.k_sigma, min_pixels=args.min_pixels)


def star_spec_from_args(args):
    """The validated ``hil_star`` spec of the command line (truths resolved now); every check is made
    before the lake is touched.  Its dict form is ``spec.to_dict()``."""
    from dualsight.errors import InputError
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.cli.args import expand_inputs
    from dualsight.jobs.kinds.hil_truth import Site, resolve_star_truths
    from dualsight.scene.camera import Camera, read_toml
    from dualsight.scene.skytruth import load_truth_json
    from dualsight.scene.timescale import observation_epoch

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
    return hs.spec_from_dict(hs.build_spec(paths, camera, settings, resolve_star_truths(paths, truth_file, site)),
                             source="hil star")


def cmd_hil_star(args) -> int:
    import time

    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.reports import hil_star as rep
    from dualsight.jobs.cli.args import done_message, engine_lake, run_engine
    from dualsight.scene.camera import Camera
    from dualsight.warehouse.query import connect, run_report

    if args.fit_distortion or args.output is not None or args.force:     # lens distortion from the sky
        return cmd_fit_distortion(args)
    t_start = time.perf_counter()
    spec = star_spec_from_args(args)
    if args.sweep:
        return cmd_hil_star_sweep(args, spec, t_start)
    with engine_lake(args) as (lake, kept):
        manifest = run_engine("hil_star", spec.to_dict(), hs.n_cases(spec), lake, args, label="hil star")
        run_id = manifest["run_id"]
        con = connect(lake)
        rows, stars = rep.fetch(con, run_id)
        overlays = (rep.write_overlays(spec, rows, stars, args.overlay_dir, credit=args.credit)
                    if args.overlay_dir is not None else {})
        docs = [rep.to_json(r, stars.get(r["case_id"], []), overlays.get(r["case_id"])) for r in rows]
        for j in docs:
            if j["error"]:
                print(f"dualsight: {j['error']}; skipped, the other images go on", file=sys.stderr)
            elif j.get("truth_note") and (args.truth is not None or args.lat is not None):
                print(f"dualsight: {j['image']}: no truth ({j['truth_note']})", file=sys.stderr)
        print(json.dumps(docs, indent=1) if args.json else
              rep.text_report(con, run_id, docs, spec.settings, camera=Camera.from_dict(spec.camera)))
        cols, srows = run_report(con, "hil_star_summary", run=run_id)
        summary = dict(zip(cols, srows[0]))
        con.close()
    n_err = summary["errors"]
    print(done_message(f"{summary['images']} images: {summary['identified']} identified, {n_err} could not be "
                       "processed", time.perf_counter() - t_start, run_id, lake, kept, tuple(hs.SCHEMAS),
                       query="hil_star"), file=sys.stderr)
    return 1 if n_err else 0


def cmd_hil_star_sweep(args, base, t_start: float) -> int:
    """``hil star --sweep``: the grid of settings as one ``hil_star_sweep`` job, ranked."""
    import argparse
    import time

    from dualsight.jobs.kinds import hil_star_sweep as sw
    from dualsight.jobs.cli.args import done_message, engine_lake, run_engine
    from dualsight.scene.camera import read_toml
    from dualsight.warehouse.query import connect

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
        f"{int(rep.final.stars.sum())} stars identified."])
    table = {"method": "nav/distortion_fit.py: Levenberg-Marquardt, OpenCV radial model, Huber + rejection",
             "input_camera": str(camera_file), "images": n_img, "frames_used": fit.n_frames,
             "stars_used": fit.n_stars, "stars_rejected": int((~fit.inlier).sum()),
             "fitted": ["fx=fy", "k1", "k2"], "std": fit.std, "rms_before_px": rep.rms_before_px,
             "rms_after_px": fit.rms_px, "sigma_px": fit.sigma_px, "reject_sigma": FULL_CONFIG.reject_sigma,
             "min_stars": MIN_STARS, "frames_solved_after": int(rep.final.solved.sum())}
    notes = f"k1, k2, fx = fy fitted from {fit.n_stars} stars in {fit.n_frames} frames (hil star --fit-distortion)"
    return write_camera_toml(rep.camera, output, extra={"distortion_fit": table}, name=src.get("name"),
                             notes=notes, comment=comment)


def cmd_fit_distortion(args) -> int:
    """``hil star --fit-distortion``: focal length and lens distortion from the sky (jobs/kinds/fit_distortion.py).

    Refusals (one line ``dualsight: error: ...``, exit status 2, nothing written): ``--fit-distortion`` without
    ``-o``; ``-o`` or ``--force`` without ``--fit-distortion``; ``--sweep`` or ``--overlay-dir`` with it; ``-o``
    naming an existing file without ``--force``, a folder, or a file in a missing folder (these before any work);
    too few stars identified by a whole-field pass.  Unreadable images are named on stderr and left out (exit
    status 1 after writing, as ``hil star``).  ``--lake``, ``--run``, ``--workers`` ... are not used.  Progress
    (one line per pass) goes to stderr, the summary to stdout; ``--json`` prints one JSON object instead
    (jobs/reports/fit_distortion.py: ``summary_json``) and no progress."""
    from dualsight.jobs.kinds import fit_distortion           # Taichi (the hil_star chain)

    if not args.fit_distortion:
        raise InputError("-o/--output and --force go with --fit-distortion", source="hil star")
    if getattr(args, "sweep", None):
        raise InputError("fits one camera with one set of settings; drop --sweep", source="--fit-distortion")
    if args.overlay_dir is not None:
        raise InputError("draws no overlays; run hil star with the fitted camera for them", source="--fit-distortion")
    out = check_fit_output(args)
    spec = star_spec_from_args(args)
    n = len(spec.images)
    rep = fit_distortion.fit_from_spec(
        spec, progress=None if args.json else (lambda event, value: print(fd_report.progress_line(event, value, n),
                                                                          file=sys.stderr)),
        warn=lambda e: print(f"dualsight: {e}; skipped, the other images go on", file=sys.stderr))
    try:
        write_fitted_camera(rep, out, args.camera, [e.path for e in spec.images])
    except OSError as e:
        raise InputError(f"cannot write the camera file ({e.strerror or e})", source=str(out)) from None
    print(json.dumps(fd_report.summary_json(rep, out), indent=1) if args.json else fd_report.summary_text(rep, out))
    return 1 if any(rep.errors) else 0
