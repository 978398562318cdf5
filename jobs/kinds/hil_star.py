"""Job kind ``hil_star``: the SIL star chain on real night-sky frames, scored against independent truth.

    read (scene.imageio; NaN and infinite pixels counted, ``nonfinite_pixels``, and replaced by the frame's
    finite median; fewer than 64 finite pixels: an error row) -> detect/centroid: local background, matched filter, hot pixels, saturation,
    PSF fit (kernels.detect_local; or smooth background (kernels.background) + kernels.detect: "global")
    -> back-project (nav.observations) -> lost-in-space geometric voting -> SVD attitude (nav.star_solution)
    -> boresight RA/Dec and roll (scene.pointing), per-star residuals (reference Table 6)
    -> errors against the truth (nav.hil_score) -> lake rows ``hil_star``, ``hil_star_stars``
    -> zero point, unknown objects and the ``--target`` (jobs/kinds/hil_star_objects.py) -> ``hil_star_objects``

No prior attitude is used: every frame is identified lost in space.  Detection, identification and
attitude are the simulated chain's own stages; this module adds what a real frame needs before them
(decoding, the ADC shift, a smooth background) and wires the scoring after them.

Engine contract (jobs/engine/runner.py): case i = image i of the spec's image list; one shard = a range of images;
``compute_shard`` gives one ``hil_star`` row per image (an image that cannot be read or changed since the run
was planned gives a row with ``error`` set and status ``error``) and one ``hil_star_stars`` row per
identified star.  Rows are a function of the spec alone (timing columns ``t_*_ns`` excepted).

Spec (``spec_from_dict``; JSON/TOML layout, pydantic strict)::

    camera   = {...}                  the [camera] table (scene/camera.py)
    settings = {method = "robust"|"paper", compare = true, background_block_px = 32 (0 = off, 4..4096),
                max_obs = 100 (2..1000), batch_size = 16 (1..1024), limit_arcsec = null | > 0,
                catalog = {mag_limit = 7.0, epoch_jyear}, detector = "local"|"global",
                detect_local = {k_sigma = 5, psf_sigma_px = null (measured), tile_px = 32, ...} (detector
                "local"), detect = {k_sigma = 5, min_pixels = 3, ...} (detector "global"),
                centroid_floor_px = 0.1 | null (attitude weights 1 / (sigma_px^2 + floor^2); null = equal),
                voting = {...}, alt_voting = {...} | null}     (the canonical form lists every field)
    images   = [{path (absolute), bytes, mtime_ns}, ...]      (jobs/kinds/hil_common.py)
    truths   = [] or one entry per image (jobs/kinds/hil_truth.py: source, A, ra_deg, dec_deg, matched, altaz_A, note)

Defaults, measured on the eight ESA tetra3 frames (tests/test_hil_star.py):
  * V <= 7.0: the frames' plate-solved stars reach V 7.3.  At V 6.5 the robust method still solves all
    eight (the paper method 7), at V 6.0 six; V 7.5 solves all eight too at 4x the voting time.
  * tolerance 20 arcsec: centroids are good to ~0.1-0.15 px (4-6 arcsec; 1 px = 40.3 arcsec), a pair
    angle to ~8 arcsec, so 20 arcsec is ~2.5 sigma; with 2.1M catalog pairs the paper method is
    confidently wrong on one frame at 30 arcsec and solves only 5 at 40, while the robust method solves
    all eight from 10 to 40 arcsec.
  * max_stars 25 brightest detections vote.  Detector "local" (default): 5 sigma on the matched-filtered
    SNR, 32 px tiles, PSF width measured per frame (0.64-0.70 px core on these frames), 9-21 hot pixels
    rejected per frame; against the global detector (5 sigma, 3 pixels after the 32 px background) the
    median truth residual per star drops from 7.1 to 6.7 arcsec and the median boresight error from 1.7
    to 1.2 arcsec (max 6.1 -> 6.4 arcsec on Alt40_Azi45, whose plate solution is itself the poorest).
  * centroid_floor_px 0.1: the per-star residuals (~0.16 px) are systematic, not photon noise; weights of
    the Cramér-Rao sigma_px alone (floor 0) give a median boresight error of 4 arcsec.
  * epoch: the CLI passes the images' date (scene.timescale.observation_epoch).

Voting methods: ``robust`` (default; VotingConfig.robust) or ``paper`` (VotingConfig.paper, the reference's
Kolomenkin voting); with ``compare`` the other method runs on the same detections and is reported beside it
(``alt_*`` columns).  Angles are stored in radians (``*_rad``); the report SQL (warehouse/sql/hil_star_*.sql)
converts to arcseconds.  Definitions of the scores: nav/hil_score.py.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from dualsight.kernels.taichi_runtime import ensure_init, is_initialised
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.catalogs.pair_cache import check_new_pair_catalog, load_pair_catalog
from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
from dualsight.errors import ImageError
from dualsight.config import validate
from dualsight.jobs.engine.specs import check_memory
from dualsight.jobs.kinds.hil_common import ImageEntry, check_unchanged, rows_table, spec_base
from dualsight.jobs.kinds.hil_star_spec import MAX_VOTE_CELLS, HilStarSpec, StarSettings, StarTruth
from dualsight.jobs.kinds import hil_star_spec
from dualsight.jobs.kinds.hil_star_objects import OBJECT_COLUMNS, OBJECTS_SCHEMA, ObjectContext, frame_objects, \
    object_context
from dualsight.jobs.kinds.hil_star_track import track_columns
from dualsight.jobs.kinds.star import catalog_bytes, pair_angle
from dualsight.kernels.detect import DetectConfig, detect_stars
from dualsight.kernels.detect_local import LocalDetectConfig, detect_real, subtract_local_background
from dualsight.nav import hil_score
from dualsight.nav.observations import observations
from dualsight.nav.pair_index import VotingIndex
from dualsight.nav.star_solution import centroid_weights, identify, solve
from dualsight.nav.voting_config import VotingConfig
from dualsight.scene.attitude import unit_to_radec
from dualsight.kernels.background import background_model, subtract_background
from dualsight.scene.camera import Camera
from dualsight.scene.imageio import read_image
from dualsight.scene.pointing import roll_deg
from dualsight.scene.units import angle_between

NAME = "hil_star"
PRIMARY = "hil_star"


# ============================================================================================ spec
def spec_from_dict(d: dict, source: str = "spec") -> HilStarSpec:
    """The job kind's spec reader (the engine, replay and the nightly call it by kind):
    :func:`dualsight.jobs.kinds.hil_star_spec.spec_from_dict`, where the spec's models live."""
    return hil_star_spec.spec_from_dict(d, source)


