"""The ``dualsight hil`` command group: the flight algorithms on real images (hardware in the loop).

    dualsight hil star IMAGES... --camera FILE [--truth FILE]
                      [--lat DEG --lon DEG [--height M] [--time UTC] [--alt DEG] [--az DEG] [--roll DEG]]
                      [--method robust|paper] [--mag-limit M] [--tolerance-arcsec A] [--max-stars N]
                      [--config FILE.toml] [--json] [--lake DIR] [--run ID] [--no-lake] [--overlay-dir DIR]
    dualsight hil prox ...   (added by jobs/hil_prox.py)

``hil star`` identifies every image lost in space (no prior attitude) with the star chain of the
simulations (jobs/star_pipeline.py) and prints, per image, the boresight RA/Dec and roll, the stars
detected / identified, the match threshold T, and the reference's Table 6 (catalog id, magnitude,
observed-versus-predicted error per identified star); with ``--overlay-dir`` it draws the reference's
Figure 11 per image.  Results go to the lake: ``hil_star`` (one row per image) and ``hil_star_stars``
(one row per identified star), run id ``hil-star-<UTC timestamp>`` unless ``--run`` is given.

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
(null where not applicable; definitions in jobs/hil_star.py).

Exit status: 0 when every image was processed (identified or not), 1 when an image could not be read
(it still gets a row with ``error`` set, a message on stderr, and the other images run), 2 for bad
options (nothing is written).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path


def register(subparsers) -> None:
    """Add the ``hil`` command group to the top-level sub-parsers of ``dualsight``."""
    hil = subparsers.add_parser("hil", help="hardware in the loop: the flight algorithms on real images")
    hsub = hil.add_subparsers(dest="hil_action", metavar="ACTION")
    add_star_parser(hsub)
    # `hil prox` is registered here by jobs/hil_prox.py: hil_prox.add_parser(hsub)
    from dualsight.jobs import hil_prox

    hil_prox.add_parser(hsub)
    hil.set_defaults(func=lambda a: (hil.print_help(), 0)[1])


def add_star_parser(hsub) -> argparse.ArgumentParser:
    from dualsight.jobs.cli import _lake_arg

    p = hsub.add_parser("star", help="lost-in-space identification and attitude of real star images",
                        description="Identify real star images lost in space with the simulations' star chain; "
                                    "score them against a truth file or the tripod's time/site/alt-az.")
    p.add_argument("images", nargs="+", type=Path, help="image files (PNG, JPEG, TIFF, FITS) or folders of them")
    p.add_argument("--camera", type=Path, required=True, help="camera file (TOML with a [camera] table)")
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
    s.add_argument("--mag-limit", type=float, default=7.0, help="catalog magnitude limit, Johnson V (default 7.0)")
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
                   help="TOML overriding the settings: method, background_block_px, max_obs, [catalog], "
                        "[detect], [voting], [alt_voting]")
    o = p.add_argument_group("output")
    o.add_argument("--json", action="store_true", help="print one JSON list, one object per image")
    _lake_arg(o)
    o.add_argument("--run", default=None, help="run id (default hil-star-<UTC timestamp>)")
    o.add_argument("--no-lake", action="store_true", help="do not write to the lake")
    o.add_argument("--overlay-dir", type=Path, default=None,
                   help="write one Figure-11-style PNG per image (<image stem>.png) here")
    o.add_argument("--credit", default=None,
                   help="attribution on the overlays (default: the Licence line of a README.md next to the images)")
    p.set_defaults(func=cmd_hil_star)
    return p


def cmd_hil_star(args) -> int:
    from dualsight.errors import InputError
    from dualsight.jobs import hil_star as hs
    from dualsight.scene.camera import Camera, read_toml
    from dualsight.scene.skytruth import load_truth_json

    t_start = time.perf_counter()
    camera = Camera.from_toml(args.camera)
    config = read_toml(args.config) if args.config is not None else None
    paths = hs.expand_inputs(args.images)
    if not paths:
        raise InputError("no image files given", source="IMAGES")
    epoch = args.epoch if args.epoch is not None else (hs.observation_epoch(paths, args.time) or 2000.0)
    settings = hs.make_settings(method=args.method or "robust", mag_limit=args.mag_limit, epoch_jyear=epoch,
                                tolerance_arcsec=args.tolerance_arcsec, max_stars=args.max_stars,
                                k_sigma=args.k_sigma, min_pixels=args.min_pixels,
                                background_block_px=args.background_block, compare=not args.no_compare,
                                limit_arcsec=args.limit_arcsec, config=config,
                                source=str(args.config) if args.config else "hil star")
    if args.method and config and "method" in config and config["method"] != args.method:
        raise InputError(f"--method {args.method} contradicts method = {config['method']!r} in {args.config}",
                         source="--method")
    truth_file = load_truth_json(args.truth) if args.truth is not None else None
    site = None
    if args.lat is not None or args.lon is not None:
        if args.lat is None or args.lon is None:
            raise InputError("the tripod truth needs both --lat and --lon", source="--lat" if args.lat is None
                             else "--lon")
        site = hs.Site(args.lat, args.lon, args.height, args.time, args.alt, args.az, args.roll, args.pressure)
    elif args.alt is not None or args.az is not None:
        raise InputError("--alt/--az need the site: give --lat and --lon too", source="--lat")

    lake = run_id = None
    spec = {"camera": camera.to_dict(), "camera_file": str(args.camera), "settings": settings.to_dict(),
            "truth_file": str(args.truth) if args.truth else None,
            "site": None if site is None else dataclasses.asdict(site), "images": [str(p) for p in paths]}
    if not args.no_lake:
        from dualsight.jobs.cli import _lake

        lake = _lake(args)
        run_id = args.run or hs.default_run_id(lake)
        hs.check_run(lake, run_id, spec)                       # before any work: nothing written on refusal

    truths = hs.resolve_truths(paths, truth_file, site)
    ctx = hs.make_context(camera, settings)
    results = hs.run(paths, ctx, truths=truths, overlay_dir=args.overlay_dir, credit=args.credit)
    for r in results:
        if r.row.get("truth_note") and (args.truth is not None or site is not None):
            print(f"dualsight: {r.row['image']}: no truth ({r.row['truth_note']})", file=sys.stderr)
    elapsed = time.perf_counter() - t_start
    if lake is not None:
        hs.write_run(lake, run_id, results, spec, elapsed)

    if args.json:
        print(json.dumps([hs.to_json(r) for r in results], indent=1))
    else:
        print(_text(results, settings))
    n_err = sum(1 for r in results if r.row["error"])
    n_id = sum(1 for r in results if r.row["identified"])
    msg = f"{len(results)} images: {n_id} identified, {n_err} could not be processed ({elapsed:.1f} s)"
    if lake is not None:
        msg += (f"; run {run_id} in {lake.root} (datasets hil_star, hil_star_stars)\n"
                f"query: dualsight sql \"SELECT * FROM hil_star WHERE run = '{run_id}'\" --lake {lake.root}")
    print(msg, file=sys.stderr)
    return 1 if n_err else 0


def _text(results, settings) -> str:
    from dualsight.jobs import hil_star as hs
    from dualsight.warehouse.query import format_table

    st = settings
    out = [f"catalog V <= {st.catalog.mag_limit:g} at epoch {st.catalog.epoch_jyear:g}, {st.method} voting "
           f"(tolerance {st.voting.tolerance_rad / hs.ARCSEC:.0f} arcsec, {st.voting.max_stars} brightest vote)"
           + (f"; {st.alt_method} beside it" if st.alt_method else ""), ""]
    for r in results:
        out.append(hs.summary_line(r))
        if r.stars:
            out.append(hs.table6_text(r))
        out.append("")
    rows = []
    for r in results:
        j = hs.to_json(r)
        rows.append([j["image"], j["status"], j["stars_detected"], j["stars_identified"], j["T"],
                     j["ra_deg"], j["dec_deg"], j["roll_deg"], j["boresight_error_arcsec"],
                     j["residual_median_arcsec"], (j.get("alt") or {}).get("boresight_error_arcsec"),
                     j["runtime_ms"]])
    alt = settings.alt_method or "alt"
    out.append(format_table(["image", "status", "detected", "identified", "T", "RA deg", "Dec deg", "roll deg",
                             "bore err \"", "resid med \"", f"{alt} bore err \"", "ms"], rows,
                            floatfmt="{:.6g}"))
    return "\n".join(out)
