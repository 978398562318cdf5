"""Import a peer solver's per-frame answers into the lake as dataset ``peer_star`` (one run per import).

    dualsight peer import ANSWERS.json [--method cedar-solve] [--run ID] [--lake DIR]     (jobs/cli/peer.py)

A peer (cedar-solve, through ``benchmarks/bench_peers.py``; never a dependency of dualsight) solves the same
frames as ``dualsight hil star``; its answers become rows that SQL joins to ``hil_star`` frame by frame on
``path`` (the absolute image path, as ``hil_star`` stores it) or on ``image`` (the file name)::

    SELECT h.image, h.identified, p.solved, h.ra_rad, p.ra_rad
    FROM hil_star h JOIN peer_star p USING (path)
    WHERE h.run = 'hil-star-...' AND p.run = 'peer-star-...'

Answers file (JSON; keys not listed are refused, numbers must be finite)::

    {"method": "cedar-solve",            (optional when --method is given; they must agree when both are)
     "method_version": "0.5.1",          (optional)
     "settings": {...},                  (optional, free-form: the peer's database, options; kept in the spec)
     "environment": {...},               (optional, free-form: versions, threads, setup times)
     "frames": [{
        "path": "/abs/frame.tiff",       (absolute, or relative to the answers file's folder)
        "solved": true,
        "status": "MATCH_FOUND",         (optional: the peer's own word)
        "error": null,                   (optional: why the frame could not be processed)
        "ra_deg": 230.66, "dec_deg": 11.03,   boresight, ICRS, deg   } given together, or only A:
        "roll_deg": 27.72,               (optional) dualsight's roll: position angle of the image's "up"
                                         (decreasing row) from north through east (scene/pointing.py)
        "A": [9 numbers],                (optional) ICRS -> camera rotation, row-major, dualsight's camera
                                         axes (+x increasing column, +y increasing row, +z boresight)
        "stars_detected": 23, "stars_matched": 22, "prob_false_match": 2e-38,
        "time_ms": 47.8, "detect_ms": 44.4, "solve_ms": 3.3,
        "fov_deg": 11.42, "residual_rms_arcsec": 6.1     (all optional)
     }, ...]}

A solved frame needs its boresight (``ra_deg`` and ``dec_deg``, or ``A``); an unsolved frame has none of
``ra_deg``, ``dec_deg``, ``roll_deg``, ``A``.  When both ``A`` and RA/Dec (or roll) are given they must agree
to :data:`AGREE_ARCSEC` (a swapped RA/Dec or a roll in another convention is refused, naming the frame).
Every problem is one :class:`~dualsight.errors.InputError` naming the file and the field, and the lake is
left as it was.

The run.  An import is a run like every other: manifest (kind ``peer_star``, spec = method, version,
settings, environment and the frames' answers themselves, spec hash over them and the code version),
shards written atomically with their identity in the Parquet metadata, a journal, an identity copy and the
run's lock (warehouse/lake.py), so ``dualsight runs`` lists it, ``dualsight sql`` reads it and
``dualsight lake check`` verifies it.  The default run id is ``peer-star-<spec hash>``: importing the same
file again changes nothing; another file under an existing id is refused.  The module also has the job-kind
contract of jobs/engine/runner.py (``NAME``, ``PRIMARY``, ``SCHEMAS``, ``spec_from_dict``, ``make_context``,
``compute_shard``: the rows are a function of the spec alone), so listing it in ``JOB_KINDS`` would let
``lake check --repair`` recompute a damaged shard; until then a damaged peer run is re-imported.
Angles are stored in radians (``*_rad``) except the rolls (``roll_deg``), as in ``hil_star``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from pydantic import Field, field_validator, model_validator

from dualsight.errors import InputError, read_user_file
from dualsight.config import validate
from dualsight.jobs.kinds.hil_common import Frozen, rows_table
from dualsight.scene.attitude import radec_to_unit, unit_to_radec
from dualsight.scene.pointing import roll_deg as roll_of
from dualsight.scene.units import ARCSEC, DEG, angle_between

NAME = "peer_star"
PRIMARY = "peer_star"
AGREE_ARCSEC = 1.0
"""Largest disagreement allowed between a frame's ``A`` and its RA/Dec (boresight) or roll, arcsec."""
MAX_FRAMES = 100_000
MAX_FILE_BYTES = 256 * 2**20

__all__ = ["NAME", "PRIMARY", "SCHEMAS", "PeerFrame", "PeerSpec", "load_answers", "spec_from_dict", "make_context",
           "compute_shard", "n_cases", "import_answers"]


