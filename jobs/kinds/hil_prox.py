"""Job kind ``hil_prox``: the SIL blobber on real photos of a target (reference Sec. 2.4).

Processing of every image, for every threshold T (the reference's, in this order; scene/segment.py):

1. read the file (scene.imageio: PNG, JPEG, TIFF, FITS; 8/16-bit or float; mono or RGB; alpha dropped);
2. optional ``undistort``: remap to the ideal pinhole with the same fx, fy, cx, cy; pixels from outside
   the frame are filled with the background value (full scale when inverted, else 0); the blobber then
   uses the camera without distortion;
3. optional ``invert`` (a dark object on a light background): v -> full_scale - v per channel;
4. binary threshold: foreground when ANY colour channel is >= T (image units: 0-255 for 8-bit data,
   0-65535 for 16-bit, 0-1 for float images);
5. optional ``border_px``: the outer pixels of the frame to background (frame-grabber edges);
6. optional opening (``open_px``) then closing (``close_px``) with K x K squares (K <= 1: off);
7. the blobber (:func:`dualsight.nav.blobber.run_blobber`, the very code of the simulations) on the binary
   images (1.0 / 0.0, blobber threshold 0.5), batched over the thresholds of one image: the target is the
   **largest** 8-connected blob (``blob = "largest"``) or every foreground pixel (``"all"``); its
   centroid -> unit vector; its axis ratio -> the target's projected-area table -> A_min, A_est, A_max ->
   range by Eq. 1 (``estimator = "paper"``: rho = f sqrt(A / (N p^2)) = mean(fx, fy) sqrt(A / N), so the
   pixel pitch cancels) or the blobber's ``subpixel`` estimator.

Scores against the per-image true range (nav/hil_score.py): ``range_error_m``, ``abs_error_m``,
``rel_error`` (fraction), ``within_min_max``.  The sweep summary (the reference's Figure 8 numbers) is
``warehouse/sql/hil_prox_sweep.sql`` over the lake.

Engine contract (jobs/engine/runner.py): case i = image i.  Datasets: ``hil_prox_cases`` (primary, one row per
image: size, truth, error) and ``hil_prox`` (one row per image x threshold; an image that could not be
read has ONE row there too, with ``error`` set and ``threshold`` NULL).  Lengths in metres, angles in
radians.  Rows are a function of the spec alone (timing columns ``t_*_ns`` excepted).

Spec (``spec_from_dict``; pydantic strict)::

    camera   = {...}                         the [camera] table
    target   = {name, components = [{shape, size, position, orientation_deg}, ...]}   (the area table's input)
    settings = {thresholds = [230.0], invert, open_px, close_px, border_px, undistort, estimator, blob,
                connectivity, area_curve, min_pixels, table_samples, bin_width}
    images   = [{path, bytes, mtime_ns}, ...]
    truths_m = [] or one true range (m, > 0) or null per image;  truth_source = "none"|"value"|"json"|"calibration"

Real-image check (tests/test_hil_prox.py): OpenCV's 13 chessboard photos (a flat plate of known size at
0.27-0.41 m, truth from the calibration's board poses), ``invert, threshold 210, border 6, open 9,
close 61``: errors -21 .. +13 %, median |error| 7.7 %, truth inside [min, max] for 7/13; with the exact
silhouette the same blobber gives -6.5 .. +0.5 %, median 3.9 %, 13/13 inside -- segmentation dominates
(in a cluttered office the closing wide enough to merge the squares also bridges into dark background,
and the palest squares fall below the threshold); a near-frontal plate's axis ratio is also produced by
strongly tilted views (the uniform-orientation table reads ~10 % small in area), perspective at 0.3 m adds
2-16 % pixels (Eq. 1 is orthographic), barrel distortion shrinks the blob by a few %.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import pyarrow as pa
from pydantic import Field, field_validator, model_validator

from dualsight.jobs.kinds.hil_defaults import DEFAULT_THRESHOLD
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.errors import ConfigError, ImageError
from dualsight.config import validate
from dualsight.jobs.kinds.hil_common import Frozen, ImageEntry, check_unchanged, fixed_point, rows_table, spec_base
from dualsight.nav.blobber import BlobberConfig, run_blobber
from dualsight.nav.blobber_names import ESTIMATORS, TARGETS
from dualsight.nav.hil_score import score_range
from dualsight.scene.camera import Camera
from dualsight.scene.imageio import read_image
from dualsight.scene.satellite import load_satellite
from dualsight.scene.segment import foreground_masks, score_image, undistort_image

NAME = "hil_prox"
PRIMARY = "hil_prox_cases"
MAX_THRESHOLDS = 1000
MAX_KERNEL = 1001
_CHUNK = 8            # thresholds per blobber batch (bounds memory: 8 float32 frames)


# ============================================================================================ spec
class ProxSettings(Frozen):
    """Everything that decides how an image is processed (module docstring)."""

    thresholds: tuple[float, ...] = Field(default=(DEFAULT_THRESHOLD,), min_length=1, max_length=MAX_THRESHOLDS)
    invert: bool = False
    open_px: int = Field(default=0, ge=0, le=MAX_KERNEL)
    close_px: int = Field(default=0, ge=0, le=MAX_KERNEL)
    border_px: int = Field(default=0, ge=0, le=10_000)
    roi_px: tuple[int, int, int, int] | None = None
    undistort: bool = False
    estimator: Literal[ESTIMATORS] = "paper"            # type: ignore[valid-type]
    blob: Literal[TARGETS] = "largest"                  # type: ignore[valid-type]
    connectivity: Literal[4, 8] = 8
    area_curve: Literal["min", "mean", "max", "median", "relopt"] | None = None
    min_pixels: int = Field(default=1, ge=1)
    table_samples: int = Field(default=20000, ge=100, le=10_000_000)
    bin_width: float = Field(default=0.05, gt=0, le=1)

    @field_validator("roi_px")
    @classmethod
    def _roi(cls, v):
        if v is not None and not (0 <= v[0] < v[2] <= 65536 and 0 <= v[1] < v[3] <= 65536):
            raise ValueError(f"must be x0,y0,x1,y1 pixels with 0 <= x0 < x1 <= 65536 and 0 <= y0 < y1 <= 65536, got "
                             f"{','.join(map(str, v))}")
        return v

    def blobber_config(self) -> BlobberConfig:
        """The blobber's settings: binary input (1.0 / 0.0) thresholded at 0.5."""
        return BlobberConfig(estimator=self.estimator, threshold=0.5, connectivity=self.connectivity,
                             target=self.blob, area_curve=self.area_curve, min_pixels=self.min_pixels)