def build_spec(paths, camera: Camera | dict, settings: StarSettings | dict | None = None,
               truths: list[dict] | None = None) -> dict:
    """A spec dict for ``run_job("hil_star", ...)`` from image paths (stat now), a camera, settings and
    the per-image truths of :func:`dualsight.jobs.kinds.hil_truth.resolve_star_truths`."""
    return {**spec_base(paths, camera, settings), "truths": list(truths or [])}


# ============================================================================================ context
@dataclass(frozen=True)
class Runtime:
    """The spec's settings as the stages' config objects."""

    camera: Camera
    catalog: StarCatalogConfig
    detect: DetectConfig
    voting: VotingConfig
    alt_voting: VotingConfig | None
    settings: StarSettings


def runtime(spec: HilStarSpec) -> Runtime:
    """The spec's stage configs (:func:`runtime_of` its camera table and settings)."""
    return runtime_of(spec.camera, spec.settings)


def runtime_of(camera: dict, settings: StarSettings) -> Runtime:
    """The stage configs of a canonical camera table and settings
    (:func:`~dualsight.jobs.kinds.hil_star_spec.normalise_run`)."""
    s = settings
    return Runtime(camera=Camera.from_dict(camera, source="spec"),
                   catalog=validate(StarCatalogConfig, s.catalog, source="spec", section="settings.catalog"),
                   detect=validate(DetectConfig, s.detect, source="spec", section="settings.detect"),
                   voting=validate(VotingConfig, s.voting, source="spec", section="settings.voting"),
                   alt_voting=(validate(VotingConfig, s.alt_voting, source="spec", section="settings.alt_voting")
                               if s.alt_voting is not None else None),
                   settings=s)


@dataclass
class Context:
    """Per-process state: the stages' configs, the star catalog, its pair catalog and the pair catalog's voting
    index (``VotingIndex.load_or_build``: its derived arrays mapped from the cache)."""

    rt: Runtime
    catalog: object
    pairs: object
    index: object
    objects: ObjectContext | None = None
    """Unknown objects and the target (jobs/kinds/hil_star_objects.py); None: not computed."""


def make_context(spec: HilStarSpec) -> Context:
    ctx = context_of(runtime(spec), with_objects=False)
    target = None
    if spec.target is not None:                      # --target: the satellite's projected-area table
        from dualsight.jobs.kinds.hil_prox import ProxSettings, make_target     # pyarrow (the area table)

        target = make_target(spec.target, ProxSettings())
    ctx.objects = object_context(spec.settings, target, spec.target_near)
    return ctx


