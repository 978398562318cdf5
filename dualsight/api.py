"""The Python API for scripts and notebooks (docs/api.md): three entry points over the command line's own code.

    solve(image, camera, **settings) -> Solution   one frame identified lost in space: ``dualsight hil star``'s chain
    Lake(path).runs() / .sql(query)                 what ``dualsight runs`` lists; ``dualsight sql``, as an Arrow table
    run(kind, spec, cases=..., seed=..., lake=...)  a Monte Carlo run into a lake: ``dualsight star run``,
                                                    ``prox sweep``, ``prox trajectory``, ``selftest run``

Nothing here is an algorithm, a check or a rule of its own.  ``solve`` normalises its camera and settings with
``hil_star_spec.normalise_run`` (as every ``hil_star`` spec is), its defaults are the ``hil star`` command's own
(read from its argument parser), and it runs ``hil_star.read_frame`` and ``hil_star.solve_frames``, the calls
of every image of a ``hil star`` run.  ``Lake.sql`` is ``warehouse.query.run_sql_arrow`` (the read-only statement
gate of ``dualsight sql``), ``Lake.runs`` is ``warehouse.lake.run_records`` (what ``dualsight runs`` prints), and
``run`` is the kind module's ``plan_run`` + ``start_run`` (``jobs.kinds.star``, ``prox``, ``selftest``: what
``dualsight star run``, ``prox sweep``/``trajectory`` and ``selftest run`` call).

Errors are dualsight's own (``dualsight.errors``: InputError and its ConfigError, ImageError; the lake's
LakeError and the engine's EngineError are InputErrors too), each with a one-line message naming the argument,
file or key and what is allowed.  The root package exposes these names lazily (``dualsight.solve``, ...).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from dualsight.errors import ConfigError, ImageError, InputError
from dualsight.jobs.cli.hil_star import add_star_parser
from dualsight.jobs.cli.hil_star_settings import settings_from_args
from dualsight.scene.camera import Camera, read_toml
from dualsight.scene.timescale import observation_epoch
from dualsight.scene.units import ARCSEC
from dualsight.warehouse.paths import check_run_id, default_lake

if TYPE_CHECKING:                                   # heavy modules: imported where used
    import pandas
    import pyarrow

    from dualsight.warehouse.lake import RunRecord

__all__ = ["solve", "Solution", "Star", "Timings", "Lake", "run", "SOLVE_SETTINGS", "RUN_KINDS"]


# ============================================================================================ solve
@dataclass(frozen=True)
class Star:
    """One identified star of a :class:`Solution` (a row of the reference's Table 6).

    Pixel coordinates are continuous, from the image's top-left corner (the top-left pixel's centre is
    (0.5, 0.5)); x along columns, y along rows.
    """

    x_px: float                  # detection centroid, column (px)
    y_px: float                  # detection centroid, row (px)
    hip: int                     # Hipparcos catalog number
    vmag: float                  # catalog Johnson V magnitude
    ra_deg: float                # catalog position (ICRS, at the catalog epoch), degrees
    dec_deg: float
    pred_x_px: float             # where the solved attitude projects the catalog star (px)
    pred_y_px: float
    residual_arcsec: float       # angle between the detection's direction and the catalog star, solved attitude
    flux: float                  # detected flux (ADU)
    sigma_px: float | None       # centroid uncertainty per axis (px; Cramér-Rao), None with detector "global"
    votes: int                   # votes of the identification


@dataclass(frozen=True)
class Timings:
    """CPU time of the stages of one :func:`solve`, milliseconds (wall clock, this process)."""

    read_ms: float | None        # decoding the file (None for an array)
    detect_ms: float             # background, detection and centroids
    identify_ms: float           # back-projection and lost-in-space voting
    attitude_ms: float           # SVD attitude
    total_ms: float              # the sum of the above


@dataclass(frozen=True, eq=False)
class Solution:
    """The answer of :func:`solve` for one frame.

    ``attitude`` is the (3, 3) float64 rotation that maps ICRS unit vectors into the camera frame (+x along
    columns, +y along rows, +z out through the lens; its rows are the camera axes in ICRS), read-only; None
    (and None angles) when the frame was not identified.  ``status`` is "success" when it was identified (at
    least 3 stars, a match threshold T > 0 and an attitude; ``hil star`` calls this "identified" when it has no
    truth to score against) and "no_solution" otherwise.  ``row`` is the ``hil_star`` lake row this frame
    would have in a ``hil star`` run without truth (SI units: radians, nanoseconds), read-only.
    """

    status: str
    attitude: np.ndarray | None      # (3, 3) ICRS -> camera
    ra_deg: float | None             # boresight (camera +z) right ascension, ICRS, degrees in [0, 360)
    dec_deg: float | None            # boresight declination, degrees
    roll_deg: float | None           # position angle of the image's "up" (camera -y), north through east, [0, 360)
    stars: tuple[Star, ...]          # the identified stars, in the order of their detections
    T: int                           # the voting's match threshold (0: no answer)
    p_chance: float | None           # probability that the answer is a chance match
    residual_median_arcsec: float | None
    residual_max_arcsec: float | None
    residual_rms_arcsec: float | None
    stars_detected: int
    stars_used: int                  # detections that voted in the answering round
    method: str                      # "robust" or "paper"
    detector: str                    # "local" or "global"
    image: str                       # the file's name, or "<array>"
    timings: Timings
    row: Mapping[str, Any]

    @property
    def identified(self) -> bool:
        """Whether the frame was identified (``status == "success"``)."""
        return self.status == "success"

    @property
    def residuals_arcsec(self) -> np.ndarray:
        """(S,) float64: every identified star's residual (arcsec), in the order of :attr:`stars`."""
        return np.array([s.residual_arcsec for s in self.stars], np.float64)

    @property
    def hip(self) -> np.ndarray:
        """(S,) int64: the identified stars' Hipparcos numbers."""
        return np.array([s.hip for s in self.stars], np.int64)

    @property
    def xy_px(self) -> np.ndarray:
        """(S, 2) float64: the identified stars' detection centroids (x = column, y = row; px)."""
        return np.array([(s.x_px, s.y_px) for s in self.stars], np.float64).reshape(-1, 2)