# ============================================================================================ spec
class PeerFrame(Frozen):
    """One frame's answer (module docstring)."""

    path: str = Field(min_length=1, max_length=4096)
    solved: bool
    status: str | None = Field(default=None, max_length=200)
    error: str | None = Field(default=None, max_length=2000)
    ra_deg: float | None = Field(default=None, ge=0.0, le=360.0)
    dec_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    roll_deg: float | None = Field(default=None, ge=-360.0, le=360.0)
    A: tuple[float, ...] | None = None
    stars_detected: int | None = Field(default=None, ge=0, le=10**7)
    stars_matched: int | None = Field(default=None, ge=0, le=10**7)
    prob_false_match: float | None = Field(default=None, ge=0.0)
    time_ms: float | None = Field(default=None, ge=0.0)
    detect_ms: float | None = Field(default=None, ge=0.0)
    solve_ms: float | None = Field(default=None, ge=0.0)
    fov_deg: float | None = Field(default=None, gt=0.0, lt=180.0)
    residual_rms_arcsec: float | None = Field(default=None, ge=0.0)

    @field_validator("A")
    @classmethod
    def _rotation(cls, v):
        from dualsight.jobs.kinds.hil_star_spec import check_rotation     # Taichi (the detectors' configs)

        return check_rotation(v)

    @model_validator(mode="after")
    def _consistent(self):
        attitude = [k for k in ("ra_deg", "dec_deg", "roll_deg", "A") if getattr(self, k) is not None]
        if not self.solved:
            if attitude:
                raise ValueError(f"an unsolved frame has no attitude; remove {', '.join(attitude)} or set solved "
                                 "to true")
            return self
        if (self.ra_deg is None) != (self.dec_deg is None):
            raise ValueError("ra_deg and dec_deg are given together")
        if self.ra_deg is None and self.A is None:
            raise ValueError("a solved frame needs its boresight: ra_deg and dec_deg, or A")
        if self.A is not None:
            A = self.matrix()
            if self.ra_deg is not None:
                d = float(angle_between(A[2], radec_to_unit(self.ra_deg * DEG, self.dec_deg * DEG))) / ARCSEC
                if d > AGREE_ARCSEC:
                    raise ValueError(f"A's boresight is {d:.1f} arcsec from ra_deg/dec_deg (at most {AGREE_ARCSEC:g}"
                                     " allowed): RA and Dec swapped, or A in another convention?")
            if self.roll_deg is not None:
                d = abs((float(roll_of(A)) - self.roll_deg + 180.0) % 360.0 - 180.0) * 3600.0
                if d > AGREE_ARCSEC:
                    raise ValueError(f"roll_deg differs from A's roll by {d:.1f} arcsec (at most {AGREE_ARCSEC:g} "
                                     "allowed): roll_deg is the position angle of the image's up from north "
                                     "through east")
        return self

    def matrix(self) -> np.ndarray | None:
        return None if self.A is None else np.asarray(self.A, np.float64).reshape(3, 3)


_METHOD = r"[A-Za-z0-9._+-]{1,64}"


class AnswersFile(Frozen):
    """The answers file (module docstring)."""

    method: str | None = Field(default=None, pattern=f"^{_METHOD}$")
    method_version: str | None = Field(default=None, max_length=200)
    settings: dict[str, Any] = Field(default_factory=dict)
    environment: dict[str, Any] = Field(default_factory=dict)
    frames: tuple[PeerFrame, ...] = Field(min_length=1, max_length=MAX_FRAMES)


class PeerSpec(Frozen):
    """A validated ``peer_star`` run: the answers with absolute paths and the answers file's digest."""

    method: str = Field(pattern=f"^{_METHOD}$")
    method_version: str | None = None
    settings: dict[str, Any] = Field(default_factory=dict)
    environment: dict[str, Any] = Field(default_factory=dict)
    answers_sha256: str | None = None
    frames: tuple[PeerFrame, ...] = Field(min_length=1, max_length=MAX_FRAMES)

    @field_validator("frames")
    @classmethod
    def _absolute(cls, v):
        for i, f in enumerate(v):
            if not os.path.isabs(f.path):
                raise ValueError(f"frame {i}: path must be absolute in a spec, got {f.path!r}")
        return v


def load_answers(path, *, method: str | None = None) -> PeerSpec:
    """The validated spec of an answers file; ``method`` (``--method``) names the peer when the file does
    not, and must agree with it when it does.  InputError (one line, naming the file and the field)."""
    path = Path(path)
    data = read_user_file(path, InputError, what="JSON answers file", max_bytes=MAX_FILE_BYTES)
    try:
        raw = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise InputError("is not UTF-8 text; give a JSON answers file", source=str(path)) from None
    except json.JSONDecodeError as e:
        raise InputError(f"is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})", source=str(path)) \
            from None
    if not isinstance(raw, dict):
        raise InputError("must be a JSON object with a 'frames' list", source=str(path))
    f = validate(AnswersFile, raw, source=str(path))
    if method is not None and f.method is not None and method != f.method:
        raise InputError(f"--method {method} contradicts method = {f.method!r} in the file", source=str(path),
                         field="method")
    name = f.method or method
    if name is None:
        raise InputError("names no method; add \"method\": \"<peer name>\" or give --method", source=str(path),
                         field="method")
    base = path.resolve().parent
    frames = tuple(fr.model_copy(update={"path": fr.path if os.path.isabs(fr.path)
                                         else os.path.normpath(os.path.join(base, fr.path))}) for fr in f.frames)
    seen: dict[str, int] = {}
    for i, fr in enumerate(frames):
        if fr.path in seen:
            raise InputError(f"frame {i} repeats the path of frame {seen[fr.path]} ({fr.path})", source=str(path),
                             field=f"frames.{i}.path")
        seen[fr.path] = i
    return spec_from_dict({"method": name, "method_version": f.method_version, "settings": f.settings,
                           "environment": f.environment, "answers_sha256": hashlib.sha256(data).hexdigest(),
                           "frames": [fr.to_dict() for fr in frames]}, source=str(path))