def context_of(rt: Runtime, with_objects: bool = True) -> Context:
    """The per-process state of stage configs ``rt``: the star catalog and its pair catalog (from the cache), and
    with ``with_objects`` the unknown objects' context (no target)."""
    cat = load_star_catalog(rt.catalog)
    pairs = load_pair_catalog(cat, pair_angle(rt.camera))
    return Context(rt, cat, pairs, VotingIndex.load_or_build(pairs),
                   object_context(rt.settings) if with_objects else None)


def check_pair_catalog(spec: HilStarSpec, source: str | None = None):
    """Before a run: refuse a spec whose pair catalog is not cached and whose estimated size or build time is
    over the bound (:func:`dualsight.catalogs.pair_cache.check_new_pair_catalog`: PairCatalogTooLarge, one line
    naming ``source``, the camera file); else its estimate (None when cached).  Writes nothing.  The engine's
    memory check (:func:`memory_estimate`) is made first, as the run would make it."""
    check_memory(memory_estimate(spec), source="hil star")
    rt = runtime(spec)
    return check_new_pair_catalog(load_star_catalog(rt.catalog, write=False), pair_angle(rt.camera), source=source)


FRAME_PLANES = 6
"""float32-sized planes per frame in flight: the decoded frame, the stacked batch, the background-subtracted
frame, the background grid and the detector's threshold mask and labels."""


def memory_estimate(spec: HilStarSpec) -> int:
    """Peak bytes of one worker, before anything is allocated (the engine refuses a spec over the limit):
    ``batch_size`` frames of the camera's size x :data:`FRAME_PLANES` float32 planes, the vote tables
    (:data:`~dualsight.jobs.kinds.hil_star_spec.MAX_VOTE_CELLS` int64 cells), and the star and pair catalogs
    for the magnitude limit and the field diagonal (:func:`dualsight.jobs.kinds.star.catalog_bytes`)."""
    cam = Camera.from_dict(spec.camera, source="spec")
    frames = FRAME_PLANES * 4 * cam.width * cam.height * spec.settings.batch_size
    return frames + 8 * MAX_VOTE_CELLS + catalog_bytes(float(spec.settings.catalog["mag_limit"]), pair_angle(cam))


# ============================================================================================ computing
@dataclass
class StarRow:
    """One identified star (reference Table 6 row)."""

    det_index: int
    x_px: float
    y_px: float
    flux: float
    npix: int
    sigma_px: float | None
    saturated: bool | None
    hip: int
    vmag: float
    ra_rad: float
    dec_rad: float
    pred_x_px: float
    pred_y_px: float
    residual_rad: float
    truth_residual_rad: float | None
    votes: int
    verify_votes: int
    truth_match: bool | None
    truth_id_agrees: bool | None


@dataclass
class ImageResult:
    """Everything computed for one image; ``row`` is its ``hil_star`` lake row (SI units)."""

    case_id: int
    row: dict
    stars: list[StarRow] = field(default_factory=list)
    detections: tuple | None = None
    """(xy (D, 2) px brightest first, sigma_px (D,) or None) of the frame's detections, for ``--track``."""
    objects: list[dict] = field(default_factory=list)
    """``hil_star_objects`` rows: the listed unknown objects and the target (jobs/kinds/hil_star_objects.py)."""


def read_frame(entry: ImageEntry, camera: Camera) -> tuple[np.ndarray, object]:
    """(ADC counts (H, W), Image) of an image entry, ready for detection: :func:`decode_frame`, then
    :func:`fill_nonfinite` (NaN and infinite pixels replaced by the frame's finite median); ImageError if it cannot
    be read, changed since the run was planned, is not the camera's size, or has fewer than
    :data:`MIN_FINITE_PIXELS` finite pixels."""
    px, img = decode_frame(entry, camera)
    return fill_nonfinite(px, nonfinite_pixels(px), source=entry.path), img


def decode_frame(entry: ImageEntry, camera: Camera) -> tuple[np.ndarray, object]:
    """(ADC counts (H, W) as decoded, non-finite pixels included, Image) of an image entry; ImageError if it
    cannot be read, changed since the run was planned, or is not the camera's size."""
    check_unchanged(entry)
    img = read_image(entry.path, as_gray=True)
    if (img.width, img.height) != (camera.width, camera.height):
        raise ImageError(f"is {img.width} x {img.height} px, the camera file says {camera.width} x "
                         f"{camera.height}", source=entry.path)
    return img.adc_counts(), img


MIN_FINITE_PIXELS = 64
"""Fewest finite pixels of a frame that is solved (:func:`fill_nonfinite`); fewer leave nothing to detect."""