SOLVE_SETTINGS = {
    # keyword: (the hil star option's argparse dest, accepted types, what is allowed)
    "method": ("method", (str,), "'robust' or 'paper' (--method)"),
    "detector": ("detector", (str,), "'local' or 'global' (--detector)"),
    "mag_limit": ("mag_limit", (int, float, str), "catalog V limit, a number or 'auto' (--mag-limit)"),
    "epoch": ("epoch", (int, float), "catalog epoch, Julian year (--epoch)"),
    "time": ("time", (str,), "UTC time of the image, ISO 8601, for the catalog epoch (--time)"),
    "tolerance_arcsec": ("tolerance_arcsec", (int, float), "voting tolerance, arcsec (--tolerance-arcsec)"),
    "max_stars": ("max_stars", (int,), "brightest detections that vote (--max-stars)"),
    "k_sigma": ("k_sigma", (int, float), "detection threshold, noise sigmas (--k-sigma)"),
    "min_pixels": ("min_pixels", (int,), "smallest blob, px (--min-pixels)"),
    "background_block": ("background_block", (int,), "background block, px, 0 = off (--background-block)"),
    "compare": ("no_compare", (bool,), "also run the other voting method (hil star's default; not reported)"),
    "config": ("config", (str, os.PathLike, Mapping), "a TOML file or a table of hil star --config's layout"),
}
"""The keyword settings of :func:`solve`: the options of ``dualsight hil star`` that decide how a frame is
processed, under their option names; unset ones take that command's defaults."""

_SOURCE = "dualsight.solve"
_CONTEXTS: dict[str, Any] = {}
_MAX_CONTEXTS = 4


