"""Proximity hardware-in-the-loop: the SIL blobber on real photos of a target (reference Sec. 2.4).

    dualsight hil prox IMAGES... --camera FILE --target FILE [--invert] [--threshold T | --sweep A:B:STEP]
                       [--open K] [--close K] [--border PX] [--undistort] [--estimator paper|subpixel]
                       [--blob largest|all] [--range-truth M|FILE] [--json] [--lake DIR] [--run ID]
                       [--no-lake] [--plot FILE.png]

Processing of every image, for every threshold T (the reference's, Sec. 2.4, in this order):

1. read the file (scene.imageio: PNG, JPEG, TIFF, FITS; 8/16-bit or float; mono or RGB; alpha dropped);
2. optional ``--undistort``: remap the image through the camera's distortion model to the ideal pinhole
   with the *same* fx, fy, cx, cy (OpenCV ``initUndistortRectifyMap`` + bilinear ``remap``); pixels that
   come from outside the frame are filled with the background value (full scale with ``--invert``, else
   0); the blobber then uses the camera without distortion;
3. optional ``--invert`` (a dark object on a light background): every channel v -> full_scale - v
   (255 - v for 8-bit data);
4. binary threshold: a pixel is foreground when ANY colour channel is >= T (the reference: "if any of
   the colour channels met or exceeded the threshold, the pixel was considered a 1").  T is in the
   image's own units (0-255 for 8-bit data, 0-65535 for 16-bit, 0-1 for float images);
5. optional ``--border PX``: the outer PX pixels of the frame are set to background (frame-grabber
   edges: OpenCV's chessboard samples have a 1-4 px black frame that would join every dark object);
6. optional morphological opening (``--open K``: erode then dilate, removes foreground thinner than K)
   and then closing (``--close K``: dilate then erode, fills gaps and holes narrower than K), both with
   a K x K square structuring element (OpenCV ``morphologyEx``, ``MORPH_RECT``, anchor at the centre;
   OpenCV's default border handling, so the frame edge neither erodes nor dilates).  Opening comes
   first, as in the reference ("the thresholded images were opened and closed"); K <= 1 is off;
7. the blobber (:func:`dualsight.nav.blobber.run_blobber`, the very code of the simulations, through
   :func:`dualsight.kernels.blobs.label_blobs`) on the binary image (1.0 foreground, 0.0 background,
   blobber threshold 0.5), batched over the thresholds of one image:

   * the target is the **largest** 8-connected blob (default, ``--blob largest``): a real scene has
     other foreground (background clutter, reflections) that must not count in N_blob;
     ``--blob all`` takes every foreground pixel as one blob (only for a clean background);
   * the centre of brightness of a binary blob is its centroid -> unit vector (``Camera.backproject``,
     through the distortion model unless the image was undistorted);
   * the axis ratio of the blob's second moments -> the projected-area table of the target
     (:func:`dualsight.catalogs.areas.area_table` of the target's satellite file: random orientations
     uniform on SO(3)) -> A_min, A_est, A_max -> range by Eq. 1.  ``--estimator paper`` (default) is
     Eq. 1 as printed, rho = f sqrt(A / (N p^2)); ``subpixel`` the blobber's other estimator (Sheppard
     moments, the ``relopt`` area curve, the field-angle correction).

Pixel pitch.  Eq. 1 needs f / p only: ``paper`` computes f = mean(fx, fy) * p and divides by p again, so
rho = mean(fx, fy) sqrt(A / N) and ``subpixel`` uses fx, fy directly.  A camera from ``dualsight
calibrate`` without ``--pixel-pitch-um`` (a placeholder pitch) gives the same ranges as one with the true
pitch (tests/test_hil_prox.py checks it to 1e-12).

Truth (``--range-truth``), per image, optional: a number (metres, every image), a JSON file
``{"<image file name>": metres, ...}`` (or ``{"name": {"range_m": metres}}``), or a camera file written
by ``dualsight calibrate`` whose ``[[calibration.views]]`` give each board's ``distance_m`` (optical
centre to the centre of the inner-corner grid) keyed by image name.

Scores per image x threshold: ``range_error_m`` = estimate - truth, ``abs_error_m``, ``rel_error`` =
abs / truth (fraction), ``within_min_max`` = truth in [range_min, range_max] (False when no blob was
found).  The sweep summary (warehouse/sql/hil_prox_sweep.sql, the reference's Figure 8 numbers), per
threshold: ``avg_range_m`` (mean estimate over images with a blob), ``avg_abs_error_m`` (the
reference's "average residual"), ``avg_rel_error_pct``, ``median_rel_error_pct`` and
``within_min_max_pct`` (share of the images with a truth whose truth lies inside the min/max bars;
images without a blob count as outside).

Lake: dataset ``hil_prox``, one row per image x threshold (an image that could not be read has ONE row,
with ``error`` set and ``threshold`` NULL); one shard per run written atomically
(``Lake.write_shard``) with a manifest of kind ``hil_prox``; run id ``hil-prox-<UTC timestamp>`` unless
``--run``.  Lengths in metres, angles in radians (DESIGN.md).

``--json`` prints ONE object::

    {"run": id | null, "camera": {...}, "target": {...}, "settings": {...},
     "images": [{"image", "path", "error", "truth_range_m", "truth_source",
                 "results": [{"threshold", "found", "n_blobs", "n_foreground", "n_pixels", "axis_ratio",
                              "cob_px": [col, row], "unit": [x, y, z], "range_min_m", "range_m",
                              "range_max_m", "error_m", "abs_error_m", "rel_error_pct",
                              "within_min_max", "touches_edge"}, ...]}, ...],
     "sweep": [{"threshold", "images", "found", "with_truth", "avg_range_m", "avg_range_min_m",
                "avg_range_max_m", "avg_truth_m", "avg_abs_error_m", "avg_rel_error_pct",
                "median_rel_error_pct", "within_min_max_pct"}, ...],
     "best": the sweep row with the smallest avg_rel_error_pct (null without truth)}

Real-image check (tests/test_hil_prox.py): OpenCV's 13 chessboard photos, a flat plate of known size
(examples/targets/opencv_chessboard.toml: the dark pattern, 0.229 x 0.175 m) at 0.27-0.41 m, truth from
the calibration's board poses; ``--invert --threshold 210 --border 6 --open 9 --close 61``:

* errors -21 .. +13 %, median |error| 7.7 %, truth inside [min, max] for 7/13; with the exact silhouette
  (the pattern's outline projected through each pose) the same blobber gives -6.5 .. +0.5 %, median
  3.9 %, 13/13 inside -- so segmentation dominates: in a cluttered office the closing wide enough to
  merge the squares (> 50 px) also bridges the ~10 px white margin + grey frame into dark background
  (hair, shelf edges, a chair), and on boards lit from above the palest squares (up to 48 of 255) fall
  below the threshold and the closing cannot recover whole rows;
* the method itself: a near-frontal plate's axis ratio (1.1-1.6) is also produced by strongly tilted
  views, so the uniform-orientation area table reads ~10 % small in area (~5 % in range); perspective at
  0.3 m adds 2-16 % pixels for tilts of 13-44 deg (Eq. 1 is orthographic); ``paper`` Eq. 1 has no
  field-angle term (up to 4 % for an off-axis board); barrel distortion (k1 = -0.27) shrinks the blob by
  a few % and partly cancels these (``--undistort`` removes it: ideal-silhouette mean -7.4 % instead of
  -3.2 %, photos median 8.9 % instead of 7.7 %);
* direction: the blob centroid is 1-9 deg from the board centre (median 4.4; ideal silhouettes 2.8):
  the centroid of a tilted near plate is pulled towards its nearer half.

Exit status: 0 when every image was processed (a blob found or not), 1 when an image could not be read
(it is reported on stderr, gets an error entry/row, and the others run), 2 for bad options (nothing
is written).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from dualsight.errors import ConfigError, ImageError, InputError
from dualsight.nav.blobber import ESTIMATORS, TARGETS, BlobberConfig, run_blobber
from dualsight.scene.camera import Camera
from dualsight.scene.imageio import list_images, read_image

NAME = "hil_prox"
DATASETS = ["hil_prox"]
PRIMARY = "hil_prox"
DEFAULT_THRESHOLD = 230.0
"""The reference's best threshold on its 8-bit HIL images (Sec. 2.4, Figure 8)."""
MAX_THRESHOLDS = 1000
MAX_KERNEL = 1001
_CHUNK = 8            # thresholds per blobber batch (bounds memory: 8 float32 frames)


