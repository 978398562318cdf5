"""Star-tracker hardware-in-the-loop: the SIL star chain on real night-sky frames, scored against truth.

    read (scene.imageio) -> smooth-background subtraction -> detect/centroid (kernels.detect.detect_stars)
    -> back-project -> lost-in-space geometric voting (nav.starid.identify) -> SVD attitude (nav.attitude)
    -> boresight RA/Dec and roll, per-star residuals (reference Table 6) -> errors against the truth
    -> lake rows (``hil_star``, ``hil_star_stars``), text/JSON, overlay pictures (reference Figure 11)

Detection, identification and attitude are the simulated chain's own stages
(:mod:`dualsight.jobs.star_pipeline`: ``observations``, ``identify``, ``solve``); this module only adds
what a real frame needs before them (decoding, the ADC shift, a smooth background) and the scoring
after them.  No prior attitude is used: every frame is identified lost in space.

Real frames versus simulated ones
    A night-sky frame has a sky background that varies over the field (vignetting, sky glow: 103-182 ADU
    across one ESA frame against a pixel noise of ~8 ADU), so a single global threshold either misses
    faint stars or floods the bright corners.  :func:`subtract_background` removes a smooth background
    first: the median of every ``background_block_px`` square block, interpolated bilinearly between
    block centres.  ``detect_stars`` then thresholds the residual at ``k_sigma`` times its robust noise
    sigma; ``min_pixels`` (3) drops hot pixels, which are single pixels (or pairs) while a star's
    slightly defocused image covers 3-50 pixels.

Truth (optional, per image), scored by :func:`score`
    * a truth file in the format of ``shared/data/real/esa_tetra3/truth.json``
      (:func:`dualsight.scene.skytruth.load_truth_json`), keyed by image file name: the truth attitude is
      its ``R_icrs_to_cam``; its ``matched`` stars are compared with ours;
    * or the reference's tripod test: UTC time, site latitude/longitude/height and the mount's altitude,
      azimuth (and roll) through astropy (:func:`dualsight.scene.skytruth.attitude_from_altaz`); time,
      altitude and azimuth default to the ones in the file name (``2019-07-29T204726_Alt40_Azi-135``).
      A nominal mount pointing is good to about a degree only, so the status limit defaults to 2 deg
      for this source (100 arcsec, the reference's, for a truth file).
    With both, the truth file is the truth and the alt/az pointing is reported beside it (``altaz_*``).

Definitions (all angles between unit vectors, ``scene.attitude.angle_between``)
    boresight error   angle between the solved camera +z axis (third row of A_est) and the truth's
                      (third row of the truth matrix); ``boresight_error_radec`` uses the truth file's
                      ``ra_deg``/``dec_deg`` instead (they differ from R's third row by up to 63 arcsec
                      on the poorly solved ESA frame).
    residual          per identified star, angle between its observed unit vector and A_est times its
                      catalog unit vector (the reference's "predicted versus observed", Table 6);
                      ``truth_residual`` uses the truth matrix instead of A_est.
    roll              position angle of the image's "up" direction (camera -y, decreasing row) at the
                      boresight, measured from celestial north through east, in [0, 360) deg.  The
                      image is not mirrored, so with roll 0 north is up and east is to the left.
    attitude error    rotation angle of A_true A_est^T; ``err_x/y/z`` the reference's Eqs. 4-7 about the
                      camera axes (x, y across the boresight, z = roll), as the SIL job's "camera" frame.
    identified        the voting gave a confident solution (T > 0) and the attitude was solved.
    status            with truth: success (every axis error <= the limit), confident_wrong (failed,
                      T > 0), no_solution (T <= 0), as ``nav.errors.classify``; without truth:
                      identified / no_solution; a frame that could not be processed: error.

Voting methods: ``robust`` (default; :meth:`VotingConfig.robust`: unique maxima, consistent-set
acceptance, attitude check and re-identification of every detected star) or ``paper``
(:meth:`VotingConfig.paper`, the reference's Kolomenkin voting); the other method runs on the same
detections and is reported beside it (``alt_*``), as the SIL job's ``*_robust`` columns.

Lake (``warehouse.lake``): ``hil_star`` one row per image (bad images too, with ``error`` set),
``hil_star_stars`` one row per identified star; one shard (0) per run, written atomically, with a
manifest of kind ``hil_star``.  Angles are stored in radians (``*_rad``, DESIGN.md); the report SQL
(``warehouse/sql/hil_star_*.sql``) converts to arcseconds.
"""

from __future__ import annotations

import math
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pyarrow as pa

from dualsight.catalogs.pairs import load_pair_catalog
from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
from dualsight.errors import ConfigError, ImageError, InputError
from dualsight.jobs import star_pipeline as pipe
from dualsight.kernels.detect import DetectConfig, detect_stars
from dualsight.nav.errors import STATUS_NAMES, axis_errors, classify, total_error_angle
from dualsight.nav.starid import VotingConfig
from dualsight.scene.attitude import angle_between, radec_to_unit, unit_to_radec
from dualsight.scene.camera import Camera
from dualsight.scene.imageio import list_images, read_image

NAME = "hil_star"
DATASETS = ["hil_star", "hil_star_stars"]
PRIMARY = "hil_star"