def nonfinite_pixels(px: np.ndarray) -> int:
    """Pixels of a frame that are NaN or +/-infinite (0 for integer data, without looking at it)."""
    if px.dtype.kind != "f":
        return 0
    return px.size - int(np.count_nonzero(np.isfinite(px)))


def fill_nonfinite(px: np.ndarray, n_bad: int, *, source: str | None = None) -> np.ndarray:
    """The frame with its ``n_bad`` (:func:`nonfinite_pixels`) NaN and infinite pixels replaced by the median of
    its finite pixels, a background level that cannot make a detection; the frame itself (the same array, bit for
    bit) when there are none.  ImageError naming ``source`` when fewer than :data:`MIN_FINITE_PIXELS` are finite."""
    if n_bad == 0:
        return px
    total = px.size
    if total - n_bad < MIN_FINITE_PIXELS:
        what = (f"all {total:,} pixels are NaN or infinite" if n_bad == total else
                f"{n_bad:,} of {total:,} pixels are NaN or infinite, {total - n_bad} finite (fewer than "
                f"{MIN_FINITE_PIXELS}: nothing to detect)")
        raise ImageError(what, source=source)
    good = np.isfinite(px)
    out = px.copy()
    out[~good] = np.median(px[good])
    return out


def detect_frames(frames: np.ndarray, settings: StarSettings, detect: DetectConfig, *,
                  saturation_adu: float | None = None, residual: bool = True):
    """Background subtraction and detection of (B, H, W) frames: (residual frames (float32, None unless
    ``residual``), background levels (B,), Detections).

    ``settings.detector``: "local" (default) = :func:`dualsight.kernels.detect_local.detect_real` on the raw
    frames (tiled local background, matched filter, hot pixels, saturation at ``saturation_adu``, e.g. the
    camera's 2^bits - 1, PSF-fit centroids with their uncertainty); "global" = the smooth background
    (``background_block_px``, :func:`~dualsight.kernels.background.background_model`) then
    :func:`dualsight.kernels.detect.detect_stars` on the frames minus that background, evaluated per pixel
    inside the labeller (no residual frame is made unless asked for)."""
    if settings.detector == "local":
        cfg = validate(LocalDetectConfig, settings.detect_local, source="spec", section="settings.detect_local")
        det = detect_real(frames, cfg, saturation_adu=saturation_adu)
        resid = subtract_local_background(frames, cfg)[0] if residual else None
        return resid, det.background_adu, det
    if settings.background_block_px <= 0:                # no background: the frames themselves
        resid, bg = subtract_background(frames, settings.background_block_px)
        return (resid if residual else None), bg, detect_stars(resid, detect)
    model = background_model(frames, settings.background_block_px)
    det = detect_stars(frames, detect, background=model)
    return (model.subtract(frames) if residual else None), model.levels, det


def compute_shard(spec: HilStarSpec, case_ids: np.ndarray, ctx: Context) -> dict[str, pa.Table]:
    """The engine's contract: rows of images ``case_ids`` (int64, ascending), in batches of ``batch_size``."""
    ids = np.asarray(case_ids, np.int64)
    bs = spec.settings.batch_size
    results = []
    for s in range(0, len(ids), bs):
        results.extend(_run_batch([int(k) for k in ids[s:s + bs]], spec, ctx))
    if spec.track is not None:                        # hil star --track: the frames as one sequence
        cols = track_columns([r.case_id for r in results], [r.detections for r in results], spec.track, ctx,
                             engine=voting_engine(len(spec.images)))
        for r, c in zip(results, cols):
            r.row.update(c)
    return tables(results)


def base_row(case_id: int, image: str, path: str | None, rt: Runtime, truth: StarTruth) -> dict:
    """The ``hil_star`` row of one image before it is processed (status "error" until :func:`solve_frames`
    fills it): its case id, file name and path, the truth's source and the settings' summary columns."""
    st = rt.settings
    return {"case_id": case_id, "image": image, "path": path, "error": None, "status": "error",
            "method": st.method, "identified": False, "truth_source": truth.source, "truth_note": truth.note,
            "camera_fx_px": rt.camera.fx, "camera_width": rt.camera.width, "camera_height": rt.camera.height,
            "mag_limit": rt.catalog.mag_limit, "tolerance_rad": rt.voting.tolerance_rad,
            "max_stars": rt.voting.max_stars, "alt_method": st.alt_method}


TAICHI_VOTING_MIN_FRAMES = 1024
"""Images per CPU core from which a ``hil star`` process starts Taichi for its voting (:func:`voting_engine`)."""


