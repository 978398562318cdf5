"""Nightly suites: a TOML list of jobs (or the built-in ``standard`` suite), validated into runnable specs.

Layout (every error names the file, the key as ``job.<i>.<key>`` and what is allowed)::

    name = "quick"
    alpha = 0.01               # family-wise false-alarm rate per night, split over the night's tests (Bonferroni)
    throughput_min_s = 5.0     # a run shorter than this gets no throughput verdict (start-up dominates)

    [[job]]
    name = "star_paper"        # [a-z][a-z0-9_]{0,29}; run ids are nightly-<night>-<name>[.fresh]
    kind = "star"              # star | star_track | prox_sweep | prox_trajectory | hil_star | hil_prox
    spec = "paper"             # a preset name, a TOML file (the keys of that job's --config) or an inline table
    cases = 2000               # star: cases; star_track: sequences; prox_sweep: ranges x orientations;
                               # prox_trajectory: frames
    seed = 1                   # the fixed seed (default: the spec's)
    fresh_cases = 2000         # the fresh-seed sample's cases (default: = cases; 0: none)

    [[job]]                    # hardware in the loop: the images are the cases (no seed, no fresh sample)
    name = "hil_star_esa"
    kind = "hil_star"
    images = "{shared}/data/real/esa_tetra3/*.tiff"      # a folder, a glob or one file
    camera = "examples/cameras/esa_tetra3.toml"
    truth = "{shared}/data/real/esa_tetra3/truth.json"   # optional plate-solved truth file
    spec = {}                  # the settings table of `hil star --config` (method, [catalog], [voting], ...)

    [[job]]
    name = "hil_prox_chessboard"
    kind = "hil_prox"
    images = "{shared}/data/real/opencv_chessboard"
    target = "examples/targets/opencv_chessboard.toml"
    calibrate = { board = [9, 6], square_m = 0.025 }     # camera and per-image true range from these photos
    # or: camera = "FILE.toml" and range_truth = 0.33 | "truth.json" | "camera-from-calibrate.toml"
    spec = { thresholds = [210.0], invert = true, border_px = 6, open_px = 9, close_px = 61 }

Paths: ``{shared}`` is ``$DUALSIGHT_SHARED`` or the ``shared`` folder beside the repository; a relative path
is looked up beside the suite file, then in the repository.  A HIL job whose images or truth are absent is
*skipped* with the reason (never an error), so the same suite runs where the real data is not installed.
"""

from __future__ import annotations

import copy
import glob
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from dualsight.config import validate
from dualsight.errors import ConfigError
from dualsight.jobs.engine.specs import deep_merge, preset_and_config
from dualsight.jobs.kinds.hil_truth import load_range_truth, resolve_star_truths
from dualsight.scene.imageio import list_images
from dualsight.scene.calibration import calibrate_chessboard
from dualsight.scene.camera import Camera, read_toml
from dualsight.scene.skytruth import load_truth_json
from dualsight.scene.timescale import observation_epoch

REPO = Path(__file__).resolve().parents[2]
MC_KINDS = ("star", "star_track", "prox_sweep", "prox_trajectory")
SEQUENCE_KINDS = ("star", "star_track")
"""Monte Carlo kinds whose case count is the number of cases itself (no sweep grid, no trajectory frames)."""
HIL_KINDS = ("hil_star", "hil_prox")
KINDS = MC_KINDS + HIL_KINDS
MAX_SUITE_CASES = 10**7

TRACK_SPEC = {"preset": "paper", "sequence": {"frames": 50, "motion": "mixed", "rate_max_deg_s": 1.0,
                                             "blinded": 1, "dropped": 1}}
"""The nightly's star-tracking campaign (issue 22, point 5): the paper preset's camera and sensor, sequences of 50
frames at the default 10 frames/s, constant rates and slews up to 1 deg/s, one blinded and one dropped frame each
(so that re-acquisition is exercised every night)."""