def solve(image: str | os.PathLike | np.ndarray, camera: str | os.PathLike | Camera | Mapping,
          **settings: Any) -> Solution:
    """Identify one star image lost in space and solve its attitude, with ``dualsight hil star``'s chain.

    Parameters
    ----------
    image : an image file (PNG, JPEG, TIFF, FITS; colour is converted to gray, 16-bit files holding shifted
        12-bit values are shifted back, as ``hil star`` reads them), or a 2-D (H, W) numpy array of ADC counts
        of any integer or float dtype (uint8, uint16, float32 and float64 go in as they are, other integers as
        float64, float16 as float32: the detector gives the same answer for the same values in any of them).
        Values at ``2**camera.bit_depth - 1`` and above count as saturated.
    camera : a camera file (TOML with a ``[camera]`` table, e.g. examples/cameras/esa_tetra3.toml), a
        :class:`dualsight.scene.camera.Camera`, or a ``[camera]`` table as a dict.  Its width and height must
        be the image's.
    **settings : the options of ``hil star`` that decide how a frame is processed (:data:`SOLVE_SETTINGS`):
        ``method``, ``detector``, ``mag_limit``, ``epoch`` or ``time``, ``tolerance_arcsec``, ``max_stars``,
        ``k_sigma``, ``min_pixels``, ``background_block``, ``compare``, ``config``.  Unset ones are that
        command's defaults: robust voting, local detector, automatic magnitude limit, 20 arcsec, 25 stars,
        5 sigma, 3 px, 32 px blocks; the catalog epoch is the time in the file's name (ESA-style names), else
        J2000.0.  ``compare`` (default False here) also runs the other voting method, which changes nothing
        in the answer.

    Returns
    -------
    :class:`Solution`: attitude (3, 3) ICRS -> camera, boresight RA/Dec and roll (deg), identified stars
    (pixels, HIP numbers, V magnitudes, residuals in arcsec), T, p_chance, per-stage times (ms).

    Raises
    ------
    ImageError (unreadable file, wrong size, shape, dtype or non-finite pixels), ConfigError (camera file or
    settings), InputError: one line each.  The catalogs are built into the cache on first use.
    """
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.kinds.hil_common import ImageEntry, image_entries
    from dualsight.jobs.kinds.hil_star_spec import StarTruth, normalise_run

    cam = _camera(camera)
    if isinstance(image, np.ndarray):
        frame, path = _frame(image, cam), None
    elif isinstance(image, (str, os.PathLike)):
        frame, path = None, os.fspath(image)
    else:
        raise ImageError(f"must be an image file path or a 2-D numpy array, got {type(image).__name__}",
                         source="image")
    args, table = _settings_args(settings)
    epoch = args.epoch if args.epoch is not None else (
        observation_epoch([path] if path is not None else [], args.time) or 2000.0)
    cam_table, st = normalise_run(cam.to_dict(), settings_from_args(args, table, epoch), source=_SOURCE,
                                  n_images=1)
    ctx = _context(cam_table, st)
    rt = ctx.rt
    t_read = None
    if path is not None:
        entry = ImageEntry(**image_entries([path])[0])
        if entry.bytes is None:
            raise ImageError("file not found", source=entry.path)
        t0 = time.perf_counter_ns()
        frame, _ = hs.read_frame(entry, rt.camera)
        t_read = time.perf_counter_ns() - t0
        name, where = entry.name, entry.path
    else:
        name, where = "<array>", None
    res = hs.ImageResult(0, hs.base_row(0, name, where, rt, StarTruth()))
    hs.solve_frames(frame[None], [res], [StarTruth()], ctx, n_images=1,
                    t_read_ns=None if t_read is None else [t_read])
    return _solution(res)


def _camera(camera) -> Camera:
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, (str, os.PathLike)):
        return Camera.from_toml(Path(camera))
    if isinstance(camera, Mapping):
        return Camera.from_dict(dict(camera), source="camera table")
    raise ConfigError(f"must be a camera file (TOML), a Camera or a [camera] table, got {type(camera).__name__}",
                      source="camera")