ARCSEC = math.pi / (180.0 * 3600.0)
METHODS = ("robust", "paper")
TRUTH_MATCH_PX = 2.0
"""A truth-file matched star is "the same detection" as ours when the centroids are within 2 px."""
TRUTH_ID_ARCSEC = 60.0
"""...and "the same star" when its catalog position is within 60 arcsec of ours (catalog and epoch
differences are a few arcsec; the nearest other V <= 7.5 star is usually tens of arcmin away)."""
ALTAZ_LIMIT_ARCSEC = 7200.0
"""Default status limit against an alt/az (tripod) truth: a nominal mount pointing is good to ~1 deg."""


# ============================================================================================ settings
@dataclass(frozen=True)
class HilStarSettings:
    """Everything that decides a HIL star run (recorded in the manifest).

    catalog : star catalog (Hipparcos to ``mag_limit``).  The ESA frames (11.4 deg field) show stars
        to V ~7.3; V 7.0 gives 15.6k stars and 2.1M pairs within the 14.25 deg diagonal (cached).
    detect : :class:`DetectConfig` applied to the background-subtracted frame.
    method : "robust" or "paper"; ``voting`` is that method's :class:`VotingConfig`.
    compare : also run the other method on the same detections (``alt_*`` columns).
    alt_voting : the other method's :class:`VotingConfig` (None when ``compare`` is off).
    background_block_px : block size (px) of the smooth background; 0 = none (detect_stars' own global
        median background).
    max_obs : brightest detections back-projected per frame (voting uses ``voting.max_stars`` of them;
        the robust method's re-identification may identify all of them).
    batch_size : frames per detection/identification batch.
    limit_arcsec : status limit per axis; None = 100 arcsec (truth file) or 7200 arcsec (alt/az truth).
    """

    catalog: StarCatalogConfig
    detect: DetectConfig
    method: str
    voting: VotingConfig
    compare: bool = True
    alt_voting: VotingConfig | None = None
    background_block_px: int = 32
    max_obs: int = 100
    batch_size: int = 16
    limit_arcsec: float | None = None

    def to_dict(self) -> dict:
        from dualsight.jobs.config import dataclass_to_table

        return {"catalog": dataclass_to_table(self.catalog), "detect": dataclass_to_table(self.detect),
                "method": self.method, "voting": dataclass_to_table(self.voting), "compare": self.compare,
                "alt_method": self.alt_method,
                "alt_voting": dataclass_to_table(self.alt_voting) if self.alt_voting is not None else None,
                "background_block_px": self.background_block_px, "max_obs": self.max_obs,
                "batch_size": self.batch_size, "limit_arcsec": self.limit_arcsec}

    @property
    def alt_method(self) -> str | None:
        return None if not self.compare else next(m for m in METHODS if m != self.method)


def make_settings(*, method: str = "robust", mag_limit: float = 7.0, epoch_jyear: float = 2000.0,
                  tolerance_arcsec: float = 20.0, max_stars: int = 25, k_sigma: float = 5.0, min_pixels: int = 3,
                  background_block_px: int = 32, max_obs: int = 100, compare: bool = True,
                  batch_size: int = 16, limit_arcsec: float | None = None, config: dict | None = None,
                  source: str = "hil star") -> HilStarSettings:
    """Validated settings from flags and an optional TOML dict (tables ``catalog``, ``detect``, ``voting``,
    ``alt_voting`` and top-level ``method``, ``background_block_px``, ``max_obs``, ``compare``); the
    TOML values override the flags' defaults.

    Defaults, measured on the eight ESA tetra3 frames (see tests/test_hil_star.py):
      * V <= 7.0: the frames' plate-solved stars reach V 7.3.  At V 6.5 the robust method still solves all
        eight (the paper method 7), at V 6.0 six; V 7.5 solves all eight too at 4x the voting time.
      * tolerance 20 arcsec: centroids are good to ~0.1-0.15 px (4-6 arcsec; 1 px = 40.3 arcsec), a pair
        angle to ~8 arcsec, so 20 arcsec is ~2.5 sigma (10-15 arcsec work as well); with 2.1M catalog pairs
        the paper method is confidently wrong on one frame at 30 arcsec and solves only 5 at 40, while
        the robust method solves all eight from 10 to 40 arcsec.
      * max_stars 25 brightest detections vote; 5 sigma and 3 pixels separate stars from noise and
        hot pixels after the 32 px background.
      * epoch: the CLI passes the images' date (:func:`observation_epoch`); J2000 positions put HIP 114622
        50 arcsec from where it was in 2019, outside the re-identification radius.
    """
    from dualsight.jobs.config import dataclass_from_table

    cfg = dict(config or {})
    allowed = {"method", "catalog", "detect", "voting", "alt_voting", "compare", "background_block_px",
               "max_obs", "batch_size", "limit_arcsec"}
    unknown = sorted(set(cfg) - allowed)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown}; allowed: {sorted(allowed)}", source=source)
    method = cfg.get("method", method)
    if method not in METHODS:
        raise ConfigError(f"must be one of {list(METHODS)}, got {method!r}", source=source, field="method")
    catalog = dataclass_from_table(StarCatalogConfig, cfg.get("catalog"), source=source, section="catalog",
                                   base=StarCatalogConfig(mag_limit=mag_limit, epoch_jyear=epoch_jyear))
    detect = dataclass_from_table(DetectConfig, cfg.get("detect"), source=source, section="detect",
                                  base=_checked(DetectConfig, source, "detect", k_sigma=k_sigma,
                                                min_pixels=min_pixels))
    tol = float(tolerance_arcsec) * ARCSEC
    # 4M int64 cells = 32 MB per vote table chunk: with 15.6k catalog stars x 25 voters that is ten frames
    # at a time, and 1M candidate pairs per expansion (the default 250k would vote one frame at a time).
    common = dict(max_stars=max_stars, max_vote_cells=4_000_000)
    bases = {"robust": lambda: VotingConfig.robust(tol, **common), "paper": lambda: VotingConfig.paper(tol, **common)}
    try:
        base = bases[method]()
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e), source=source, field="voting") from None
    voting = dataclass_from_table(VotingConfig, cfg.get("voting"), source=source, section="voting", base=base)
    compare = cfg.get("compare", compare)
    if not isinstance(compare, bool):
        raise ConfigError(f"must be true or false, got {compare!r}", source=source, field="compare")
    alt = None
    if compare:
        other = next(m for m in METHODS if m != method)
        alt_base = {"robust": VotingConfig.robust, "paper": VotingConfig.paper}[other](voting.tolerance_rad,
                                                                                      **common)
        alt = dataclass_from_table(VotingConfig, cfg.get("alt_voting"), source=source, section="alt_voting",
                                   base=alt_base)
    block = cfg.get("background_block_px", background_block_px)
    if isinstance(block, bool) or not isinstance(block, int) or not (block == 0 or 4 <= block <= 4096):
        raise ConfigError(f"must be 0 (off) or an integer in [4, 4096], got {block!r}", source=source,
                          field="background_block_px")
    max_obs = cfg.get("max_obs", max_obs)
    if isinstance(max_obs, bool) or not isinstance(max_obs, int) or not 2 <= max_obs <= 1000:
        raise ConfigError(f"must be an integer in [2, 1000], got {max_obs!r}", source=source, field="max_obs")
    bs = cfg.get("batch_size", batch_size)
    if isinstance(bs, bool) or not isinstance(bs, int) or not 1 <= bs <= 1024:
        raise ConfigError(f"must be an integer in [1, 1024], got {bs!r}", source=source, field="batch_size")
    lim = cfg.get("limit_arcsec", limit_arcsec)
    if lim is not None and (isinstance(lim, bool) or not isinstance(lim, (int, float)) or not lim > 0
                            or not math.isfinite(lim)):
        raise ConfigError(f"must be a number > 0 (arcsec), got {lim!r}", source=source, field="limit_arcsec")
    return HilStarSettings(catalog=catalog, detect=detect, method=method, voting=voting, compare=compare,
                           alt_voting=alt, background_block_px=int(block), max_obs=int(max_obs),
                           batch_size=int(bs), limit_arcsec=None if lim is None else float(lim))