class Component(Frozen):
    """One primitive of the target model (catalogs.areas.shape_spec)."""

    shape: str
    size: tuple[float, ...] = Field(min_length=1, max_length=3)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)


class TargetSpec(Frozen):
    """The target model: the shape its projected-area table is built from."""

    name: str = Field(max_length=200)
    components: tuple[Component, ...] = Field(min_length=1, max_length=100)


TrueRange = Annotated[float, Field(gt=0)]


class HilProxSpec(Frozen):
    """A validated ``hil_prox`` run (module docstring)."""

    camera: dict[str, Any]
    target: TargetSpec
    settings: ProxSettings = Field(default_factory=ProxSettings)
    images: tuple[ImageEntry, ...] = Field(min_length=1, max_length=10_000_000)
    truths_m: tuple[TrueRange | None, ...] = ()
    truth_source: Literal["none", "value", "json", "calibration"] = "none"

    @model_validator(mode="after")
    def _truths(self):
        if self.truths_m and len(self.truths_m) != len(self.images):
            raise ValueError(f"truths_m must be empty or have one entry per image ({len(self.images)}), "
                             f"got {len(self.truths_m)}")
        return self

    def truth(self, k: int) -> float | None:
        return self.truths_m[k] if self.truths_m else None


def settings_from_dict(d: dict | None, source: str = "hil prox", section: str | None = None) -> ProxSettings:
    """Validated settings (ConfigError naming ``source`` and the key); the blobber's own checks too."""
    return _check_blobber(validate(ProxSettings, dict(d or {}), source=source, section=section), source, section)


def _check_blobber(s: ProxSettings, source: str, section: str | None) -> ProxSettings:
    """``s`` when the blobber accepts its settings, else a ConfigError naming ``source`` and ``section``."""
    try:
        s.blobber_config()
    except ValueError as e:
        raise ConfigError(str(e), source=source, field=section or "settings") from None
    return s


def spec_from_dict(d: dict, source: str = "spec") -> HilProxSpec:
    """Validate a spec dict (module docstring); every error is a ConfigError naming ``source`` and the key."""
    if not isinstance(d, dict):
        raise ConfigError("must be a table", source=source)
    m = validate(HilProxSpec, d, source=source)
    _check_blobber(m.settings, source, "settings")
    from dualsight.catalogs.areas import shape_spec

    try:
        shape_spec([c.to_dict() for c in m.target.components])
    except ValueError as e:
        raise ConfigError(str(e), source=source, field="target.components") from None
    cam = fixed_point(lambda c: Camera.from_dict(c, source=source).to_dict(), dict(m.camera))
    return m.model_copy(update={"camera": cam})


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