def _frame(a: np.ndarray, cam: Camera) -> np.ndarray:
    """The (H, W) ADC counts the detector takes, from any 2-D integer or float array (solve's docstring)."""
    if a.ndim != 2:
        raise ImageError(f"must be a 2-D (H, W) array of ADC counts, got shape {a.shape}", source="image")
    if a.shape != (cam.height, cam.width):
        raise ImageError(f"is {a.shape[1]} x {a.shape[0]} px, the camera says {cam.width} x {cam.height}",
                         source="image")
    kind = a.dtype.kind
    if kind not in "uif":
        raise ImageError(f"must hold integer or float pixel values, got dtype {a.dtype}", source="image")
    if a.dtype in (np.uint8, np.uint16, np.float32, np.float64):
        out = a
    elif kind == "f":                                   # float16: exact in float32; longer floats: float64
        out = a.astype(np.float32 if a.dtype.itemsize < 4 else np.float64)
    else:                                               # other integers: exact in float64 up to 2^53
        lo, hi = (int(a.min()), int(a.max())) if a.size else (0, 0)
        if not (-2**53 <= lo and hi <= 2**53):
            raise ImageError(f"values {lo} .. {hi} are beyond 2^53 (not exact as float64)", source="image")
        out = a.astype(np.float64)
    if out.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(out)))
        if bad:
            raise ImageError(f"has {bad} non-finite pixels (NaN or infinity)", source="image")
    return np.ascontiguousarray(out)


def _settings_args(settings: dict) -> tuple[argparse.Namespace, dict | None]:
    """The ``hil star`` command's parsed defaults with the keyword settings laid over them, and the config
    table (None without one)."""
    unknown = sorted(set(settings) - set(SOLVE_SETTINGS))
    if unknown:
        raise ConfigError(f"unknown setting {unknown[0]!r}; known: {', '.join(SOLVE_SETTINGS)}", source=_SOURCE)
    args = _cli_defaults()
    table = None
    for key, value in settings.items():
        dest, types, allowed = SOLVE_SETTINGS[key]
        if value is None:
            continue
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            raise ConfigError(f"must be {allowed}, got {value!r}", source=_SOURCE, field=key)
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"must be a finite number, got {value!r}", source=_SOURCE, field=key)
        if key == "compare":
            value = not value
        elif key == "config":
            # settings_from_args names the config in its messages by args.config: the file, or this label
            table = dict(value) if isinstance(value, Mapping) else read_toml(Path(value))
            value = Path(value) if not isinstance(value, Mapping) else f"{_SOURCE} config table"
        setattr(args, dest, value)
    if args.config is None:
        args.config = _SOURCE
    for key in ("method", "detector"):                  # as hil star: an option and the config must agree
        if settings.get(key) is not None and table and key in table and table[key] != settings[key]:
            raise ConfigError(f"{key}={settings[key]!r} contradicts {key} = {table[key]!r} in the config",
                              source=_SOURCE, field=key)
    return args, table


def _cli_defaults() -> argparse.Namespace:
    """The defaults of ``dualsight hil star`` (its own argument parser), with the comparison method off."""
    args = argparse.Namespace(**vars(_parsed_defaults()))
    args.no_compare = True
    return args


@functools.lru_cache(maxsize=1)
def _parsed_defaults() -> argparse.Namespace:
    parser = argparse.ArgumentParser(add_help=False)
    return add_star_parser(parser.add_subparsers()).parse_args(["<image>", "--camera", "<camera>"])


def _context(cam_table: dict, settings) -> Any:
    """The star and pair catalogs of a camera and settings, kept for the next frames (the last few)."""
    from dualsight.jobs.kinds import hil_star as hs

    key = json.dumps([cam_table, settings.to_dict()], sort_keys=True)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        if len(_CONTEXTS) >= _MAX_CONTEXTS:
            _CONTEXTS.clear()
        ctx = _CONTEXTS[key] = hs.context_of(hs.runtime_of(cam_table, settings))
    return ctx