STANDARD = {
    "name": "standard",
    "alpha": 0.01,
    "throughput_min_s": 5.0,
    "job": [
        {"name": "star_paper", "kind": "star", "spec": "paper", "cases": 20000, "seed": 1},
        {"name": "star_noisy", "kind": "star", "spec": "examples/star/noisy_sensor.toml", "cases": 2000, "seed": 7},
        {"name": "star_track_paper", "kind": "star_track", "spec": TRACK_SPEC, "cases": 200, "seed": 1},
        {"name": "prox_sweep_accurate", "kind": "prox_sweep", "spec": "accurate", "cases": 3300, "seed": 1},
        {"name": "prox_trajectory", "kind": "prox_trajectory", "spec": "paper", "seed": 1},
        {"name": "hil_star_esa", "kind": "hil_star", "images": "{shared}/data/real/esa_tetra3/*.tiff",
         "camera": "examples/cameras/esa_tetra3.toml", "truth": "{shared}/data/real/esa_tetra3/truth.json"},
        {"name": "hil_prox_chessboard", "kind": "hil_prox", "images": "{shared}/data/real/opencv_chessboard",
         "target": "examples/targets/opencv_chessboard.toml", "calibrate": {"board": [9, 6], "square_m": 0.025},
         "spec": {"thresholds": [210.0], "invert": True, "border_px": 6, "open_px": 9, "close_px": 61}},
    ],
}
"""The built-in standard suite (`dualsight nightly`): the star paper preset at 20,000 cases, the noisy sensor
example at 2,000, a star-tracking campaign of 200 sequences (:data:`TRACK_SPEC`), the accurate proximity sweep
(11 ranges x 300 orientations), the reference trajectory, and
the HIL star (ESA frames) and HIL proximity (OpenCV chessboard) jobs when ../shared has the photos."""