def _checked(cls, source, section, **kw):
    try:
        return cls(**kw)
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e), source=source, field=section) from None


# ============================================================================================ truth inputs
@dataclass(frozen=True)
class Site:
    """The tripod test's inputs: site, and optionally one time / mount pointing for every image
    (None = take it from each file name, ``scene.skytruth.altaz_from_filename``)."""

    lat_deg: float
    lon_deg: float
    height_m: float = 0.0
    time_utc: str | None = None
    alt_deg: float | None = None
    az_deg: float | None = None
    roll_deg: float = 0.0
    pressure_hpa: float = 0.0

    def __post_init__(self):
        for name, lo, hi in (("lat_deg", -90.0, 90.0), ("lon_deg", -360.0, 360.0), ("height_m", -500.0, 1e5),
                             ("alt_deg", -89.99, 90.0), ("az_deg", -360.0, 720.0), ("roll_deg", -360.0, 360.0),
                             ("pressure_hpa", 0.0, 1100.0)):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                flag = "--" + name.rsplit("_", 1)[0].replace("_", "-")
                raise InputError(f"must be a number in [{lo:g}, {hi:g}], got {v!r}", source=flag)


@dataclass
class Truth:
    """Truth of one image: attitude (ICRS -> camera), its source, and the truth file's entry if any."""

    A: np.ndarray | None = None
    source: str = "none"
    entry: dict | None = None
    altaz_A: np.ndarray | None = None
    note: str | None = None


def resolve_truths(paths: list[Path], truth_file: dict | None, site: Site | None) -> list[Truth]:
    """Truth of every image (see the module docstring); the alt/az attitudes in one astropy call."""
    out = [Truth() for _ in paths]
    if truth_file is not None:
        for t, p in zip(out, paths):
            e = truth_file.get(Path(p).name)
            if e is not None:
                t.A, t.source, t.entry = np.asarray(e["R_icrs_to_cam"], np.float64), "file", e
            else:
                t.note = "not in the truth file"
    if site is not None:
        from dualsight.scene.skytruth import altaz_from_filename, attitude_from_altaz

        want, times, alts, azs = [], [], [], []
        for k, p in enumerate(paths):
            t_, a_, z_ = site.time_utc, site.alt_deg, site.az_deg
            if t_ is None or a_ is None or z_ is None:
                try:
                    ft, fa, fz = altaz_from_filename(p)
                except ConfigError:
                    out[k].note = ("no --time/--alt/--az given and the file name carries no "
                                   "'YYYY-MM-DDTHHMMSS..._Alt<deg>_Azi<deg>'")
                    continue
                t_ = ft if t_ is None else t_
                a_ = fa if a_ is None else a_
                z_ = fz if z_ is None else z_
            want.append(k)
            times.append(t_)
            alts.append(a_)
            azs.append(z_)
        if want:
            try:
                A = attitude_from_altaz(times, site.lat_deg, site.lon_deg, site.height_m, np.asarray(alts),
                                        np.asarray(azs), site.roll_deg, pressure_hpa=site.pressure_hpa)
            except (ValueError, TypeError) as e:   # astropy rejects a malformed time string
                raise InputError(f"cannot compute the alt/az truth: {e}", source="--time") from None
            for k, a in zip(want, np.asarray(A).reshape(-1, 3, 3)):
                out[k].altaz_A = a
                if out[k].A is None:
                    out[k].A, out[k].source, out[k].note = a, "altaz", None
    return out