def voting_engine(n_images: int = 0) -> str:
    """Engine of the voting (``nav.starid.identify``) for a run of ``n_images`` images: ``"taichi"`` when
    Taichi already runs in this process (the global detector starts it) or the run has at least
    :data:`TAICHI_VOTING_MIN_FRAMES` images per CPU core (then Taichi is started here), else ``"numpy"``.

    The two engines are bit-identical, so rows never depend on the choice, only the time does.  Measured on
    batches of 16 ESA frames at the defaults (one thread, 2-core VM): the robust method 1.70 ms per frame
    with numpy, 1.60 with the kernels; the reference method that ``--compare`` runs beside it 4.3-4.6 against
    2.4-2.5; starting Taichi and building the voting kernels from the offline cache ~1.1 s per process (the
    AST transform runs in every process).  So the kernels repay their start after ~500 frames in one
    process, with the comparison on; the threshold is twice that.  Images per core stands for images per
    worker: the local executor runs one worker per core by default (a Dask cluster's workers may each see
    fewer; the most a wrong guess costs is one start)."""
    if not is_initialised() and n_images >= TAICHI_VOTING_MIN_FRAMES * (os.cpu_count() or 1):
        ensure_init()
    return "taichi" if is_initialised() else "numpy"


def _run_batch(idx: list[int], spec: HilStarSpec, ctx: Context) -> list[ImageResult]:
    rt = ctx.rt
    results: dict[int, ImageResult] = {}
    good, frames, t_read = [], [], {}
    for k in idx:
        entry = spec.images[k]
        res = results[k] = ImageResult(k, base_row(k, entry.name, entry.path, rt, spec.truth(k)))
        t0 = time.perf_counter_ns()
        try:
            px, img = decode_frame(entry, rt.camera)
            n_bad = nonfinite_pixels(px)
            res.row.update(width=img.width, height=img.height, bit_depth=img.bit_depth, shift=img.shift,
                           image_digest=int(to_int64(frame_digest(px[None]))[0]), nonfinite_pixels=n_bad)
            px = fill_nonfinite(px, n_bad, source=entry.path)
        except ImageError as e:
            res.row["error"] = str(e)
            res.row["t_read_ns"] = time.perf_counter_ns() - t0
            continue
        t_read[k] = time.perf_counter_ns() - t0
        good.append(k)
        frames.append(px)
    if good:
        solve_frames(np.stack(frames), [results[k] for k in good], [spec.truth(k) for k in good], ctx,
                     n_images=len(spec.images), t_read_ns=[t_read[k] for k in good])
    return [results[k] for k in idx]