def spec_from_dict(d: dict, source: str = "spec") -> PeerSpec:
    """Validate a spec dict (ConfigError naming ``source`` and the key)."""
    return validate(PeerSpec, d, source=source)


def n_cases(spec: PeerSpec) -> int:
    return len(spec.frames)


def make_context(spec: PeerSpec):
    return None


# ============================================================================================ rows
_MAT9 = pa.list_(pa.float64(), 9)
PEER_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("path", pa.string()),
    ("method", pa.string()), ("method_version", pa.string()),
    ("solved", pa.bool_()), ("status", pa.string()), ("error", pa.string()),
    ("ra_rad", pa.float64()), ("dec_rad", pa.float64()), ("roll_deg", pa.float64()), ("A_est", _MAT9),
    ("stars_detected", pa.int32()), ("stars_matched", pa.int32()), ("prob_false_match", pa.float64()),
    ("fov_deg", pa.float64()), ("residual_rms_rad", pa.float64()),
    ("time_ms", pa.float64()), ("detect_ms", pa.float64()), ("solve_ms", pa.float64()),
])
SCHEMAS = {"peer_star": PEER_SCHEMA}


def frame_row(k: int, f: PeerFrame, spec: PeerSpec) -> dict:
    """The ``peer_star`` row of frame ``k``: the given values (angles to radians), and what ``A`` implies where
    the file gave ``A`` only (boresight RA/Dec, roll)."""
    A = f.matrix()
    ra = f.ra_deg * DEG if f.ra_deg is not None else None
    dec = f.dec_deg * DEG if f.dec_deg is not None else None
    roll = f.roll_deg
    if A is not None:
        if ra is None:
            r, d = unit_to_radec(A[2])
            ra, dec = float(r), float(d)
        if roll is None:
            roll = float(roll_of(A))
    return {"case_id": k, "image": Path(f.path).name, "path": f.path, "method": spec.method,
            "method_version": spec.method_version, "solved": f.solved, "status": f.status, "error": f.error,
            "ra_rad": ra, "dec_rad": dec, "roll_deg": roll, "A_est": None if f.A is None else list(f.A),
            "stars_detected": f.stars_detected, "stars_matched": f.stars_matched,
            "prob_false_match": f.prob_false_match, "fov_deg": f.fov_deg,
            "residual_rms_rad": None if f.residual_rms_arcsec is None else f.residual_rms_arcsec * ARCSEC,
            "time_ms": f.time_ms, "detect_ms": f.detect_ms, "solve_ms": f.solve_ms}


def compute_shard(spec: PeerSpec, case_ids: np.ndarray, ctx=None) -> dict[str, pa.Table]:
    """The job-kind contract: the rows of frames ``case_ids`` (a function of the spec alone)."""
    return {"peer_star": rows_table([frame_row(int(k), spec.frames[int(k)], spec) for k in case_ids], PEER_SCHEMA)}


def shard_summary(tables: dict[str, pa.Table]) -> dict[str, int]:
    t = tables["peer_star"]
    return {"frames": t.num_rows, "solved": sum(bool(x) for x in t.column("solved").to_pylist())}


# ============================================================================================ the run
def import_answers(lake, answers, *, run_id: str | None = None, method: str | None = None,
                   label: str | None = None) -> dict:
    """Import answers file ``answers`` into ``lake`` (a Lake or a folder) as run ``run_id`` (default
    ``peer-star-<spec hash>``); returns the run's manifest.  Everything is validated before the lake is
    touched; an existing run with the same spec is verified and completed (a no-op when it is complete),
    one with another spec is refused."""
    from dualsight.jobs.engine.runner import run_job
    from dualsight.warehouse.lake import Lake

    lake = lake if isinstance(lake, Lake) else Lake(Path(lake))
    spec = load_answers(answers, method=method)
    return run_job(NAME, spec.to_dict(), n_cases=n_cases(spec), lake=lake, run_id=run_id, workers=1,
                   progress=False, label=label or f"{spec.method} answers",
                   extra={"source_file": str(Path(answers)), "peer_version": spec.method_version},
                   source=str(answers))
