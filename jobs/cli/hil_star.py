"""The ``dualsight hil`` command group: the flight algorithms on real images (hardware in the loop).

    dualsight hil star IMAGES... --camera FILE [--truth FILE]
                      [--lat DEG --lon DEG [--height M] [--time UTC] [--alt DEG] [--az DEG] [--roll DEG]]
                      [--method robust|paper] [--mag-limit M] [--tolerance-arcsec A] [--max-stars N]
                      [--config FILE.toml] [--json] [--overlay-dir DIR] [--track [--times FILE.csv]]
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
    truth_error_arcsec, truth_match, truth_id_agrees}],
    zp_mag, zp_scatter_mag, zp_stars (photometric zero point: V = zp_mag - 2.5 log10(flux ADU), from the identified
    unsaturated stars), unknown_mag_limit, unknown_faint (unknown but fainter: counted), unknown_objects
    [{ra_deg, dec_deg, sigma_arcsec, x_px, y_px, pixels, mag, flux_adu, saturated, nearest_hip, nearest_vmag,
    nearest_sep_px, is_target}] (detections no catalog star to V 12 explains, at least unknown_mag_limit bright;
    nav/unknown_objects.py)
(null where not applicable; definitions in nav/hil_score.py).  Lake dataset ``hil_star_objects``: the unknown objects.

``--target SAT.toml`` adds per image: target (its name), target_kind ("resolved", "point" or null),
target_reason (why it is null), target_ra_deg, target_dec_deg, target_sigma_arcsec (1 sigma per axis, centroid and
attitude), target_pixels, target_x_px, target_y_px, target_mag (a point target; null for a resolved one, whose
flux saturates), and for a resolved target target_range_m,
target_range_min_m, target_range_max_m (nav/field_target.py: the rule).

``--track`` treats the images as one ordered sequence (issue 22, point 4; jobs/kinds/hil_star_track.py): each
image's time from ``--times FILE`` (CSV with the header ``image,utc``), else FITS ``DATE-OBS``, EXIF
``DateTimeOriginal``, or the file name (scene/frame_times.py); the images are sorted by time (the JSON list and
the case ids follow that order), run as one shard, and go through the tracker's state machine (nav/sequence.py:
lost-in-space until a fix, then tracking, fallback).  Each JSON object gains ``time_utc``, ``time_source``,
``mode`` ("lost_in_space", "tracking" or "none"), ``mode_reason``, ``track_stars``, ``track_ra_deg``,
``track_dec_deg``, ``track_roll_deg`` (the sequence's attitude), ``rate_deg_s`` [x, y, z] (camera frame),
``rate_sigma_deg_s`` [x, y, z] (1 sigma per axis), ``rate_source`` ("stars" or "attitudes"); the other keys
stay the lost-in-space answer of each image alone.

Exit status: 0 when every image was processed (identified or not), 1 when an image could not be read
(it still gets a row with ``error`` set, a message on stderr, and the other images run), 2 for bad
options (nothing is written).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dualsight.jobs.cli import hil_prox as cli_hil_prox
from dualsight.jobs.cli.args import add_engine_args, add_image_args


def register(subparsers) -> None:
    """Add the ``hil`` command group to the top-level sub-parsers of ``dualsight``."""
    hil = subparsers.add_parser("hil", help="hardware in the loop: the flight algorithms on real images")
    hsub = hil.add_subparsers(dest="hil_action", metavar="ACTION")
    add_star_parser(hsub)
    cli_hil_prox.add_parser(hsub)
    hil.set_defaults(func=lambda a: (hil.print_help(), 0)[1])


def add_star_parser(hsub) -> argparse.ArgumentParser:
    """Add ``hil star`` (its options; ``--sweep`` and ``--fit-distortion`` included) to the ``hil`` group."""
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
    t = p.add_argument_group("image sequences (jobs/kinds/hil_star_track.py)")
    t.add_argument("--track", action="store_true",
                   help="treat the images as one sequence ordered by time: lost-in-space until a fix, then "
                        "tracking; adds time_utc, mode and rate_deg_s per image")
    t.add_argument("--times", type=Path, default=None, metavar="FILE.csv",
                   help="with --track: each image's UTC time, a CSV with the header image,utc (default: FITS "
                        "DATE-OBS, EXIF DateTimeOriginal, or a YYYY-MM-DDTHHMMSS in the file name)")
    t.add_argument("--tracking", type=Path, default=None, metavar="FILE.toml",
                   help="with --track: the tracker's settings, a [tracking] table (window_k_sigma, rate_sigma_arcsec_s, "
                        "...) and max_coast_frames, lis_min_stars (jobs/kinds/hil_star_track.tracking_settings)")
    tg = p.add_argument_group("unknown objects and the target spacecraft (jobs/kinds/hil_star_objects.py)")
    tg.add_argument("--target", type=Path, default=None, metavar="SAT.toml",
                    help="a satellite file (examples/satellites/cubesat_3u.toml): report per image the target's "
                         "RA/Dec, pixels and 1-sigma, and where it is resolved its range (Eq. 1 with the file's "
                         "projected-area table); the target is the resolved blob, else the brightest unknown object")
    tg.add_argument("--target-near", default=None, metavar="RA,DEC[,RADIUS]",
                    help="with --target: the unknown object nearest this ICRS direction (deg) within RADIUS "
                         "(deg, default 1) is the point-like target")
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


def cmd_hil_star(args) -> int:
    """``dualsight hil star`` (the module docstring; ``--sweep`` and ``--fit-distortion`` too): run by
    jobs/cli/hil_star_command.py, imported when the command runs (the hil_star kind: Taichi)."""
    from dualsight.jobs.cli import hil_star_command

    return hil_star_command.run(args)