def target_spec(path: str | Path) -> dict:
    """The spec's ``target`` of a satellite TOML (scene/satellite.py): its name and components."""
    from dualsight.catalogs.areas import shape_spec         # pyarrow

    sat = load_satellite(path)
    return {"name": sat.name or Path(path).stem, "components": shape_spec(sat)}


def build_spec(paths, camera: Camera | dict, target: dict, settings: ProxSettings | dict | None = None,
               truths_m: list[float | None] | None = None, truth_source: str = "none") -> dict:
    """A spec dict for ``run_job("hil_prox", ...)`` (images stat'ed now)."""
    return {**spec_base(paths, camera, settings), "target": dict(target), "truths_m": list(truths_m or []),
            "truth_source": truth_source}


# ============================================================================================ context
@dataclass(frozen=True)
class Target:
    """The target model and its projected-area table (catalogs.areas.area_table, cached on disk)."""

    name: str
    components: tuple
    table: object


def make_target(target: TargetSpec | dict, settings: ProxSettings) -> Target:
    from dualsight.catalogs.areas import area_table

    t = target if isinstance(target, TargetSpec) else TargetSpec.model_validate(target)
    comps = [c.to_dict() for c in t.components]
    return Target(t.name, tuple(t.components),
                  area_table(comps, n=settings.table_samples, bin_width=settings.bin_width))


def load_target(path: str | Path, settings: ProxSettings | None = None) -> Target:
    """Read a target model (a satellite TOML) and build its projected-area table."""
    return make_target(target_spec(path), settings or ProxSettings())


@dataclass(frozen=True)
class Context:
    camera: Camera
    target: Target


def make_context(spec: HilProxSpec) -> Context:
    return Context(Camera.from_dict(spec.camera, source="spec"), make_target(spec.target, spec.settings))


def memory_estimate(spec: HilProxSpec) -> int:
    """Peak bytes of one worker, before anything is allocated (the engine refuses a spec over the limit).

    One image at a time, per pixel: the decoded pixels and the undistorted copy (float64, up to 3 channels:
    48 bytes), the foreground score (8) and, for each of the :data:`_CHUNK` thresholds of a blobber batch,
    the binary mask, the blobber's float32 frame and its int32 labels (9 bytes each); plus the projected-area
    table's samples (~64 bytes each)."""
    cam = Camera.from_dict(spec.camera, source="spec")
    return int((48 + 8 + 9 * _CHUNK) * cam.width * cam.height + 64 * spec.settings.table_samples)


# ============================================================================================ computing
def compute_shard(spec: HilProxSpec, case_ids: np.ndarray, ctx: Context) -> dict[str, pa.Table]:
    """The engine's contract: rows of images ``case_ids`` (int64, ascending)."""
    cases, rows = [], []
    for k in np.asarray(case_ids, np.int64):
        k = int(k)
        case, r = process_image(k, spec.images[k], ctx.camera, ctx.target, spec.settings, spec.truth(k),
                                spec.truth_source if spec.truth(k) is not None else "none")
        cases.append(case)
        rows.extend(r)
    return {"hil_prox_cases": rows_table(cases, CASES_SCHEMA), "hil_prox": rows_table(rows, SCHEMA)}