def solve_frames(frames: np.ndarray, results: list[ImageResult], truths: list[StarTruth], ctx: Context, *,
                 n_images: int | None = None, t_read_ns: list[int] | None = None) -> list[ImageResult]:
    """The chain of every ``hil_star`` image after decoding, on a batch: detection and centroids
    (:func:`detect_frames`), back-projection, lost-in-space voting, SVD attitude (and the comparison
    method when the settings ask for it), then the scores against ``truths``.

    frames : (B, H, W) ADC counts (uint8, uint16, float32 or float64; :func:`read_frame`'s), the camera's size.
    results : B results whose rows are :func:`base_row`'s; filled in place (row and identified stars) and returned.
    truths : B truths (``StarTruth()``: none).
    n_images : images of the whole run, for :func:`voting_engine` (default B).
    t_read_ns : B decoding times (ns) for the rows' ``t_read_ns`` and ``t_total_ns``, or None.
    """
    rt = ctx.rt
    B = len(results)
    t0 = time.perf_counter_ns()
    octx = ctx.objects
    need_residual = octx is not None and octx.target is not None       # a resolved target is measured on it
    resid, bg, det = detect_frames(np.asarray(frames), rt.settings, rt.detect,
                                   saturation_adu=float(2 ** rt.camera.bit_depth - 1), residual=need_residual)
    t1 = time.perf_counter_ns()
    cat_unit = ctx.catalog.unit
    obs = observations(det, B, rt.camera, max_obs=rt.settings.max_obs)
    engine = voting_engine(B if n_images is None else n_images)
    ident = identify(obs, cat_unit, ctx.index, rt.voting, cat_vmag=ctx.catalog.vmag, engine=engine)
    t2 = time.perf_counter_ns()
    floor = rt.settings.centroid_floor_px
    w = centroid_weights(det, obs, floor) if floor is not None else None
    sol = solve(obs, ident, cat_unit, None, weights=w)
    t3 = time.perf_counter_ns()
    alt = None
    if rt.alt_voting is not None:
        ident_a = identify(obs, cat_unit, ctx.index, rt.alt_voting, cat_vmag=ctx.catalog.vmag, engine=engine)
        alt = (ident_a, solve(obs, ident_a, cat_unit, None, weights=w))
    t4 = time.perf_counter_ns()
    share = {"t_detect_ns": (t1 - t0) // B, "t_identify_ns": (t2 - t1) // B, "t_attitude_ns": (t3 - t2) // B,
             "t_alt_ns": (t4 - t3) // B if alt is not None else 0}     # no reference method: no stage
    for b, res in enumerate(results):
        t_read = t_read_ns[b] if t_read_ns is not None else None
        res.row.update(share, t_read_ns=t_read, t_total_ns=(t_read or 0) + sum(share.values()),
                       background_adu=float(bg[b]))
        s0, s1 = int(det.offsets[b]), int(det.offsets[b + 1])
        sig = (np.hypot(det.sigma_px[s0:s1], floor) if det.sigma_px is not None and floor is not None else None)
        res.detections = (np.stack([det.x[s0:s1], det.y[s0:s1]], axis=1), sig)     # the attitude's weights
        _fill(res, b, det, obs, ident, sol, alt, truths[b], ctx)
        if octx is not None:
            res.objects = frame_objects(res, b, det, obs, ident, sol, cat_unit, rt.camera, rt.settings, octx,
                                        residual=resid[b] if resid is not None else None,
                                        frame=frames[b] if resid is not None else None)
    return results


MIN_IDENTIFIED_STARS = 3
"""Fewest identified stars for an image to count as identified (two give an attitude but no check)."""


def voters_in_round(n_valid: int, rnd: int, schedule) -> int:
    """Stars that voted in round ``rnd`` (the answer's round; 0 without an answer) of the voting schedule
    (``VotingConfig.widen_schedule``: valid-star ranks ``[start, stop)`` per round) for a frame of
    ``n_valid`` valid detections."""
    start, stop = schedule[rnd]
    return max(0, min(n_valid, stop) - start)


def _fill(res: ImageResult, b: int, det, obs, ident, sol, alt, truth: StarTruth, ctx: Context):
    """Per-image numbers and per-star rows from the batch's stage outputs."""
    cam, cat, rt = ctx.rt.camera, ctx.catalog, ctx.rt
    r = res.row
    n_det = int(det.counts[b])
    s0 = int(det.offsets[b])
    r["detector"] = rt.settings.detector
    for col, name in (("blobs_dropped", "blobs_dropped"), ("large_blobs", "large_blobs"), ("hot_pixels", "hot_pixels"),
                      ("saturated_stars", "n_saturated")):
        v = getattr(det, name, None)
        r[col] = int(v[b]) if v is not None else None
    for col, name in (("psf_sigma_px", "psf_sigma_px"), ("noise_adu", "noise_adu")):
        v = getattr(det, name, None)
        r[col] = float(v[b]) if v is not None else None
    r.update(stars_detected=n_det, threshold_adu=float(det.threshold_adu[b]),
             detect_background_adu=float(det.background_adu[b]),
             stars_used=voters_in_round(int(obs.valid[b].sum()), int(ident.answer_round[b]) if ident.T[b] > 0 else 0,
                                rt.voting.widen_schedule),
             T=int(ident.T[b]), stars_identified=int(ident.accepted[b].sum()),
             p_chance=float(ident.p_chance[b]) if np.isfinite(ident.p_chance[b]) else None)
    A_true = truth.matrix("A")
    matched = truth.matched.arrays() if truth.matched is not None else None
    # two stars fit any catalog pair at their separation: an answer needs a third star that checks it
    ok = bool(sol.ok[b]) and int(ident.T[b]) > 0 and int(ident.accepted[b].sum()) >= MIN_IDENTIFIED_STARS
    r["identified"] = ok
    A = sol.A_est[b]
    agrees = None
    if ok:
        ra, dec = unit_to_radec(A[2])
        r.update(ra_rad=float(ra), dec_rad=float(dec), roll_deg=float(roll_deg(A)), A_est=A.ravel().tolist())
        acc = np.flatnonzero(ident.accepted[b] & (ident.ids[b] >= 0))
        rows_ = ident.ids[b, acc].astype(np.int64)
        u = cat.unit[rows_]
        pred, _ = cam.project(u @ A.T)
        resid = sol.residual[b, acc]
        r.update(hil_score.residual_stats(resid))
        t_res = None
        if A_true is not None:
            t_res = angle_between(obs.vec[b, acc], u @ A_true.T)
            r["truth_residual_median_rad"] = float(np.median(t_res))
        tm, agree = hil_score.truth_star_checks(obs.x[b, acc], obs.y[b, acc], u, matched)
        for j, s in enumerate(acc):
            res.stars.append(StarRow(
                det_index=int(s), x_px=float(obs.x[b, s]), y_px=float(obs.y[b, s]),
                flux=float(det.flux[s0 + s]), npix=int(det.npix[s0 + s]),
                sigma_px=float(det.sigma_px[s0 + s]) if det.sigma_px is not None else None,
                saturated=bool(det.saturated[s0 + s]) if det.saturated is not None else None,
                hip=int(cat.hip[rows_[j]]),
                vmag=float(cat.vmag[rows_[j]]), ra_rad=float(cat.ra[rows_[j]]), dec_rad=float(cat.dec[rows_[j]]),
                pred_x_px=float(pred[j, 0]), pred_y_px=float(pred[j, 1]), residual_rad=float(resid[j]),
                truth_residual_rad=None if t_res is None else float(t_res[j]),
                votes=int(ident.votes[b, s]), verify_votes=int(ident.verify_votes[b, s]),
                truth_match=None if tm is None else bool(tm[j]),
                truth_id_agrees=None if agree is None else (bool(agree[j]) if tm[j] else None)))
        agrees = [s.truth_id_agrees for s in res.stars] if matched is not None else None
    if matched is not None:
        ours = np.array([[s.x_px, s.y_px] for s in res.stars]) if ok and res.stars else None
        r.update(hil_score.truth_star_counts(matched, ours, agrees))
    radec = (truth.ra_deg, truth.dec_deg) if truth.source == "file" and truth.ra_deg is not None else None
    r.update(hil_score.score_star_frame(A if ok else None, int(ident.T[b]), A_true, truth_source=truth.source,
                                        limit_arcsec=rt.settings.limit_arcsec, radec_true_deg=radec,
                                        altaz_A=truth.matrix("altaz_A")))
    if alt is not None:
        ident_a, sol_a = alt
        ok_a = bool(sol_a.ok[b]) and int(ident_a.T[b]) > 0 and int(ident_a.accepted[b].sum()) >= MIN_IDENTIFIED_STARS
        r.update(alt_identified=ok_a, alt_T=int(ident_a.T[b]), alt_stars_identified=int(ident_a.accepted[b].sum()),
                 alt_status=hil_score.score_star_frame(
                     sol_a.A_est[b] if ok_a else None, int(ident_a.T[b]), A_true, truth_source=truth.source,
                     limit_arcsec=rt.settings.limit_arcsec, radec_true_deg=radec,
                     altaz_A=truth.matrix("altaz_A"))["status"])
        if ok_a:
            ra_ = sol_a.residual[b][ident_a.accepted[b] & (ident_a.ids[b] >= 0)]
            r["alt_residual_median_rad"] = float(np.median(ra_)) if ra_.size else None
            if A_true is not None:
                r["alt_boresight_error_rad"] = float(angle_between(sol_a.A_est[b, 2], A_true[2]))


# ============================================================================================ tables
_MAT9 = pa.list_(pa.float64(), 9)
IMAGES_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("path", pa.string()), ("error", pa.string()),
    ("status", pa.string()), ("identified", pa.bool_()), ("method", pa.string()),
    ("width", pa.int32()), ("height", pa.int32()), ("bit_depth", pa.int32()), ("shift", pa.int32()),
    ("image_digest", pa.int64()), ("nonfinite_pixels", pa.int64()),
    ("background_adu", pa.float64()), ("detect_background_adu", pa.float64()), ("threshold_adu", pa.float64()),
    ("stars_detected", pa.int32()), ("stars_used", pa.int32()), ("stars_identified", pa.int32()), ("T", pa.int32()),
    ("p_chance", pa.float64()),
    ("detector", pa.string()), ("psf_sigma_px", pa.float64()), ("noise_adu", pa.float64()),
    ("blobs_dropped", pa.int32()), ("large_blobs", pa.int32()), ("hot_pixels", pa.int32()),
    ("saturated_stars", pa.int32()),
    ("ra_rad", pa.float64()), ("dec_rad", pa.float64()), ("roll_deg", pa.float64()), ("A_est", _MAT9),
    ("residual_median_rad", pa.float64()), ("residual_rms_rad", pa.float64()), ("residual_max_rad", pa.float64()),
    ("truth_source", pa.string()), ("truth_note", pa.string()), ("limit_arcsec", pa.float64()),
    ("ra_true_rad", pa.float64()), ("dec_true_rad", pa.float64()), ("roll_true_deg", pa.float64()),
    ("A_true", _MAT9),
    ("boresight_error_rad", pa.float64()), ("boresight_error_radec_rad", pa.float64()),
    ("attitude_error_rad", pa.float64()),
    ("err_x_rad", pa.float64()), ("err_y_rad", pa.float64()), ("err_z_rad", pa.float64()),
    ("truth_residual_median_rad", pa.float64()),
    ("truth_stars", pa.int32()), ("truth_stars_found", pa.int32()), ("truth_ids_agree", pa.int32()),
    ("truth_ids_disagree", pa.int32()),
    ("altaz_ra_rad", pa.float64()), ("altaz_dec_rad", pa.float64()), ("altaz_error_rad", pa.float64()),
    ("alt_method", pa.string()), ("alt_status", pa.string()), ("alt_identified", pa.bool_()), ("alt_T", pa.int32()),
    ("alt_stars_identified", pa.int32()), ("alt_boresight_error_rad", pa.float64()),
    ("alt_residual_median_rad", pa.float64()),
    ("camera_fx_px", pa.float64()), ("camera_width", pa.int32()), ("camera_height", pa.int32()),
    ("mag_limit", pa.float64()), ("tolerance_rad", pa.float64()), ("max_stars", pa.int32()),
    ("t_read_ns", pa.int64()), ("t_detect_ns", pa.int64()), ("t_identify_ns", pa.int64()),
    ("t_attitude_ns", pa.int64()), ("t_alt_ns", pa.int64()), ("t_total_ns", pa.int64()),
    # --track only (jobs/kinds/hil_star_track.py), null otherwise
    ("time_utc", pa.string()), ("time_source", pa.string()), ("track_mode", pa.string()),
    ("track_reason", pa.string()), ("track_stars", pa.int32()), ("track_A", _MAT9),
    ("rate_rad_s", pa.list_(pa.float64(), 3)), ("rate_cov", _MAT9), ("rate_source", pa.string()),
    # unknown objects and --target (jobs/kinds/hil_star_objects.py)
    *OBJECT_COLUMNS,
])