# ============================================================================================ settings
@dataclass(frozen=True)
class HilProxSettings:
    """Everything that decides a proximity HIL run (recorded in the manifest).

    thresholds : the binary thresholds (image units), one or a sweep.
    invert : dark object on a light background (v -> full_scale - v before the threshold).
    open_px, close_px : K of the K x K opening / closing (<= 1: off); opening first.
    border_px : outer frame pixels forced to background (0: none).
    undistort : remap the image to the ideal pinhole before the threshold.
    estimator, blob, connectivity, area_curve, min_pixels : the blobber's (``BlobberConfig``;
        ``blob`` is its ``target``: "largest" or "all").
    table_samples, bin_width : the projected-area table (random orientations, axis-ratio bin).
    """

    thresholds: tuple[float, ...] = (DEFAULT_THRESHOLD,)
    invert: bool = False
    open_px: int = 0
    close_px: int = 0
    border_px: int = 0
    undistort: bool = False
    estimator: str = "paper"
    blob: str = "largest"
    connectivity: int = 8
    area_curve: str | None = None
    min_pixels: int = 1
    table_samples: int = 20000
    bin_width: float = 0.05

    def __post_init__(self):
        th = tuple(float(t) for t in self.thresholds)
        if not th or not all(math.isfinite(t) for t in th):
            raise ConfigError(f"thresholds must be finite numbers, got {self.thresholds!r}", field="--threshold")
        if len(th) > MAX_THRESHOLDS:
            raise ConfigError(f"at most {MAX_THRESHOLDS} thresholds, got {len(th)}", field="--sweep")
        object.__setattr__(self, "thresholds", th)
        for name in ("open_px", "close_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_KERNEL:
                raise ConfigError(f"must be an integer kernel size in [0, {MAX_KERNEL}] px (0 or 1: off), got {v!r}",
                                  field="--" + name[:-3])
        if isinstance(self.border_px, bool) or not isinstance(self.border_px, int) or not 0 <= self.border_px <= 10000:
            raise ConfigError(f"must be an integer >= 0 px, got {self.border_px!r}", field="--border")
        if self.estimator not in ESTIMATORS:
            raise ConfigError(f"must be one of {', '.join(ESTIMATORS)}, got {self.estimator!r}", field="--estimator")
        if self.blob not in TARGETS:
            raise ConfigError(f"must be one of {', '.join(TARGETS)}, got {self.blob!r}", field="--blob")
        if isinstance(self.table_samples, bool) or not isinstance(self.table_samples, int) \
                or not 100 <= self.table_samples <= 10_000_000:
            raise ConfigError(f"must be an integer in [100, 1e7], got {self.table_samples!r}", field="--table-samples")
        if not (isinstance(self.bin_width, (int, float)) and 0 < self.bin_width <= 1):
            raise ConfigError(f"must be in (0, 1], got {self.bin_width!r}", field="--bin-width")
        try:
            self.blobber_config()
        except ValueError as e:
            raise ConfigError(str(e), field="blobber") from None

    def blobber_config(self) -> BlobberConfig:
        """The blobber's settings: binary input (1.0 / 0.0) thresholded at 0.5."""
        return BlobberConfig(estimator=self.estimator, threshold=0.5, connectivity=self.connectivity,
                             target=self.blob, area_curve=self.area_curve, min_pixels=self.min_pixels)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["thresholds"] = list(self.thresholds)
        return d


def parse_sweep(text: str) -> tuple[float, ...]:
    """"A:B:STEP" -> (A, A+STEP, ..., <= B) (B included when on the grid, to 1e-9 of a step)."""
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*:\s*([-+0-9.eE]+)\s*:\s*([-+0-9.eE]+)\s*", str(text))
    try:
        a, b, step = (float(m.group(i)) for i in (1, 2, 3)) if m else (None, None, None)
    except ValueError:
        a = None
    if a is None or not all(math.isfinite(x) for x in (a, b, step)):
        raise ConfigError(f"must look like A:B:STEP (e.g. 200:250:5), got {text!r}", field="--sweep")
    if step <= 0 or b < a:
        raise ConfigError(f"needs STEP > 0 and A <= B, got {text!r}", field="--sweep")
    n = int(math.floor((b - a) / step + 1e-9)) + 1
    if n > MAX_THRESHOLDS:
        raise ConfigError(f"gives {n} thresholds; at most {MAX_THRESHOLDS}", field="--sweep")
    return tuple(round(a + k * step, 10) for k in range(n))


# ============================================================================================ image processing
def score_image(pixels: np.ndarray, *, invert: bool = False, full_scale: float = 255.0) -> np.ndarray:
    """(H, W) float32 "any channel" score: the largest channel value (after inversion), so that
    ``score >= T`` is exactly "any colour channel >= T".  Inversion maps v -> full_scale - v per channel,
    so the score of an inverted pixel is full_scale - (its smallest channel).  An alpha channel (4th) is
    ignored."""
    a = np.asarray(pixels)
    if a.ndim == 3:
        a = a[..., :3] if a.shape[2] >= 3 else a[..., :1]
        a = a.min(axis=2) if invert else a.max(axis=2)
    elif a.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, C) image, got shape {a.shape}")
    s = a.astype(np.float32)
    return (np.float32(full_scale) - s) if invert else s