def process_image(k: int, image: ImageEntry | str | Path, camera: Camera, target: Target, settings: ProxSettings,
                  truth_m: float | None = None, truth_source: str = "none") -> tuple[dict, list[dict]]:
    """(``hil_prox_cases`` row, ``hil_prox`` rows: one per threshold, or one error row) of one image.
    ``image`` an :class:`ImageEntry` (checked unchanged since the run was planned) or a plain path."""
    entry = image if isinstance(image, ImageEntry) else None
    path = Path(entry.path if entry is not None else image)
    case = {"case_id": k, "image": path.name, "path": str(path), "error": None, "truth_range_m": truth_m,
            "truth_source": truth_source, "n_thresholds": len(settings.thresholds)}
    base = {"case_id": k, "image": path.name, "path": str(path), "error": None, "truth_range_m": truth_m,
            "truth_source": truth_source, "target": target.name, "A0_m2": target.table.A0_m2,
            "camera_fx_px": camera.fx, "camera_fy_px": camera.fy, "invert": settings.invert,
            "open_px": settings.open_px, "close_px": settings.close_px, "border_px": settings.border_px,
            "undistort": settings.undistort, "estimator": settings.estimator, "blob": settings.blob,
            "area_curve": settings.blobber_config().curve}
    t0 = time.perf_counter_ns()
    try:
        if entry is not None:
            check_unchanged(entry)
        img = read_image(path)
        if (img.width, img.height) != (camera.width, camera.height):
            raise ImageError(f"size {img.width}x{img.height} differs from the camera's {camera.width}x{camera.height}",
                             source=str(path))
    except ImageError as e:
        err = str(e.detail if getattr(e, "detail", None) else e)
        t = time.perf_counter_ns() - t0
        case.update(error=err, t_read_ns=t)
        return case, [dict(base, error=err, t_read_ns=t)]
    t1 = time.perf_counter_ns()
    full = img.full_scale
    pix, cam = img.pixels, camera
    if settings.undistort:
        pix, cam = undistort_image(pix, camera, fill=full if settings.invert else 0.0)
    score = score_image(pix, invert=settings.invert, full_scale=full)
    if settings.roi_px is not None:          # region of interest: everything outside is background
        x0, y0, x1, y1 = settings.roi_px
        inside = np.zeros(score.shape, bool)
        inside[y0:y1, x0:x1] = True
        score[~inside] = -np.inf
    shape = dict(width=img.width, height=img.height, channels=img.channels, bit_depth=img.bit_depth, full_scale=full)
    case.update(shape, t_read_ns=t1 - t0, image_digest=int(to_int64(frame_digest(img.pixels[None]))[0]))
    base.update(shape, t_read_ns=t1 - t0)
    cfg = settings.blobber_config()
    th = settings.thresholds
    W, H, edge = cam.width, cam.height, settings.border_px
    rows = []
    for s in range(0, len(th), _CHUNK):          # chunks of thresholds: one blobber batch each
        tp = time.perf_counter_ns()
        chunk = th[s:s + _CHUNK]
        masks = foreground_masks(score, chunk, border_px=settings.border_px, open_px=settings.open_px,
                                 close_px=settings.close_px)
        n_fg = masks.sum(axis=(1, 2)).astype(np.int64)
        tb = time.perf_counter_ns()
        r = run_blobber(masks, cam, target.table, cfg)
        te = time.perf_counter_ns()
        del masks
        for j, t in enumerate(chunk):
            row = dict(base, threshold=float(t), n_foreground=int(n_fg[j]),
                       t_prep_ns=(tb - tp) // len(chunk), t_blob_ns=(te - tb) // len(chunk))
            row.update(_blob_row(r, j))
            box = r.box[j]
            row["touches_edge"] = bool(row["found"] and (box[0] <= edge or box[1] <= edge or box[2] >= W - 1 - edge
                                                        or box[3] >= H - 1 - edge))
            row.update(score_range(row["found"], row["range_m"], row["range_min_m"], row["range_max_m"], truth_m))
            rows.append(row)
    case["found_any"] = any(r["found"] for r in rows)
    return case, rows


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


# ============================================================================================ tables
CASES_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("path", pa.string()), ("error", pa.string()),
    ("width", pa.int32()), ("height", pa.int32()), ("channels", pa.int32()), ("bit_depth", pa.int32()),
    ("full_scale", pa.float64()), ("image_digest", pa.int64()), ("truth_range_m", pa.float64()),
    ("truth_source", pa.string()),
    ("n_thresholds", pa.int32()), ("found_any", pa.bool_()), ("t_read_ns", pa.int64()),
])

SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("path", pa.string()), ("error", pa.string()),
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

SCHEMAS = {"hil_prox_cases": CASES_SCHEMA, "hil_prox": SCHEMA}
TIMING_COLUMNS = ("t_read_ns", "t_prep_ns", "t_blob_ns")


def shard_summary(tbls: dict[str, pa.Table]) -> dict[str, int]:
    t = tbls["hil_prox_cases"]
    return {"images": t.num_rows, "errors": sum(e is not None for e in t.column("error").to_pylist()),
            "found_any": sum(bool(x) for x in t.column("found_any").to_pylist())}


def progress_postfix(stats: dict) -> str:
    return f"errors {stats.get('errors', 0)}"


__all__ = ["NAME", "PRIMARY", "SCHEMAS", "ProxSettings", "TargetSpec", "HilProxSpec", "settings_from_dict",
           "spec_from_dict", "parse_sweep", "target_spec", "build_spec", "Target", "make_target",
           "load_target", "make_context", "memory_estimate", "compute_shard", "process_image", "shard_summary",
           "progress_postfix"]