def julian_year(time_utc: str) -> float:
    """Julian epoch (J2000.0 + days / 365.25) of an ISO UTC time such as "2019-07-29T20:47:26" (UTC ~ TT
    to a minute, immaterial for proper motion)."""
    from datetime import datetime, timezone

    try:
        t = datetime.fromisoformat(str(time_utc).replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"not an ISO time (YYYY-MM-DDTHH:MM:SS): {time_utc!r}", source="--time") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    jd = t.timestamp() / 86400.0 + 2440587.5
    return 2000.0 + (jd - 2451545.0) / 365.25


def observation_epoch(paths, time_utc: str | None = None) -> float | None:
    """Catalog epoch for a set of images: the Julian year of ``time_utc`` if given, else the median
    of the times in the file names (``scene.skytruth.altaz_from_filename``) when every name has one;
    rounded to 0.1 yr (proper motions reach ~1 arcsec/yr for a few V < 7 stars, so 0.05 yr is
    negligible, and the catalog cache is reused).  None when the time is unknown.

    Why it matters: HIP 114622 (V 5.5) moves 50 arcsec between J2000 and the ESA frames (2019.6), more
    than the 40 arcsec re-identification radius.
    """
    from dualsight.scene.skytruth import altaz_from_filename

    if time_utc is not None:
        return round(julian_year(time_utc), 1)
    years = []
    for p in paths:
        try:
            years.append(julian_year(altaz_from_filename(p)[0]))
        except (ConfigError, InputError):
            return None
    return round(float(np.median(years)), 1) if years else None