STARS_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("det_index", pa.int32()),
    ("x_px", pa.float64()), ("y_px", pa.float64()), ("flux", pa.float64()), ("npix", pa.int32()),
    ("sigma_px", pa.float64()), ("saturated", pa.bool_()),
    ("hip", pa.int32()), ("vmag", pa.float64()), ("ra_rad", pa.float64()), ("dec_rad", pa.float64()),
    ("pred_x_px", pa.float64()), ("pred_y_px", pa.float64()), ("residual_rad", pa.float64()),
    ("truth_residual_rad", pa.float64()), ("votes", pa.int32()), ("verify_votes", pa.int32()),
    ("truth_match", pa.bool_()), ("truth_id_agrees", pa.bool_()), ("method", pa.string()),
])

SCHEMAS = {"hil_star": IMAGES_SCHEMA, "hil_star_stars": STARS_SCHEMA, "hil_star_objects": OBJECTS_SCHEMA}
TIMING_COLUMNS = ("t_read_ns", "t_detect_ns", "t_identify_ns", "t_attitude_ns", "t_alt_ns", "t_total_ns")


def tables(results: list[ImageResult]) -> dict[str, pa.Table]:
    """The ``hil_star``, ``hil_star_stars`` and ``hil_star_objects`` tables of some images."""
    stars = [{**vars(s), "case_id": r.row["case_id"], "image": r.row["image"], "method": r.row["method"]}
             for r in results for s in r.stars]
    return {"hil_star": rows_table([r.row for r in results], IMAGES_SCHEMA),
            "hil_star_stars": rows_table(stars, STARS_SCHEMA),
            "hil_star_objects": rows_table([o for r in results for o in r.objects], OBJECTS_SCHEMA)}


def shard_summary(tbls: dict[str, pa.Table]) -> dict[str, int]:
    """Counts summed into the manifest's stats."""
    t = tbls["hil_star"]
    status = t.column("status").to_pylist()
    return {"images": t.num_rows, "identified": sum(bool(x) for x in t.column("identified").to_pylist()),
            "success": status.count("success"), "errors": sum(e is not None for e in t.column("error").to_pylist())}


def progress_postfix(stats: dict) -> str:
    return f"identified {stats.get('identified', 0)}, errors {stats.get('errors', 0)}"


__all__ = ["NAME", "PRIMARY", "SCHEMAS", "build_spec", "make_context", "memory_estimate", "compute_shard",
           "shard_summary", "progress_postfix", "read_frame", "decode_frame", "nonfinite_pixels",
           "fill_nonfinite", "MIN_FINITE_PIXELS", "detect_frames", "runtime", "tables",
           "runtime_of", "context_of", "base_row", "solve_frames", "Runtime", "Context", "ImageResult", "StarRow"]