def _solution(res) -> Solution:
    """The :class:`Solution` of a filled ``hil_star`` result (row and stars)."""
    r = res.row
    ok = bool(r["identified"])
    A = None
    if ok:
        A = np.array(r["A_est"], np.float64).reshape(3, 3)
        A.setflags(write=False)

    def arcsec(key):
        v = r.get(key)
        return None if v is None else float(v) / ARCSEC

    def ms(key):
        v = r.get(key)
        return None if v is None else v / 1e6

    stars = tuple(Star(x_px=s.x_px, y_px=s.y_px, hip=s.hip, vmag=s.vmag, ra_deg=math.degrees(s.ra_rad),
                       dec_deg=math.degrees(s.dec_rad), pred_x_px=s.pred_x_px, pred_y_px=s.pred_y_px,
                       residual_arcsec=s.residual_rad / ARCSEC, flux=s.flux, sigma_px=s.sigma_px, votes=s.votes)
                  for s in res.stars)
    timings = Timings(read_ms=ms("t_read_ns"), detect_ms=ms("t_detect_ns"), identify_ms=ms("t_identify_ns"),
                      attitude_ms=ms("t_attitude_ns"), total_ms=ms("t_total_ns"))
    return Solution(status="success" if ok else "no_solution", attitude=A,
                    ra_deg=math.degrees(r["ra_rad"]) if ok else None,
                    dec_deg=math.degrees(r["dec_rad"]) if ok else None,
                    roll_deg=float(r["roll_deg"]) if ok else None, stars=stars, T=int(r["T"]),
                    p_chance=r.get("p_chance"), residual_median_arcsec=arcsec("residual_median_rad"),
                    residual_max_arcsec=arcsec("residual_max_rad"), residual_rms_arcsec=arcsec("residual_rms_rad"),
                    stars_detected=int(r["stars_detected"]), stars_used=int(r["stars_used"]), method=r["method"],
                    detector=r["detector"], image=r["image"], timings=timings, row=MappingProxyType(dict(r)))


# ============================================================================================ Lake
class Lake:
    """A dualsight lake (``<path>/<dataset>/run=<id>/part-*.parquet`` and manifests), read-only.

    ``path`` defaults to ``$DUALSIGHT_LAKE`` or ``./lake``, as on the command line; nothing is created or
    written.  Damaged files and manifests are left out of every answer and named through ``warn`` (default:
    a Python ``UserWarning`` each), as ``dualsight sql`` names them on stderr.
    """

    def __init__(self, path: str | os.PathLike | None = None, *, warn: Callable[[str], None] | None = None):
        if path is not None and not isinstance(path, (str, os.PathLike)):
            raise InputError(f"must be a folder path, got {type(path).__name__}", source="lake")
        self._path = Path(path) if path is not None else None
        self._warn = warn

    @property
    def root(self) -> Path:
        """The lake's folder."""
        return self._store().root

    def runs(self) -> list[RunRecord]:
        """What ``dualsight runs`` lists: every run that has a manifest, sorted by run id, as
        :class:`dualsight.warehouse.lake.RunRecord` (run_id, kind, n_cases, shards, status, seed, spec_hash,
        problems, manifest; ``damaged`` when the manifest is)."""
        from dualsight.warehouse.lake import run_records

        return run_records(self._store())

    def sql(self, query: str, *, pandas: bool = False, timeout: float | None = 300.0,
            memory_limit: int | str | None = None) -> pyarrow.Table | pandas.DataFrame:
        """The result of a read-only DuckDB query over the lake's views (one per dataset, e.g. ``star_cases``,
        ``hil_star``; column ``run`` holds the run id) as a ``pyarrow.Table`` with DuckDB's column types;
        with ``pandas=True`` a ``pandas.DataFrame`` (needs pandas).

        Exactly what ``dualsight sql`` runs: SELECT and EXPLAIN only, over the verified shard files, with
        DuckDB's file, network and extension access and configuration changes off; several statements run
        in order and the last one's result is returned.  InputError (one line) for anything else, an SQL
        error, or ``pandas=True`` without pandas.

        The limits of ``dualsight sql`` hold, without its row cap: ``timeout`` seconds (default 300; 0 or None
        for none; past it the query is stopped and ``QueryTimeout``, an InputError, raised), ``memory_limit``
        for DuckDB and for the Arrow result (bytes, ``"4GB"``, ``"25%"`` of the RAM; default half the RAM;
        nothing spills to disk).  A KeyboardInterrupt (Ctrl-C) interrupts the query and is raised again.
        """
        from dualsight.warehouse.query import SqlLimits, run_sql_arrow

        limits = SqlLimits(timeout, memory_limit, timeout_name="timeout=SECONDS", memory_name="memory_limit=")
        found: list[str] = []
        try:
            table = run_sql_arrow(self._store(), query, warn=self._warn or found.append, limits=limits)
        finally:
            for message in found:                       # named at the caller's line
                warnings.warn(f"dualsight: {message}", UserWarning, stacklevel=2)
        if not pandas:
            return table
        try:
            import pandas as _pandas  # noqa: F401  (Table.to_pandas needs it)
        except ImportError:
            raise InputError("pandas is not installed (pip install pandas); without pandas=True the result is a "
                             "pyarrow Table", source="pandas") from None
        return table.to_pandas()

    def _store(self):
        from dualsight.warehouse.lake import Lake as Store

        return Store(self._path if self._path is not None else default_lake())

    def __fspath__(self) -> str:
        return os.fspath(self.root)

    def __repr__(self) -> str:
        return f"dualsight.Lake({os.fspath(self.root)!r})"