def binarize(pixels: np.ndarray, threshold: float, *, invert: bool = False, full_scale: float = 255.0) -> np.ndarray:
    """(H, W) bool: foreground where ANY channel (after optional inversion) is >= ``threshold``."""
    return score_image(pixels, invert=invert, full_scale=full_scale) >= np.float32(threshold)


def clear_border(mask: np.ndarray, border_px: int) -> np.ndarray:
    """Set the outer ``border_px`` pixels of a (H, W) mask to background (in place; returns it)."""
    b = int(border_px)
    if b > 0:
        mask[:b] = 0
        mask[-b:] = 0
        mask[:, :b] = 0
        mask[:, -b:] = 0
    return mask


def morphology(mask: np.ndarray, open_px: int = 0, close_px: int = 0) -> np.ndarray:
    """Opening with a K x K square, then closing with another (OpenCV ``morphologyEx``, ``MORPH_RECT``);
    K <= 1 skips that step.  Returns a new uint8 (0/1) mask."""
    import cv2

    m = np.ascontiguousarray(mask, dtype=np.uint8)
    if open_px > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (open_px, open_px)))
    if close_px > 1:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (close_px, close_px)))
    return m


def undistort_image(pixels: np.ndarray, camera: Camera, fill: float = 0.0) -> tuple[np.ndarray, Camera]:
    """Remap an image to the ideal pinhole with the same fx, fy, cx, cy (no distortion).

    Returns the remapped image (same dtype; pixels from outside the frame = ``fill``) and the camera
    without distortion to use with it.  A camera without distortion returns the input unchanged."""
    import cv2

    if not camera.has_distortion:
        return pixels, camera
    K = camera.opencv_matrix()
    m1, m2 = cv2.initUndistortRectifyMap(K, np.asarray(camera.distortion, float), None, K,
                                         (camera.width, camera.height), cv2.CV_32FC1)
    a = np.asarray(pixels)
    src = a.astype(np.float32) if a.dtype not in (np.uint8, np.uint16, np.float32) else a
    fill_v = (float(fill),) * 4
    out = cv2.remap(src, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=fill_v)
    cam0 = Camera(camera.width, camera.height, camera.pixel_pitch_m, camera.fx, camera.fy, camera.cx, camera.cy,
                  (0.0,) * 5, camera.bit_depth)
    return out.astype(a.dtype, copy=False), cam0


def foreground_masks(score: np.ndarray, thresholds, settings: HilProxSettings) -> np.ndarray:
    """(len(thresholds), H, W) float32 binary images (1 foreground): threshold, border, open, close."""
    out = np.empty((len(thresholds),) + score.shape, np.float32)
    for k, t in enumerate(thresholds):  # one threshold at a time: OpenCV morphology per 2-D mask
        m = (score >= np.float32(t)).astype(np.uint8)
        clear_border(m, settings.border_px)
        out[k] = morphology(m, settings.open_px, settings.close_px)
    return out