# ============================================================================================ image prep
def subtract_background(frames: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Remove a smooth sky background from (B, H, W) frames.

    The background is the median of every ``block`` x ``block`` pixel square (a frame whose size is not
    a multiple of ``block`` is first extended by mirroring its last rows/columns, so edge blocks are
    full), interpolated bilinearly between the block centres (OpenCV ``resize``, whose half-pixel
    convention puts each block's value at its centre) and held constant beyond the outer centres.
    Stars cover a few pixels of a block of 1024, so they do not move its median.  Cost ~3 ms per
    1024 x 768 frame (one partial sort per block).

    Returns (residual float32 (B, H, W), median background level per frame (B,)).
    """
    import cv2

    f = np.asarray(frames, dtype=np.float32)
    B, H, W = f.shape
    if block <= 0:
        return f, np.median(f.reshape(B, -1), axis=1)
    nby, nbx = -(-H // block), -(-W // block)
    ext = f
    if (nby * block, nbx * block) != (H, W):
        ext = np.pad(f, ((0, 0), (0, nby * block - H), (0, nbx * block - W)), mode="symmetric")
    blocks = np.ascontiguousarray(ext.reshape(B, nby, block, nbx, block).transpose(0, 1, 3, 2, 4))
    blocks = blocks.reshape(B, nby, nbx, block * block)
    n = block * block
    hi = n // 2
    part = np.partition(blocks, hi, axis=-1)                                     # one kth: ~5x faster
    upper = part[..., hi]
    med = (upper if n % 2 else 0.5 * (part[..., :hi].max(axis=-1) + upper)).astype(np.float32)  # (B, nby, nbx)
    out = np.empty_like(f)
    for b in range(B):                                                           # one resize per frame
        bg = cv2.resize(med[b], (nbx * block, nby * block), interpolation=cv2.INTER_LINEAR)[:H, :W]
        out[b] = f[b] - bg
    return out, np.median(med.reshape(B, -1), axis=1)


def roll_deg(A: np.ndarray) -> np.ndarray:
    """Roll (deg, [0, 360)) of (..., 3, 3) ICRS -> camera matrices: position angle of the image's "up"
    (camera -y) at the boresight, from celestial north through east (module docstring)."""
    A = np.asarray(A, dtype=np.float64)
    z = A[..., 2, :]
    up = -A[..., 1, :]
    east = np.cross(np.array([0.0, 0.0, 1.0]), z)
    east /= np.linalg.norm(east, axis=-1, keepdims=True)
    north = np.cross(z, east)
    return np.mod(np.degrees(np.arctan2(np.sum(up * east, -1), np.sum(up * north, -1))), 360.0)


# ============================================================================================ results
@dataclass
class StarRow:
    """One identified star (reference Table 6 row)."""

    det_index: int
    x_px: float
    y_px: float
    flux: float
    npix: int
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

    index: int
    path: Path
    row: dict
    stars: list[StarRow] = field(default_factory=list)
    pixels: np.ndarray | None = None          # (H, W) background-subtracted frame, kept for the overlay
    det_xy: np.ndarray | None = None          # (K, 2) all detections, brightest first
    field_xy: np.ndarray | None = None        # (M, 2) catalog stars in the field, projected with A_est
    field_vmag: np.ndarray | None = None
    truth_xy: np.ndarray | None = None        # (G, 2) truth file's matched centroids


@dataclass
class Context:
    """Catalogs and camera of a run (loaded once)."""

    camera: Camera
    settings: HilStarSettings
    catalog: object
    pairs: object


def make_context(camera: Camera, settings: HilStarSettings) -> Context:
    cat = load_star_catalog(settings.catalog)
    pairs = load_pair_catalog(cat, camera.fov_rad[2])
    return Context(camera, settings, cat, pairs)


def expand_inputs(items) -> list[Path]:
    """Image paths; a folder argument expands to its images (natural order).  Missing files are kept
    (they become error rows)."""
    out = []
    for it in items:
        p = Path(it)
        if p.is_dir():
            out.extend(list_images(p))
        else:
            out.append(p)
    return out


def run(paths, ctx: Context, *, truths: list[Truth] | None = None, overlay_dir: Path | None = None,
        credit: str | None = None, log: Callable[[str], None] | None = None) -> list[ImageResult]:
    """Process every image (in batches of ``settings.batch_size``); a bad image gives an error row.

    With ``overlay_dir``, each batch's Figure-11 pictures are drawn as soon as the batch is done (so only
    one batch of frames is ever held in memory); ``credit`` as :func:`write_overlays`.
    """
    paths = [Path(p) for p in paths]
    truths = truths if truths is not None else [Truth() for _ in paths]
    log = log or (lambda m: print(m, file=sys.stderr))
    results = []
    bs = ctx.settings.batch_size
    for s in range(0, len(paths), bs):
        batch = _run_batch(list(range(s, min(len(paths), s + bs))), paths, truths, ctx, overlay_dir is not None,
                           log)
        if overlay_dir is not None:
            write_overlays(batch, overlay_dir, credit=credit)
            for r in batch:
                r.pixels = None
        results.extend(batch)
    return results


def _base_row(index: int, path: Path, ctx: Context, truth: Truth) -> dict:
    st = ctx.settings
    return {"image": path.name, "path": str(path), "image_index": index, "error": None, "status": "error",
            "method": st.method, "identified": False, "truth_source": truth.source,
            "camera_fx_px": ctx.camera.fx, "camera_width": ctx.camera.width, "camera_height": ctx.camera.height,
            "mag_limit": st.catalog.mag_limit, "tolerance_rad": st.voting.tolerance_rad,
            "max_stars": st.voting.max_stars, "alt_method": st.alt_method}


def _run_batch(idx, paths, truths, ctx: Context, keep_pixels, log) -> list[ImageResult]:
    cam, st = ctx.camera, ctx.settings
    results: dict[int, ImageResult] = {}
    good, frames, t_read = [], [], {}
    for k in idx:
        p = paths[k]
        res = ImageResult(k, p, _base_row(k, p, ctx, truths[k]))
        results[k] = res
        t0 = time.perf_counter_ns()
        try:
            img = read_image(p, as_gray=True)
            if (img.width, img.height) != (cam.width, cam.height):
                raise ImageError(f"is {img.width} x {img.height} px, the camera file says {cam.width} x "
                                 f"{cam.height}", source=str(p))
            px = img.adc_counts()
        except ImageError as e:
            res.row["error"] = str(e)
            res.row["t_read_ns"] = time.perf_counter_ns() - t0
            log(f"dualsight: {e}; skipped, the other images go on")
            continue
        t_read[k] = time.perf_counter_ns() - t0
        res.row.update(width=img.width, height=img.height, bit_depth=img.bit_depth, shift=img.shift)
        good.append(k)
        frames.append(px)
    if not good:
        return [results[k] for k in idx]

    B = len(good)
    t0 = time.perf_counter_ns()
    resid, bg = subtract_background(np.stack(frames), st.background_block_px)
    det = detect_stars(resid, st.detect)
    t1 = time.perf_counter_ns()
    obs = pipe.observations(det, B, cam, max_obs=st.max_obs)
    ident = pipe.identify(obs, ctx.catalog, ctx.pairs, st.voting)
    t2 = time.perf_counter_ns()
    sol = pipe.solve(obs, ident, ctx.catalog, None)
    t3 = time.perf_counter_ns()
    alt = None
    if st.alt_voting is not None:
        ident_a = pipe.identify(obs, ctx.catalog, ctx.pairs, st.alt_voting)
        alt = (ident_a, pipe.solve(obs, ident_a, ctx.catalog, None))
    t4 = time.perf_counter_ns()
    share = {"t_detect_ns": (t1 - t0) // B, "t_identify_ns": (t2 - t1) // B, "t_attitude_ns": (t3 - t2) // B,
             "t_alt_ns": (t4 - t3) // B}

    for b, k in enumerate(good):
        res = results[k]
        if keep_pixels:
            res.pixels = resid[b]        # background-subtracted frame: what the detector saw
        res.row.update(share)
        res.row["t_read_ns"] = t_read[k]
        res.row["t_total_ns"] = t_read[k] + sum(share.values())
        res.row["background_adu"] = float(bg[b])
        _fill(res, b, det, obs, ident, sol, alt, truths[k], ctx)
    return [results[k] for k in idx]


def _fill(res: ImageResult, b: int, det, obs, ident, sol, alt, truth: Truth, ctx: Context):
    """Per-image numbers, per-star rows and overlay arrays from the batch's stage outputs."""
    cam, cat, st = ctx.camera, ctx.catalog, ctx.settings
    r = res.row
    n_det = int(det.counts[b])
    s0 = int(det.offsets[b])
    r.update(stars_detected=n_det, threshold_adu=float(det.threshold_adu[b]),
             detect_background_adu=float(det.background_adu[b]),
             stars_used=int(min(obs.valid[b].sum(), st.voting.max_stars)),
             T=int(ident.T[b]), stars_identified=int(ident.accepted[b].sum()))
    res.det_xy = np.stack([det.x[s0:s0 + n_det], det.y[s0:s0 + n_det]], axis=1)
    if truth.entry is not None:
        m = truth.entry["matched"]
        res.truth_xy = np.stack([m["col"], m["row"]], axis=1)

    ok = bool(sol.ok[b]) and int(ident.T[b]) > 0
    r["identified"] = ok
    A = sol.A_est[b]
    if ok:
        ra, dec = unit_to_radec(A[2])
        r.update(ra_rad=float(ra), dec_rad=float(dec), roll_deg=float(roll_deg(A)), A_est=A.ravel().tolist())
        acc = np.flatnonzero(ident.accepted[b] & (ident.ids[b] >= 0))
        rows_ = ident.ids[b, acc].astype(np.int64)
        u = cat.unit[rows_]
        pred, _ = cam.project(u @ A.T)
        resid = sol.residual[b, acc]
        r.update(residual_median_rad=float(np.median(resid)), residual_max_rad=float(np.max(resid)),
                 residual_rms_rad=float(np.sqrt(np.mean(resid ** 2))))
        t_res = None
        if truth.A is not None:
            t_res = angle_between(obs.vec[b, acc], u @ truth.A.T)
            r["truth_residual_median_rad"] = float(np.median(t_res))
        tm, agree = _truth_star_checks(obs.x[b, acc], obs.y[b, acc], u, truth)
        for j, s in enumerate(acc):
            res.stars.append(StarRow(
                det_index=int(s), x_px=float(obs.x[b, s]), y_px=float(obs.y[b, s]),
                flux=float(det.flux[s0 + s]), npix=int(det.npix[s0 + s]), hip=int(cat.hip[rows_[j]]),
                vmag=float(cat.vmag[rows_[j]]), ra_rad=float(cat.ra[rows_[j]]), dec_rad=float(cat.dec[rows_[j]]),
                pred_x_px=float(pred[j, 0]), pred_y_px=float(pred[j, 1]), residual_rad=float(resid[j]),
                truth_residual_rad=None if t_res is None else float(t_res[j]),
                votes=int(ident.votes[b, s]), verify_votes=int(ident.verify_votes[b, s]),
                truth_match=None if tm is None else bool(tm[j]),
                truth_id_agrees=None if agree is None else (bool(agree[j]) if tm[j] else None)))
        # catalog stars the solved attitude puts in the field (for the overlay)
        v = cat.unit @ A.T
        px, front = cam.project(v)
        inside = front & cam.in_image(np.nan_to_num(px, nan=-1.0))
        res.field_xy, res.field_vmag = px[inside], cat.vmag[inside]
    if truth.entry is not None:
        m = truth.entry["matched"]
        r["truth_stars"] = int(m["row"].size)
        if ok and res.stars:
            ours = np.array([[s.x_px, s.y_px] for s in res.stars])
            d = np.hypot(m["col"][:, None] - ours[None, :, 0], m["row"][:, None] - ours[None, :, 1])
            r["truth_stars_found"] = int((d.min(axis=1) <= TRUTH_MATCH_PX).sum())
            r["truth_ids_agree"] = sum(1 for s in res.stars if s.truth_id_agrees is True)
            r["truth_ids_disagree"] = sum(1 for s in res.stars if s.truth_id_agrees is False)
        else:
            r.update(truth_stars_found=0, truth_ids_agree=0, truth_ids_disagree=0)
    score(r, A if ok else None, int(ident.T[b]), truth, st)
    if alt is not None:
        ident_a, sol_a = alt
        ok_a = bool(sol_a.ok[b]) and int(ident_a.T[b]) > 0
        r.update(alt_identified=ok_a, alt_T=int(ident_a.T[b]), alt_stars_identified=int(ident_a.accepted[b].sum()))
        if ok_a:
            ra_ = sol_a.residual[b][ident_a.accepted[b] & (ident_a.ids[b] >= 0)]
            r["alt_residual_median_rad"] = float(np.median(ra_)) if ra_.size else None
            if truth.A is not None:
                r["alt_boresight_error_rad"] = float(angle_between(sol_a.A_est[b, 2], truth.A[2]))


def _truth_star_checks(x, y, u, truth: Truth):
    """Per identified star: does a truth-file star sit at the same centroid (2 px), and if so is it the
    same sky position (60 arcsec)?  (None, None) without a truth file."""
    if truth.entry is None:
        return None, None
    m = truth.entry["matched"]
    if m["row"].size == 0:
        return np.zeros(len(x), bool), np.zeros(len(x), bool)
    d = np.hypot(x[:, None] - m["col"][None], y[:, None] - m["row"][None])
    k = d.argmin(axis=1)
    hit = d[np.arange(len(x)), k] <= TRUTH_MATCH_PX
    tv = radec_to_unit(np.radians(m["ra_deg"][k]), np.radians(m["dec_deg"][k]))
    agree = angle_between(u, tv) <= TRUTH_ID_ARCSEC * ARCSEC
    return hit, agree


def score(row: dict, A: np.ndarray | None, T: int, truth: Truth, st: HilStarSettings):
    """Errors against the truth (module docstring) and the status, into ``row``."""
    if truth.A is not None:
        At = truth.A
        ra_t, dec_t = unit_to_radec(At[2])
        row.update(ra_true_rad=float(ra_t), dec_true_rad=float(dec_t), roll_true_deg=float(roll_deg(At)),
                   A_true=At.ravel().tolist())
        lim = st.limit_arcsec if st.limit_arcsec is not None else (100.0 if truth.source == "file"
                                                                    else ALTAZ_LIMIT_ARCSEC)
        row["limit_arcsec"] = lim
        if A is not None:
            row["boresight_error_rad"] = float(angle_between(A[2], At[2]))
            if truth.entry is not None:
                b = radec_to_unit(math.radians(truth.entry["ra_deg"]), math.radians(truth.entry["dec_deg"]))
                row["boresight_error_radec_rad"] = float(angle_between(A[2], b))
            e = axis_errors(A[None], At[None], frame="camera")[0]
            tot = float(total_error_angle(A[None], At[None])[0])
            row.update(err_x_rad=float(e[0]), err_y_rad=float(e[1]), err_z_rad=float(e[2]), attitude_error_rad=tot)
            row["status"] = STATUS_NAMES[int(classify(e[None], np.array([tot]), np.array([T]), lim)[0])]
        else:
            row["status"] = "no_solution"
    else:
        row["status"] = "identified" if A is not None else "no_solution"
    if truth.altaz_A is not None:
        ra_a, dec_a = unit_to_radec(truth.altaz_A[2])
        row.update(altaz_ra_rad=float(ra_a), altaz_dec_rad=float(dec_a))
        if A is not None:
            row["altaz_error_rad"] = float(angle_between(A[2], truth.altaz_A[2]))
    if truth.note:
        row["truth_note"] = truth.note


# ============================================================================================ tables
_MAT9 = pa.list_(pa.float64(), 9)
IMAGES_SCHEMA = pa.schema([
    ("image", pa.string()), ("path", pa.string()), ("image_index", pa.int32()), ("error", pa.string()),
    ("status", pa.string()), ("identified", pa.bool_()), ("method", pa.string()),
    ("width", pa.int32()), ("height", pa.int32()), ("bit_depth", pa.int32()), ("shift", pa.int32()),
    ("background_adu", pa.float64()), ("detect_background_adu", pa.float64()), ("threshold_adu", pa.float64()),
    ("stars_detected", pa.int32()), ("stars_used", pa.int32()), ("stars_identified", pa.int32()), ("T", pa.int32()),
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
    ("alt_method", pa.string()), ("alt_identified", pa.bool_()), ("alt_T", pa.int32()),
    ("alt_stars_identified", pa.int32()), ("alt_boresight_error_rad", pa.float64()),
    ("alt_residual_median_rad", pa.float64()),
    ("camera_fx_px", pa.float64()), ("camera_width", pa.int32()), ("camera_height", pa.int32()),
    ("mag_limit", pa.float64()), ("tolerance_rad", pa.float64()), ("max_stars", pa.int32()),
    ("overlay", pa.string()),
    ("t_read_ns", pa.int64()), ("t_detect_ns", pa.int64()), ("t_identify_ns", pa.int64()),
    ("t_attitude_ns", pa.int64()), ("t_alt_ns", pa.int64()), ("t_total_ns", pa.int64()),
])

STARS_SCHEMA = pa.schema([
    ("image", pa.string()), ("image_index", pa.int32()), ("det_index", pa.int32()),
    ("x_px", pa.float64()), ("y_px", pa.float64()), ("flux", pa.float64()), ("npix", pa.int32()),
    ("hip", pa.int32()), ("vmag", pa.float64()), ("ra_rad", pa.float64()), ("dec_rad", pa.float64()),
    ("pred_x_px", pa.float64()), ("pred_y_px", pa.float64()), ("residual_rad", pa.float64()),
    ("truth_residual_rad", pa.float64()), ("votes", pa.int32()), ("verify_votes", pa.int32()),
    ("truth_match", pa.bool_()), ("truth_id_agrees", pa.bool_()), ("method", pa.string()),
])


def tables(results: list[ImageResult]) -> dict[str, pa.Table]:
    """The run's ``hil_star`` and ``hil_star_stars`` tables."""
    img_cols = {f.name: [r.row.get(f.name) for r in results] for f in IMAGES_SCHEMA}
    stars = [(r, s) for r in results for s in r.stars]
    star_cols = {f.name: [(r.row[f.name] if f.name in ("image", "image_index", "method") else getattr(s, f.name))
                          for r, s in stars] for f in STARS_SCHEMA}
    return {"hil_star": pa.table({k: pa.array(v, type=IMAGES_SCHEMA.field(k).type) for k, v in img_cols.items()},
                                 schema=IMAGES_SCHEMA),
            "hil_star_stars": pa.table({k: pa.array(v, type=STARS_SCHEMA.field(k).type)
                                        for k, v in star_cols.items()}, schema=STARS_SCHEMA)}


def default_run_id(lake) -> str:
    """``hil-star-<UTC timestamp>`` (see :meth:`Lake.new_run_id`)."""
    return lake.new_run_id("hil-star")


def check_run(lake, run_id: str, spec: dict):
    """Refuse to overwrite a run of another kind or with other settings/images (before any work)."""
    lake.refuse_other_run(run_id, NAME, spec)


def write_run(lake, run_id: str, results: list[ImageResult], spec: dict, elapsed_s: float) -> dict:
    """Write the run's shard (atomic) and manifest (kind ``hil_star``); returns the manifest.

    Re-running an id with identical settings and images replaces its rows (same shard file name)."""
    import socket

    from dualsight.jobs.runner import versions

    t = tables(results)
    rows = lake.write_shard(run_id, 0, t, primary=PRIMARY)
    n_err = sum(1 for r in results if r.row["error"])
    manifest = {"run_id": run_id, "kind": NAME, "job": NAME, "label": f"hil star {run_id}", "spec": spec,
                "seed": None, "n_cases": len(results), "shard_size": max(1, len(results)), "n_shards": 1,
                "datasets": DATASETS, "primary": PRIMARY, "versions": versions(), "host": socket.gethostname(),
                "created_unix": time.time(), "shards_done": [0], "status": "complete", "rows": rows,
                "stats": {"images": len(results), "errors": n_err,
                          "identified": sum(1 for r in results if r.row["identified"])},
                "executions": [{"started_unix": time.time() - elapsed_s, "elapsed_s": elapsed_s,
                                "cases_run": len(results)}]}
    lake.write_manifest(manifest)
    return manifest


# ============================================================================================ output
def _as(v, scale=1.0 / ARCSEC, nd=2):
    return None if v is None else round(float(v) * scale, nd)


def _deg(v, nd=6):
    return None if v is None else round(math.degrees(float(v)), nd)


def to_json(res: ImageResult) -> dict:
    """One image as a JSON object (angles in deg / arcsec; the field list is in jobs/cli_hil.py)."""
    r = res.row
    out = {
        "image": r["image"], "path": r["path"], "error": r["error"], "status": r["status"],
        "identified": bool(r["identified"]), "method": r["method"],
        "stars_detected": r.get("stars_detected"), "stars_used": r.get("stars_used"),
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
        "overlay": r.get("overlay"),
    }
    if r.get("alt_method"):
        out["alt"] = {"method": r["alt_method"], "identified": r.get("alt_identified"), "T": r.get("alt_T"),
                      "stars_identified": r.get("alt_stars_identified"),
                      "boresight_error_arcsec": _as(r.get("alt_boresight_error_rad")),
                      "residual_median_arcsec": _as(r.get("alt_residual_median_rad"))}
    if r.get("truth_note"):
        out["truth_note"] = r["truth_note"]
    out["stars"] = [{"hip": s.hip, "vmag": round(s.vmag, 2), "x_px": round(s.x_px, 3), "y_px": round(s.y_px, 3),
                     "pred_x_px": round(s.pred_x_px, 3), "pred_y_px": round(s.pred_y_px, 3),
                     "error_arcsec": _as(s.residual_rad),
                     "truth_error_arcsec": _as(s.truth_residual_rad), "truth_match": s.truth_match,
                     "truth_id_agrees": s.truth_id_agrees} for s in res.stars]
    return out


def table6_text(res: ImageResult, max_rows: int | None = None) -> str:
    """The reference's Table 6 for one image: catalog id, magnitude, observed versus predicted error."""
    from dualsight.warehouse.query import format_table

    stars = sorted(res.stars, key=lambda s: s.vmag)
    if max_rows is not None:
        stars = stars[:max_rows]
    has_truth = any(s.truth_residual_rad is not None for s in stars)
    cols = ["HIP", "V", "obs col", "obs row", "pred col", "pred row", "error (arcsec)"]
    if has_truth:
        cols += ["vs truth (arcsec)", "truth id"]
    rows = []
    for s in stars:
        row = [s.hip, f"{s.vmag:.2f}", f"{s.x_px:.2f}", f"{s.y_px:.2f}", f"{s.pred_x_px:.2f}", f"{s.pred_y_px:.2f}",
               f"{s.residual_rad / ARCSEC:.1f}"]
        if has_truth:
            row += ["-" if s.truth_residual_rad is None else f"{s.truth_residual_rad / ARCSEC:.1f}",
                    {True: "agrees", False: "DIFFERS", None: "-"}[s.truth_id_agrees]]
        rows.append(row)
    return format_table(cols, rows)


def summary_line(res: ImageResult) -> str:
    j = to_json(res)
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
    return head


def overlay_title(res: ImageResult) -> tuple[str, list[str]]:
    j = to_json(res)
    lines = [f"{j['method']} voting: {j['stars_detected']} detected, {j['stars_identified']} identified, T = {j['T']}"]
    if j["identified"]:
        lines.append(f"RA {j['ra_deg']:.4f}  Dec {j['dec_deg']:+.4f}  roll {j['roll_deg']:.2f} deg;  "
                     f"residual median {j['residual_median_arcsec']:.1f} arcsec")
    if j["boresight_error_arcsec"] is not None:
        lines.append(f"boresight error vs {j['truth_source']} truth {j['boresight_error_arcsec']:.1f} arcsec")
    return j["image"], lines


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


def write_overlays(results: list[ImageResult], folder: Path, credit: str | None = None,
                   error_scale: float = 100.0) -> list[Path]:
    """One Figure-11-style PNG per processed image (``<image stem>.png``); sets ``row["overlay"]``."""
    from dualsight.viz.overlay import star_overlay

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for res in results:
        if res.pixels is None:
            continue
        title, lines = overlay_title(res)
        ident = [(s.x_px, s.y_px, s.pred_x_px, s.pred_y_px, s.hip, s.vmag, s.residual_rad / ARCSEC)
                 for s in res.stars]
        p = folder / f"{res.path.stem}.png"
        star_overlay(p, res.pixels, detections=res.det_xy, identified=ident, field_xy=res.field_xy,
                     field_vmag=res.field_vmag, truth_xy=res.truth_xy, title=title, info=lines,
                     credit=credit if credit is not None else licence_credit(res.path), error_scale=error_scale)
        res.row["overlay"] = str(p)
        out.append(p)
    return out


__all__ = ["HilStarSettings", "make_settings", "Site", "Truth", "resolve_truths", "subtract_background",
           "roll_deg", "make_context", "run", "tables", "write_run", "to_json", "table6_text",
           "write_overlays", "default_run_id", "check_run", "expand_inputs", "licence_credit"]