class _Calibrate(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    board: tuple[int, int] = (9, 6)
    square_m: float = Field(0.025, gt=0, le=10)


class JobTable(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str = Field(pattern=r"^[a-z][a-z0-9_]{0,29}$")
    kind: Literal[KINDS]                                   # type: ignore[valid-type]
    spec: str | dict | None = None
    cases: int | None = Field(None, ge=1, le=MAX_SUITE_CASES)
    seed: int | None = Field(None, ge=0, le=2**63 - 1)
    fresh_cases: int | None = Field(None, ge=0, le=MAX_SUITE_CASES)
    images: str | None = None
    camera: str | None = None
    truth: str | None = None
    target: str | None = None
    calibrate: _Calibrate | None = None
    range_truth: float | str | None = None


class SuiteTable(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str = Field("suite", max_length=100)
    alpha: float = Field(0.01, gt=0, le=0.2)
    throughput_min_s: float = Field(5.0, ge=0, le=3600)
    job: tuple[JobTable, ...] = Field(min_length=1, max_length=100)


@dataclass
class Job:
    """One job of a suite: ``make(seed, cases) -> (spec dict, n_cases)`` builds its run's spec."""

    name: str
    kind: str
    n_cases: int
    seed: int | None
    fresh_cases: int
    spec: dict                          # the fixed run's spec dict (validated)
    raw: dict = field(default_factory=dict, repr=False)     # MC kinds: the merged dict before seed/cases
    skip: str | None = None             # why the job is skipped (HIL data absent)
    source: str = ""

    def make(self, seed: int | None = None, cases: int | None = None) -> tuple[dict, int]:
        """The spec and case count of this job's run with another seed / case count (MC kinds)."""
        if self.kind in HIL_KINDS or (seed is None and cases is None):
            return self.spec, self.n_cases
        return _mc_spec(self.kind, self.raw, cases or self.n_cases, seed if seed is not None else self.seed,
                        self.source)


@dataclass
class Suite:
    name: str
    source: str
    alpha: float
    throughput_min_s: float
    jobs: list[Job]


def shared_root() -> Path:
    env = os.environ.get("DUALSIGHT_SHARED")
    return Path(env) if env else REPO.parent / "shared"


def _resolve(text: str, base: Path) -> Path:
    """A suite path: ``{shared}`` expanded; relative = beside the suite file, else in the repository."""
    p = Path(text.replace("{shared}", str(shared_root())))
    if p.is_absolute():
        return p
    for cand in (base / p, REPO / p):
        if cand.exists() or glob.glob(str(cand)):
            return cand
    return base / p


def load_suite(which: str | Path | None) -> Suite:
    """``standard`` (built-in, the default), ``quick`` (examples/nightly/quick.toml) or a suite TOML file."""
    name = str(which) if which is not None else "standard"
    if name == "standard":
        return build_suite(copy.deepcopy(STANDARD), source="suite standard (built-in)", base=REPO)
    path = REPO / "examples" / "nightly" / "quick.toml" if name == "quick" else Path(name)
    return build_suite(read_toml(path), source=str(path), base=path.resolve().parent)


def build_suite(doc: dict, *, source: str, base: Path) -> Suite:
    top = validate(SuiteTable, doc, source=source)
    names = [j.name for j in top.job]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"job names must be unique; {dup[0]!r} appears twice", source=source, field="job.name")
    jobs = [_job(j, i, source, base) for i, j in enumerate(top.job)]
    return Suite(top.name, source, top.alpha, top.throughput_min_s, jobs)


def _job(j: JobTable, i: int, source: str, base: Path) -> Job:
    at = f"job.{i}"
    if j.kind in MC_KINDS:
        for key in ("images", "camera", "truth", "target", "calibrate", "range_truth"):
            if getattr(j, key) is not None:
                raise ConfigError(f"is for hil_star / hil_prox jobs only, not {j.kind}", source=source,
                                  field=f"{at}.{key}")
        raw = _mc_raw(j, at, source, base)
        spec, n = _mc_spec(j.kind, raw, j.cases, j.seed, source, at)
        fresh = n if j.fresh_cases is None else j.fresh_cases
        if fresh:
            _mc_spec(j.kind, raw, fresh, 0, source, f"{at}.fresh_cases")
        return Job(j.name, j.kind, n, spec.get("seed"), fresh, spec, raw, source=source)
    for key in ("cases", "seed", "fresh_cases"):
        if getattr(j, key) is not None:
            raise ConfigError(f"not allowed for {j.kind}: the images are the cases (no random inputs, no fresh "
                              "sample)", source=source, field=f"{at}.{key}")
    if j.images is None:
        raise ConfigError("is required for hil jobs (a folder, a glob or one image file)", source=source,
                          field=f"{at}.images")
    if j.spec is not None and not isinstance(j.spec, dict):
        raise ConfigError("must be an inline table of settings for hil jobs", source=source, field=f"{at}.spec")
    paths, why = _images(j.images, base)
    if why is None and j.truth is not None and not _resolve(j.truth, base).is_file():
        why = f"truth file {_resolve(j.truth, base)} not found"
    build = _hil_star if j.kind == "hil_star" else _hil_prox
    if why is not None:
        build(j, [], at, source, base, check_only=True)
        return Job(j.name, j.kind, 0, None, 0, {}, skip=why, source=source)
    spec = build(j, paths, at, source, base)
    return Job(j.name, j.kind, len(paths), None, 0, spec, source=source)


def _images(text: str, base: Path) -> tuple[list[Path], str | None]:
    p = _resolve(text, base)
    if any(c in str(p) for c in "*?["):
        paths = [Path(x) for x in sorted(glob.glob(str(p)))]
    elif p.is_dir():
        paths = list_images(p)
    else:
        paths = [p] if p.is_file() else []
    return paths, (None if paths else f"no images at {p} (real data not installed)")


# ============================================================================================ Monte Carlo specs
def _mc_module(kind: str):
    from dualsight.jobs.kinds import prox, star, star_track          # Taichi

    return {"star": star, "star_track": star_track}.get(kind, prox)


def _mc_raw(j: JobTable, at: str, source: str, base: Path) -> dict:
    mod = _mc_module(j.kind)
    spec = j.spec if j.spec is not None else "paper"
    preset, config, inline = None, None, {}
    if isinstance(spec, str) and spec.endswith(".toml"):
        config = _resolve(spec, base)
        if not config.is_file():
            raise ConfigError(f"file {config} not found (a preset name, a TOML file or an inline table)",
                              source=source, field=f"{at}.spec")
    elif isinstance(spec, str):
        preset = spec
    else:
        inline = {k: v for k, v in spec.items() if k != "preset"}
        preset = spec.get("preset")
    if preset is not None and preset not in mod.PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; known presets of {j.kind}: {', '.join(sorted(mod.PRESETS))}",
                          source=source, field=f"{at}.spec")
    d, _ = preset_and_config(mod.PRESETS, preset, config)
    sat = d.get("satellite")
    if config is not None and isinstance(sat, str) and not Path(sat).is_absolute() and (config.parent / sat).exists():
        d["satellite"] = str(config.parent / sat)          # as `prox sweep --config`: relative to that file
    d = deep_merge(d, inline)
    if j.kind not in SEQUENCE_KINDS:
        d["job"] = "sweep" if j.kind == "prox_sweep" else "trajectory"
    d["_source"] = str(config) if config is not None else f"{source} {at}.spec"
    d["_at"] = at
    return d


def _mc_spec(kind: str, raw: dict, cases: int | None, seed: int | None, source: str, at: str | None = None):
    """(canonical spec dict, n_cases) of a Monte Carlo job with this seed and case count."""
    mod = _mc_module(kind)
    at = at or raw.get("_at", "job")
    d = {k: v for k, v in copy.deepcopy(raw).items() if not k.startswith("_")}
    src = raw.get("_source", source)
    cases_field = at if at.endswith("cases") else f"{at}.cases"
    if seed is not None:
        d["seed"] = int(seed)
    if kind in SEQUENCE_KINDS:
        n = cases if cases is not None else d.get("cases", 200)
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SUITE_CASES:
            raise ConfigError(f"must be an integer in [1, {MAX_SUITE_CASES:,}], got {n!r}", source=source,
                              field=cases_field)
        spec = mod.spec_from_dict(d, source=src)
        return spec.to_dict(), int(n)
    if cases is not None:
        if kind == "prox_sweep":
            ranges = d.get("ranges_m") or []
            if not ranges or cases % len(ranges):
                raise ConfigError(f"must be a multiple of the sweep's {len(ranges)} ranges (ranges x orientations), "
                                  f"got {cases}", source=source, field=cases_field)
            d["orientations"] = cases // len(ranges)
        else:
            d["frames"] = int(cases)
    spec = mod.spec_from_dict(d, source=src)
    return spec.to_dict(), int(spec.n_cases)


# ============================================================================================ HIL specs
def _hil_star(j: JobTable, paths, at: str, source: str, base: Path, check_only: bool = False) -> dict:
    from dualsight.jobs.kinds import hil_star as hs       # Taichi
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table

    if j.camera is None:
        raise ConfigError("is required for hil_star jobs (a camera TOML file)", source=source, field=f"{at}.camera")
    for key in ("target", "calibrate", "range_truth"):
        if getattr(j, key) is not None:
            raise ConfigError("is for hil_prox jobs only", source=source, field=f"{at}.{key}")
    camera = Camera.from_toml(_resolve(j.camera, base))
    epoch = (observation_epoch(paths, None) if paths else None) or 2000.0
    settings = settings_from_table(j.spec or None, source=f"{source} [{at}.spec]", mag_limit=7.0,
                                   epoch_jyear=epoch, tolerance_arcsec=20.0, max_stars=25, k_sigma=5.0,
                                   min_pixels=3)
    if check_only:
        return {}
    truth = load_truth_json(_resolve(j.truth, base)) if j.truth is not None else None
    return hs.build_spec(paths, camera, settings, resolve_star_truths(paths, truth, None))


def _hil_prox(j: JobTable, paths, at: str, source: str, base: Path, check_only: bool = False) -> dict:
    from dualsight.jobs.kinds import hil_prox as hp      # Taichi

    if j.truth is not None:
        raise ConfigError("is for hil_star jobs; hil_prox takes range_truth or calibrate", source=source,
                          field=f"{at}.truth")
    if j.target is None:
        raise ConfigError("is required for hil_prox jobs (a target TOML, e.g. examples/targets/...)", source=source,
                          field=f"{at}.target")
    if (j.camera is None) == (j.calibrate is None):
        raise ConfigError("give exactly one of camera (a camera TOML) and calibrate (a table: board, square_m)",
                          source=source, field=f"{at}.camera")
    if j.calibrate is not None and j.range_truth is not None:
        raise ConfigError("calibrate already gives the true ranges; drop range_truth", source=source,
                          field=f"{at}.range_truth")
    settings = hp.settings_from_dict(j.spec or {}, source=source, section=f"{at}.spec")
    target = hp.target_spec(_resolve(j.target, base))
    if check_only:
        return {}
    if j.calibrate is not None:          # deterministic: the solver runs single-threaded (scene/calibration)
        res = calibrate_chessboard(paths, board=j.calibrate.board, square_m=j.calibrate.square_m)
        dist = {v.path.name: float(v.distance_m) for v in res.views}
        camera, truths, kind = res.camera, [dist.get(p.name) for p in paths], "calibration"
    else:
        camera = Camera.from_toml(_resolve(j.camera, base))
        rt = j.range_truth
        if isinstance(rt, str):
            rt = str(_resolve(rt, base))
        truths, kind = load_range_truth(rt, paths)
    return hp.build_spec(paths, camera, target, settings, truths, kind)