# ============================================================================================ run
RUN_KINDS = ("star", "star_track", "prox_sweep", "prox_trajectory", "selftest", "rendezvous")
"""Job kinds :func:`run` starts: the Monte Carlo jobs the command line starts from a preset, a config and a seed
(``dualsight star run``, ``star track``, ``prox sweep``, ``prox trajectory``, ``selftest run``).  The hardware-in-the-loop kinds
(hil_star, hil_prox, calibrate) take images, not cases: :func:`solve` covers one image, the command line a run."""


def _kind_functions(kind: str) -> tuple[Mapping, Callable, Callable]:
    """(presets, plan, start) of a job kind of :data:`RUN_KINDS`: the one table :func:`run` dispatches through,
    the kind module's own functions, which its command calls too (``plan(preset, config, seed=, cases=,
    run_id=)`` -> a plan with ``run_id``; ``start(plan, lake, workers=, scheduler=, shard_size=, progress=)``)."""
    from dualsight.jobs.kinds import prox, rendezvous, rendezvous_spec, selftest, star, star_track  # Taichi, pyarrow

    table = {
        "star": (star.PRESETS, star.plan_run, star.start_run),
        "star_track": (star_track.PRESETS, star_track.plan_run, star_track.start_run),
        "prox_sweep": (prox.PRESETS, functools.partial(prox.plan_run, job="sweep"), prox.start_run),
        "prox_trajectory": (prox.PRESETS, functools.partial(prox.plan_run, job="trajectory"), prox.start_run),
        "selftest": (selftest.PRESETS, selftest.plan_run, selftest.start_run),
        "rendezvous": (rendezvous_spec.PRESETS, rendezvous.plan_run, rendezvous.start_run),
    }
    return table[kind]