# ============================================================================================ target and truth
@dataclass(frozen=True)
class Target:
    """The target model: its satellite file and projected-area table."""

    name: str
    path: str
    satellite: object
    table: object

    def to_dict(self) -> dict:
        comps = [{"shape": c.shape, "size": list(c.size), "position": list(c.position),
                  "orientation_deg": list(c.orientation_deg)} for c in self.satellite.components]
        return {"name": self.name, "file": self.path, "A0_m2": self.table.A0_m2, "table_key": self.table.key,
                "table_samples": self.table.n_samples, "components": comps}


def load_target(path: str | Path, settings: HilProxSettings = HilProxSettings()) -> Target:
    """Read a target model (a satellite TOML, scene/satellite.py) and build its projected-area table."""
    from dualsight.catalogs.areas import area_table
    from dualsight.scene.satellite import load_satellite

    sat = load_satellite(path)
    table = area_table(sat, n=settings.table_samples, bin_width=settings.bin_width)
    return Target(name=sat.name or Path(path).stem, path=str(path), satellite=sat, table=table)


def load_range_truth(spec, paths) -> tuple[list[float | None], str]:
    """Per-image true ranges from ``--range-truth`` (see the module docstring) and the source name
    ("value", "json" or "calibration"); images without an entry get None."""
    paths = [Path(p) for p in paths]
    if spec is None:
        return [None] * len(paths), "none"
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        v = float(spec)
        _check_range(v, "--range-truth")
        return [v] * len(paths), "value"
    text = str(spec)
    try:
        v = float(text)
    except ValueError:
        v = None
    if v is not None:
        _check_range(v, "--range-truth")
        return [v] * len(paths), "value"
    p = Path(text)
    if not p.is_file():
        raise InputError("is neither a number (metres) nor a truth file (JSON or camera TOML)", source=text)
    table: dict[str, float] = {}
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(f"cannot be read as JSON ({e})", source=text) from None
        if not isinstance(data, dict):
            raise InputError("must be a JSON object {\"image name\": range_m, ...}", source=text)
        for k, val in data.items():
            if isinstance(val, dict):
                val = val.get("range_m", val.get("distance_m"))
            if isinstance(val, bool) or not isinstance(val, (int, float)):
                raise InputError(f"entry {k!r} must be a number (metres) or {{\"range_m\": number}}", source=text)
            _check_range(float(val), text, k)
            table[Path(k).name] = float(val)
        kind = "json"
    else:
        from dualsight.scene.calibration import read_camera_toml

        _, cal = read_camera_toml(p)
        views = cal.get("views") or []
        for i, vw in enumerate(views):
            if not isinstance(vw, dict) or "image" not in vw or "distance_m" not in vw:
                raise InputError("needs image and distance_m", source=text, field=f"calibration.views[{i}]")
            _check_range(float(vw["distance_m"]), text, f"calibration.views[{i}].distance_m")
            table[Path(str(vw["image"])).name] = float(vw["distance_m"])
        if not table:
            raise InputError("has no [[calibration.views]] with distance_m (write it with dualsight calibrate)",
                             source=text)
        kind = "calibration"
    return [table.get(q.name) for q in paths], kind


def _check_range(v: float, source: str, key: str | None = None):
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"a true range must be a number > 0 m, got {v!r}", source=source, field=key)


def expand_inputs(items) -> list[Path]:
    """Image paths; a folder expands to its images (natural order).  Missing files are kept (error rows)."""
    out = []
    for it in items:
        p = Path(it)
        out.extend(list_images(p) if p.is_dir() else [p])
    return out


# ============================================================================================ per image
@dataclass
class ImageResult:
    """One image: its rows (one per threshold; one error row if it could not be processed)."""

    index: int
    path: Path
    truth_m: float | None
    truth_source: str
    error: str | None = None
    rows: list[dict] = field(default_factory=list)


def process_image(index: int, path: Path, camera: Camera, target: Target, settings: HilProxSettings,
                  truth_m: float | None = None, truth_source: str = "none") -> ImageResult:
    """Run every threshold of ``settings`` on one image; an unreadable image gives an error result."""
    path = Path(path)
    res = ImageResult(index, path, truth_m, truth_source)
    base = {"image": path.name, "path": str(path), "image_index": index, "error": None,
            "truth_range_m": truth_m, "truth_source": truth_source, "target": target.name,
            "A0_m2": target.table.A0_m2, "camera_fx_px": camera.fx, "camera_fy_px": camera.fy,
            "invert": settings.invert, "open_px": settings.open_px, "close_px": settings.close_px,
            "border_px": settings.border_px, "undistort": settings.undistort, "estimator": settings.estimator,
            "blob": settings.blob, "area_curve": settings.blobber_config().curve}
    t0 = time.perf_counter_ns()
    try:
        img = read_image(path)
        if (img.width, img.height) != (camera.width, camera.height):
            raise ImageError(f"size {img.width}x{img.height} differs from the camera's {camera.width}x{camera.height}",
                             source=str(path))
    except ImageError as e:
        res.error = str(e.detail if getattr(e, "detail", None) else e)
        res.rows.append(dict(base, error=res.error, t_read_ns=time.perf_counter_ns() - t0))
        return res
    t1 = time.perf_counter_ns()
    full = img.full_scale
    pix, cam = img.pixels, camera
    if settings.undistort:
        pix, cam = undistort_image(pix, camera, fill=full if settings.invert else 0.0)
    score = score_image(pix, invert=settings.invert, full_scale=full)
    base.update(width=img.width, height=img.height, channels=img.channels, bit_depth=img.bit_depth,
                full_scale=full, t_read_ns=t1 - t0)
    cfg = settings.blobber_config()
    th = settings.thresholds
    W, H = cam.width, cam.height
    edge = settings.border_px
    for s in range(0, len(th), _CHUNK):          # chunks of thresholds: one blobber batch each
        tp = time.perf_counter_ns()
        chunk = th[s:s + _CHUNK]
        masks = foreground_masks(score, chunk, settings)
        n_fg = masks.sum(axis=(1, 2)).astype(np.int64)
        tb = time.perf_counter_ns()
        r = run_blobber(masks, cam, target.table, cfg)
        te = time.perf_counter_ns()
        del masks
        for k, t in enumerate(chunk):
            row = dict(base, threshold=float(t), n_foreground=int(n_fg[k]),
                       t_prep_ns=(tb - tp) // len(chunk), t_blob_ns=(te - tb) // len(chunk))
            row.update(_blob_row(r, k))
            box = r.box[k]
            row["touches_edge"] = bool(row["found"] and (box[0] <= edge or box[1] <= edge or box[2] >= W - 1 - edge
                                                        or box[3] >= H - 1 - edge))
            _score(row, truth_m)
            res.rows.append(row)
    return res


def _f(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _blob_row(r, k: int) -> dict:
    found = bool(r.found[k])
    row = {"found": found, "n_blobs": int(r.n_blobs[k]), "n_pixels": int(r.n_pixels[k]),
           "n_blob": _f(r.n_blob[k]), "cob_x_px": _f(r.cob_px[k, 0]), "cob_y_px": _f(r.cob_px[k, 1]),
           "unit_x": _f(r.unit[k, 0]), "unit_y": _f(r.unit[k, 1]), "unit_z": _f(r.unit[k, 2]),
           "major_px": _f(r.major_px[k]), "minor_px": _f(r.minor_px[k]), "axis_ratio": _f(r.axis_ratio[k]),
           "angle_rad": _f(r.angle_rad[k]), "area_rel_min": _f(r.area_rel_min[k]),
           "area_rel_est": _f(r.area_rel_est[k]), "area_rel_max": _f(r.area_rel_max[k]),
           "range_min_m": _f(r.range_min[k]), "range_m": _f(r.range_est[k]), "range_max_m": _f(r.range_max[k]),
           "pos_x_m": _f(r.position[k, 0]), "pos_y_m": _f(r.position[k, 1]), "pos_z_m": _f(r.position[k, 2])}
    for i, s in enumerate(("x0", "y0", "x1", "y1")):
        row[f"box_{s}"] = int(r.box[k, i]) if found else None
    return row


def _score(row: dict, truth: float | None):
    row.update(range_error_m=None, abs_error_m=None, rel_error=None, within_min_max=None)
    if truth is None:
        return
    row["within_min_max"] = False
    if row["found"] and row["range_m"] is not None:
        e = row["range_m"] - truth
        row.update(range_error_m=e, abs_error_m=abs(e), rel_error=abs(e) / truth,
                   within_min_max=bool(row["range_min_m"] <= truth <= row["range_max_m"]))


def run(paths, camera: Camera, target: Target, settings: HilProxSettings, truths=None, truth_source: str = "none",
        log=None) -> list[ImageResult]:
    """Process every image (one bad image is reported through ``log`` and the others run)."""
    paths = [Path(p) for p in paths]
    truths = truths if truths is not None else [None] * len(paths)
    log = log or (lambda m: print(m, file=sys.stderr))
    out = []
    for i, (p, t) in enumerate(zip(paths, truths)):
        r = process_image(i, p, camera, target, settings, t, truth_source if t is not None else "none")
        if r.error:
            log(f"dualsight: {p}: {r.error}")
        out.append(r)
    return out


# ============================================================================================ tables
SCHEMA = pa.schema([
    ("image", pa.string()), ("path", pa.string()), ("image_index", pa.int32()), ("error", pa.string()),
    ("threshold", pa.float64()), ("invert", pa.bool_()), ("open_px", pa.int32()), ("close_px", pa.int32()),
    ("border_px", pa.int32()), ("undistort", pa.bool_()), ("estimator", pa.string()), ("blob", pa.string()),
    ("area_curve", pa.string()),
    ("width", pa.int32()), ("height", pa.int32()), ("channels", pa.int32()), ("bit_depth", pa.int32()),
    ("full_scale", pa.float64()),
    ("found", pa.bool_()), ("n_blobs", pa.int32()), ("n_foreground", pa.int64()), ("n_pixels", pa.int64()),
    ("n_blob", pa.float64()), ("cob_x_px", pa.float64()), ("cob_y_px", pa.float64()),
    ("unit_x", pa.float64()), ("unit_y", pa.float64()), ("unit_z", pa.float64()),
    ("major_px", pa.float64()), ("minor_px", pa.float64()), ("axis_ratio", pa.float64()), ("angle_rad", pa.float64()),
    ("area_rel_min", pa.float64()), ("area_rel_est", pa.float64()), ("area_rel_max", pa.float64()),
    ("range_min_m", pa.float64()), ("range_m", pa.float64()), ("range_max_m", pa.float64()),
    ("pos_x_m", pa.float64()), ("pos_y_m", pa.float64()), ("pos_z_m", pa.float64()),
    ("box_x0", pa.int32()), ("box_y0", pa.int32()), ("box_x1", pa.int32()), ("box_y1", pa.int32()),
    ("touches_edge", pa.bool_()),
    ("truth_range_m", pa.float64()), ("truth_source", pa.string()), ("range_error_m", pa.float64()),
    ("abs_error_m", pa.float64()), ("rel_error", pa.float64()), ("within_min_max", pa.bool_()),
    ("target", pa.string()), ("A0_m2", pa.float64()), ("camera_fx_px", pa.float64()), ("camera_fy_px", pa.float64()),
    ("t_read_ns", pa.int64()), ("t_prep_ns", pa.int64()), ("t_blob_ns", pa.int64()),
])


def table(results: list[ImageResult]) -> pa.Table:
    """The run's ``hil_prox`` table: one row per image x threshold (one per unreadable image)."""
    rows = [r for res in results for r in res.rows]
    cols = {f.name: pa.array([row.get(f.name) for row in rows], type=f.type) for f in SCHEMA}
    return pa.table(cols, schema=SCHEMA)


def _memory_con(tbl: pa.Table, run_id: str):
    import duckdb

    con = duckdb.connect(":memory:")
    con.register("_hil_prox_rows", tbl)
    rid = run_id.replace("'", "''")
    con.execute(f"CREATE VIEW hil_prox AS SELECT *, '{rid}' AS run FROM _hil_prox_rows")
    return con


def report(tbl: pa.Table, name: str = "hil_prox_sweep", run_id: str = "-") -> tuple[list[str], list[tuple]]:
    """Run a ``warehouse/sql/hil_prox_*.sql`` report over an in-memory run table (the same SQL the lake
    is queried with)."""
    from dualsight.warehouse.query import run_report

    return run_report(_memory_con(tbl, run_id), name, run=run_id)


def sweep_summary(results_or_table, run_id: str = "-") -> list[dict]:
    """The sweep rows (warehouse/sql/hil_prox_sweep.sql) as dicts, one per threshold."""
    tbl = results_or_table if isinstance(results_or_table, pa.Table) else table(results_or_table)
    cols, rows = report(tbl, "hil_prox_sweep", run_id)
    return [dict(zip(cols, r)) for r in rows]


def best_threshold(sweep: list[dict]) -> dict | None:
    """The sweep row with the smallest average relative error (None without truth)."""
    ok = [s for s in sweep if s.get("avg_rel_error_pct") is not None]
    return min(ok, key=lambda s: s["avg_rel_error_pct"]) if ok else None


# ============================================================================================ lake
def default_run_id(lake) -> str:
    """``hil-prox-<UTC timestamp>`` (see :meth:`Lake.new_run_id`)."""
    return lake.new_run_id("hil-prox")


def check_run(lake, run_id: str, spec: dict):
    """Refuse to overwrite a run of another kind or with other settings/images (before any work)."""
    lake.refuse_other_run(run_id, NAME, spec)


def write_run(lake, run_id: str, results: list[ImageResult], spec: dict, elapsed_s: float,
              tbl: pa.Table | None = None) -> dict:
    """Write the run's shard (atomic, ``Lake.write_shard``) and its manifest (kind ``hil_prox``)."""
    import socket

    from dualsight.jobs.runner import versions

    tbl = tbl if tbl is not None else table(results)
    rows = lake.write_shard(run_id, 0, {NAME: tbl}, primary=PRIMARY)
    n_err = sum(1 for r in results if r.error)
    manifest = {"run_id": run_id, "kind": NAME, "job": NAME, "label": f"hil prox {run_id}", "spec": spec,
                "seed": None, "n_cases": len(results), "shard_size": max(1, len(results)), "n_shards": 1,
                "datasets": DATASETS, "primary": PRIMARY, "versions": versions(), "host": socket.gethostname(),
                "created_unix": time.time(), "shards_done": [0], "status": "complete", "rows": rows,
                "stats": {"images": len(results), "errors": n_err, "thresholds": len(spec["settings"]["thresholds"])},
                "executions": [{"started_unix": time.time() - elapsed_s, "elapsed_s": elapsed_s,
                                "cases_run": len(results)}]}
    lake.write_manifest(manifest)
    return manifest


# ============================================================================================ output
def _r(v, nd=6):
    return None if v is None else round(float(v), nd)


def to_json(res: ImageResult) -> dict:
    """One image as a JSON object (the keys are listed in the module docstring)."""
    out = {"image": res.path.name, "path": str(res.path), "error": res.error, "truth_range_m": res.truth_m,
           "truth_source": res.truth_source, "results": []}
    if res.error:
        return out
    for row in res.rows:
        out["results"].append({
            "threshold": row["threshold"], "found": row["found"], "n_blobs": row["n_blobs"],
            "n_foreground": row["n_foreground"], "n_pixels": row["n_pixels"], "axis_ratio": _r(row["axis_ratio"], 4),
            "cob_px": None if row["cob_x_px"] is None else [_r(row["cob_x_px"], 3), _r(row["cob_y_px"], 3)],
            "unit": None if row["unit_x"] is None else [_r(row[f"unit_{a}"], 6) for a in "xyz"],
            "range_min_m": _r(row["range_min_m"]), "range_m": _r(row["range_m"]), "range_max_m": _r(row["range_max_m"]),
            "error_m": _r(row["range_error_m"]), "abs_error_m": _r(row["abs_error_m"]),
            "rel_error_pct": None if row["rel_error"] is None else round(100 * row["rel_error"], 3),
            "within_min_max": row["within_min_max"], "touches_edge": row["touches_edge"]})
    return out


def json_document(results, sweep, *, run_id, camera: Camera, target: Target, settings: HilProxSettings) -> dict:
    clean = [{k: (_r(v, 6) if isinstance(v, float) else v) for k, v in s.items()} for s in sweep]
    return {"run": run_id, "camera": camera.to_dict(), "target": target.to_dict(), "settings": settings.to_dict(),
            "images": [to_json(r) for r in results], "sweep": clean, "best": best_threshold(clean)}


def text_report(results, sweep, settings: HilProxSettings) -> str:
    """Per-image table (one threshold) or per-image table at the best threshold + the sweep table."""
    from dualsight.warehouse.query import format_table

    best = best_threshold(sweep)
    show_t = settings.thresholds[0] if len(settings.thresholds) == 1 else (
        best["threshold"] if best else settings.thresholds[len(settings.thresholds) // 2])
    out = [f"threshold{'s' if len(settings.thresholds) > 1 else ''} "
           f"{_fmt_thresholds(settings.thresholds)}{' on the inverted image' if settings.invert else ''}; "
           f"open {settings.open_px}, close {settings.close_px}, border {settings.border_px} px"
           f"{', undistorted' if settings.undistort else ''}; {settings.estimator} estimator, {settings.blob} blob", ""]
    rows = []
    for res in results:
        if res.error:
            rows.append([res.path.name, "ERROR: " + res.error] + [None] * 9)
            continue
        row = next(r for r in res.rows if r["threshold"] == show_t)
        rows.append([res.path.name, "found" if row["found"] else "no blob", row["n_pixels"], row["axis_ratio"],
                     res.truth_m, row["range_min_m"], row["range_m"], row["range_max_m"],
                     None if row["rel_error"] is None else 100 * (row["range_m"] - res.truth_m) / res.truth_m,
                     row["within_min_max"], row["touches_edge"]])
    out.append(f"per image at threshold {show_t:g}" + (" (the sweep's best)" if len(settings.thresholds) > 1 and best
                                                      else ""))
    out.append(format_table(["image", "status", "N_blob px", "axis ratio", "true m", "min m", "est m", "max m",
                             "error %", "in [min,max]", "edge"], rows, floatfmt="{:.4g}"))
    if len(settings.thresholds) > 1 or any(s.get("with_truth") for s in sweep):
        out += ["", "sweep (reference Figure 8): per threshold, over the images"]
        keys = ["threshold", "found", "avg_range_m", "avg_range_min_m", "avg_range_max_m", "avg_truth_m",
                "avg_abs_error_m", "avg_rel_error_pct", "within_min_max_pct"]
        out.append(format_table(["T", "found", "avg est m", "avg min m", "avg max m", "avg true m", "avg |err| m",
                                 "avg rel err %", "within %"], [[s.get(k) for k in keys] for s in sweep],
                                floatfmt="{:.4g}"))
        if best:
            out.append(f"best threshold {best['threshold']:g}: average residual {best['avg_abs_error_m']:.4g} m "
                       f"({best['avg_rel_error_pct']:.2f} %), true range inside [min, max] for "
                       f"{best['within_min_max_pct']:.0f} % of the images")
    return "\n".join(out)


def _fmt_thresholds(th) -> str:
    if len(th) == 1:
        return f"{th[0]:g}"
    return f"{th[0]:g}..{th[-1]:g} ({len(th)})"


def plot(results: list[ImageResult], sweep: list[dict], path: Path, title: str = "") -> Path:
    """Figure 8 of the reference (viz/threshold_sweep.py) from a run's results."""
    from dualsight.viz.threshold_sweep import threshold_sweep_figure

    th = np.array(sorted({r["threshold"] for res in results for r in res.rows if r.get("threshold") is not None}))
    good = [res for res in results if not res.error]
    idx = {t: i for i, t in enumerate(th)}
    est, lo, hi = (np.full((len(good), len(th)), np.nan) for _ in range(3))
    for i, res in enumerate(good):
        for row in res.rows:
            j = idx[row["threshold"]]
            for arr, key in ((est, "range_m"), (lo, "range_min_m"), (hi, "range_max_m")):
                arr[i, j] = np.nan if row[key] is None else row[key]
    truth = np.array([np.nan if r.truth_m is None else r.truth_m for r in good])
    return threshold_sweep_figure(path, th, est, lo, hi, truth, labels=[r.path.name for r in good], sweep=sweep,
                                  title=title)


# ============================================================================================ CLI
def add_parser(hsub) -> argparse.ArgumentParser:
    """Add ``hil prox`` to the ``hil`` group's sub-parsers (jobs/cli_hil.py)."""
    from dualsight.jobs.cli import _lake_arg

    p = hsub.add_parser("prox", help="the proximity blobber on real photos of a target (range vs threshold)",
                        description="Threshold real photos of a target (any channel >= T, optionally inverted, "
                                    "opened and closed) and run the simulations' blobber on them: direction and "
                                    "range by Eq. 1 with the target's projected-area table; a threshold sweep "
                                    "gives the reference's Figure 8.")
    p.add_argument("images", nargs="+", type=Path, help="image files (PNG, JPEG, TIFF, FITS) or folders of them")
    p.add_argument("--camera", type=Path, required=True, help="camera file (TOML with a [camera] table)")
    p.add_argument("--target", type=Path, required=True,
                   help="target model: a satellite TOML (examples/targets/), for its projected-area table")
    g = p.add_argument_group("image processing (reference Sec. 2.4)")
    g.add_argument("--invert", action="store_true", help="dark object on a light background: v -> full scale - v")
    th = g.add_mutually_exclusive_group()
    th.add_argument("--threshold", type=float, default=None,
                    help=f"binary threshold in image units: foreground if ANY channel >= T (default {DEFAULT_THRESHOLD:g})")
    th.add_argument("--sweep", default=None, help="threshold sweep A:B:STEP (B included), e.g. 200:250:5")
    g.add_argument("--open", type=int, default=0, dest="open_px", help="opening with a K x K square, px (0: off)")
    g.add_argument("--close", type=int, default=0, dest="close_px",
                   help="closing with a K x K square, px (0: off); applied after the opening")
    g.add_argument("--border", type=int, default=0, dest="border_px",
                   help="force the outer PX pixels of the frame to background (default 0)")
    g.add_argument("--undistort", action="store_true",
                   help="remap each image to the ideal pinhole (same fx, fy, cx, cy) before thresholding")
    b = p.add_argument_group("blobber")
    b.add_argument("--estimator", choices=list(ESTIMATORS), default="paper",
                   help="paper: Eq. 1 as printed (default); subpixel: the blobber's refined estimator")
    b.add_argument("--blob", choices=list(TARGETS), default="largest",
                   help="largest blob (default) or all foreground pixels as one blob")
    b.add_argument("--area-curve", choices=["min", "mean", "max", "median", "relopt"], default=None,
                   help="area curve for the estimate (default: mean for paper, relopt for subpixel)")
    b.add_argument("--min-pixels", type=int, default=1, help="smallest target blob, px (default 1)")
    b.add_argument("--table-samples", type=int, default=20000,
                   help="random orientations of the projected-area table (default 20000)")
    t = p.add_argument_group("truth")
    t.add_argument("--range-truth", default=None, metavar="M|FILE",
                   help="true range: metres for every image, a JSON {image: metres}, or a camera file from "
                        "`dualsight calibrate` (its [[calibration.views]] distance_m per image)")
    o = p.add_argument_group("output")
    o.add_argument("--json", action="store_true", help="print one JSON object (images, sweep, best)")
    _lake_arg(o)
    o.add_argument("--run", default=None, help="run id (default hil-prox-<UTC timestamp>)")
    o.add_argument("--no-lake", action="store_true", help="do not write to the lake")
    o.add_argument("--plot", type=Path, default=None,
                   help="write the reference's Figure 8 (range with min/max bars against threshold) as PNG")
    p.set_defaults(func=cmd_hil_prox)
    return p


def settings_from_args(args) -> HilProxSettings:
    if args.sweep is not None:
        ths = parse_sweep(args.sweep)
    else:
        ths = (args.threshold if args.threshold is not None else DEFAULT_THRESHOLD,)
    if args.min_pixels < 1:
        raise ConfigError(f"must be >= 1, got {args.min_pixels}", field="--min-pixels")
    return HilProxSettings(thresholds=ths, invert=args.invert, open_px=args.open_px, close_px=args.close_px,
                           border_px=args.border_px, undistort=args.undistort, estimator=args.estimator,
                           blob=args.blob, area_curve=args.area_curve, min_pixels=args.min_pixels,
                           table_samples=args.table_samples)


def cmd_hil_prox(args) -> int:
    t_start = time.perf_counter()
    settings = settings_from_args(args)
    camera = Camera.from_toml(args.camera)
    paths = expand_inputs(args.images)
    if not paths:
        raise InputError("no image files given", source="IMAGES")
    truths, truth_kind = load_range_truth(args.range_truth, paths)
    target = load_target(args.target, settings)

    lake = run_id = None
    spec = {"camera": camera.to_dict(), "camera_file": str(args.camera), "target": target.to_dict(),
            "settings": settings.to_dict(), "range_truth": args.range_truth, "images": [str(p) for p in paths]}
    if not args.no_lake:
        from dualsight.jobs.cli import _lake

        lake = _lake(args)
        run_id = args.run or default_run_id(lake)
        check_run(lake, run_id, spec)                        # before any work: nothing written on refusal

    results = run(paths, camera, target, settings, truths, truth_kind)
    tbl = table(results)
    sweep = sweep_summary(tbl, run_id or "-")
    elapsed = time.perf_counter() - t_start
    if lake is not None:
        write_run(lake, run_id, results, spec, elapsed, tbl)
    if args.plot is not None:
        plot(results, sweep, args.plot, title=f"{target.name}: {len(paths)} image(s)"
             + (f", run {run_id}" if run_id else ""))
    if args.json:
        print(json.dumps(json_document(results, sweep, run_id=run_id, camera=camera, target=target,
                                       settings=settings), indent=1))
    else:
        print(text_report(results, sweep, settings))
    n_err = sum(1 for r in results if r.error)
    msg = (f"{len(results)} images x {len(settings.thresholds)} threshold(s): {n_err} could not be processed "
           f"({elapsed:.1f} s)")
    if lake is not None:
        msg += (f"; run {run_id} in {lake.root} (dataset hil_prox)\n"
                f"query: dualsight sql \"SELECT * FROM hil_prox WHERE run = '{run_id}'\" --lake {lake.root}")
    if args.plot is not None:
        msg += f"\nfigure: {args.plot}"
    print(msg, file=sys.stderr)
    return 1 if n_err else 0


__all__ = ["HilProxSettings", "parse_sweep", "score_image", "binarize", "clear_border", "morphology",
           "undistort_image", "foreground_masks", "Target", "load_target", "load_range_truth", "expand_inputs",
           "ImageResult", "process_image", "run", "table", "report", "sweep_summary", "best_threshold",
           "write_run", "check_run", "default_run_id", "to_json", "json_document", "text_report", "plot",
           "add_parser", "cmd_hil_prox"]