def run(kind: str, spec: str | os.PathLike | Mapping | None = None, *, cases: int | None = None,
        seed: int | None = None, lake: Lake | str | os.PathLike | None = None, run_id: str | None = None,
        workers: int | None = None, scheduler: str | None = None, shard_size: int | None = None,
        progress: bool = False) -> str:
    """Run (or resume) a Monte Carlo job into a lake, exactly as its command does; returns the run id.

    Parameters
    ----------
    kind : the job kind (:data:`RUN_KINDS`) and the command it is:

        - ``"star"``: the star-tracker Monte Carlo, ``dualsight star run``;
        - ``"star_track"``: star tracking over image sequences (one sequence a case), ``dualsight star track``;
        - ``"prox_sweep"``: the proximity range sweep (ranges x random orientations), ``dualsight prox sweep``;
        - ``"prox_trajectory"``: the proximity trajectory, frame by frame, ``dualsight prox trajectory``;
        - ``"selftest"``: the engine's self-test job, ``dualsight selftest run``;
        - ``"rendezvous"``: approaches to a target with relative navigation (presets "far", "close"),
          ``dualsight rendezvous run``.

        Not the hardware-in-the-loop kinds (hil_star, hil_prox, calibrate): they take images, not cases
        (:func:`solve` identifies one image; a run over many is the command line's ``dualsight hil star``,
        ``hil prox``, ``calibrate``).
    spec : a preset name of the kind (star: "paper", "noisy", "ideal", "realistic"; prox: "paper", "accurate";
        selftest: "default"), a TOML file of the command's ``--config`` layout, or a dict of that layout (a table
        over the kind's default preset, or over the one it names with ``"preset"``); None: the default preset
        (paper; selftest: default).  The commands' other flags are keys of that layout (prox: ``ranges_m``,
        ``orientations``, ``frames``, ``mode``, ``satellite``; selftest: ``sleep_ms``).
    cases : number of cases, 1 .. 1e9 (default: the spec's: 200 for star, ranges x orientations or frames for
        prox, 1000 for selftest).  A prox sweep runs ranges x orientations cases, so ``cases`` must be a multiple
        of the number of ranges (it sets the orientations per range); a trajectory's cases are its frames.
    seed : run seed, 0 .. 2^63 - 1 (default: the spec's); case i draws from ``default_rng([seed, i])``.
    lake : a :class:`Lake`, a folder, or None for ``$DUALSIGHT_LAKE`` / ``./lake``.
    run_id : default the command's: ``star-<seed>-<cases>-<first 8 hex digits of the spec hash>``,
        ``prox-<sweep|trajectory>-<mode>-<seed>-<cases>``, ``selftest-<spec hash>``; an existing id with the
        same spec resumes it (shards kept are verified, the rest computed), with another spec is refused.
    workers : local worker processes (default one per core; they are spawned, so a script calling run()
        needs ``if __name__ == "__main__":``); 1 runs in this process.
    scheduler, shard_size : as ``--scheduler`` (a Dask address) and ``--shard-size``.
    progress : a progress bar on stderr.

    The run's identity is the command line's: the same spec, cases and code give the same spec hash, run id
    and rows as e.g. ``dualsight star run --preset <p> --cases <n> --seed <s>`` or ``dualsight prox sweep
    --preset <p> --orientations <n / ranges> --seed <s>``.  Errors: InputError (ConfigError, the lake's
    LakeError, the engine's EngineError), one line each; Ctrl-C raises KeyboardInterrupt and the completed
    shards are kept (the same call resumes).
    """
    if kind not in RUN_KINDS:
        raise InputError(f"unknown or unsupported job kind {kind!r}; dualsight.run starts {', '.join(RUN_KINDS)} "
                         "(hil_star, hil_prox and calibrate take images: dualsight.solve for one, the command line "
                         "for a run)", source="kind")
    presets, plan_run, start_run = _kind_functions(kind)
    preset, config = _spec_layers(spec, presets)
    cases = _int_arg(cases, "cases", 1, 10**9)
    seed = _int_arg(seed, "seed", 0, 2**63 - 1)
    workers = _int_arg(workers, "workers", 1, 512)
    shard_size = _int_arg(shard_size, "shard_size", 1, 10**6)
    if run_id is not None:
        try:
            check_run_id(run_id)
        except InputError as e:
            raise InputError(e.detail, source="run_id") from None
    if scheduler is not None and not isinstance(scheduler, str):
        raise InputError(f"must be a Dask scheduler address such as tcp://host:8786, got {scheduler!r}",
                         source="scheduler")
    if lake is not None and not isinstance(lake, (Lake, str, os.PathLike)):
        raise InputError(f"must be a dualsight.Lake or a folder path, got {type(lake).__name__}", source="lake")
    store = lake._store() if isinstance(lake, Lake) else Lake(lake)._store()
    plan = plan_run(preset, config, seed=seed, cases=cases, run_id=run_id)
    start_run(plan, store, workers=workers, scheduler=scheduler, shard_size=shard_size, progress=bool(progress))
    return plan.run_id


def _spec_layers(spec, presets: Mapping) -> tuple[str | None, Path | dict | None]:
    """(preset, config) of ``run``'s ``spec``: a preset name, a TOML file or a table (None: the default preset)."""
    if spec is None:
        return None, None
    if isinstance(spec, Mapping):
        return None, dict(spec)
    if isinstance(spec, str) and spec in presets:
        return spec, None
    if isinstance(spec, (str, os.PathLike)):
        path = Path(spec)
        if isinstance(spec, str) and not path.exists() and path.suffix.lower() != ".toml" and os.sep not in spec:
            raise ConfigError(f"unknown preset {spec!r}; known presets: {', '.join(sorted(presets))} (or give a "
                              "TOML file or a dict)", source="spec")
        return None, path
    raise ConfigError(f"must be a preset name, a TOML file path or a dict, got {type(spec).__name__}", source="spec")


def _int_arg(value, name: str, lo: int, hi: int) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InputError(f"must be an integer in [{lo}, {hi:,}], got {value!r}", source=name)
    return int(value)
