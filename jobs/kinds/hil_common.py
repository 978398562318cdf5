"""What the hardware-in-the-loop job kinds (``hil_star``, ``hil_prox``, ``calibrate``) share.

* Image lists in specs.  A HIL run is its images: each is an entry ``{path (absolute), bytes, mtime_ns}``
  (:class:`ImageEntry`, :func:`image_entries`), so a changed image file makes a different run (another spec
  hash), and case i is image i of the list.  A file that is missing when the run is planned keeps its
  entry with ``bytes = mtime_ns = None``: it becomes an error row.  A worker that finds a file different
  from its entry (:func:`check_unchanged`) writes an error row instead of results of another image, so a
  run's rows are a function of its spec alone.
* The spec dict's common part (:func:`spec_base`: camera table, settings table, image entries), the case
  count (:func:`n_cases`: one case per image) and the rows -> Arrow table of every HIL dataset (:func:`rows_table`).
* The images of a command's arguments (:func:`expand_inputs`: a folder expands to its images).

The HIL commands' options, their engine call and closing line are the command line's (jobs/cli/args.py).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field, field_validator

from dualsight.errors import ImageError
from dualsight.scene.imageio import check_image_file, list_images

__all__ = ["Frozen", "ImageEntry", "image_entries", "check_unchanged", "expand_inputs", "spec_base", "n_cases",
           "rows_table", "fixed_point", "SHOWN_SKIPS", "SkipNotes"]


class Frozen(BaseModel):
    """Base of the HIL specs: immutable, unknown keys refused."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    def to_dict(self) -> dict:
        """Canonical JSON-serialisable dict (``spec_from_dict(spec.to_dict()) == spec``)."""
        return self.model_dump(mode="json")


class ImageEntry(Frozen):
    """One image of a run: absolute path, size and modification time when the run was planned
    (None, None: the file did not exist then)."""

    path: str = Field(min_length=1, max_length=4096)
    bytes: int | None = Field(default=None, ge=0)
    mtime_ns: int | None = Field(default=None, ge=0)

    @field_validator("path")
    @classmethod
    def _absolute(cls, v: str) -> str:
        if not os.path.isabs(v):
            raise ValueError("must be an absolute path")
        return v

    @property
    def name(self) -> str:
        return Path(self.path).name


def image_entries(paths) -> list[dict]:
    """Spec entries of image files (absolute paths, sizes and modification times; missing: None).  A pipe,
    socket, device or folder, or an image whose header declares more than the reader's limits, refuses the
    whole run now (ImageError naming the file, :func:`dualsight.scene.imageio.check_image_file`)."""
    out = []
    for p in paths:
        a = os.path.abspath(os.fspath(p))
        check_image_file(p)
        try:
            st = os.stat(a)
            out.append({"path": a, "bytes": int(st.st_size), "mtime_ns": int(st.st_mtime_ns)})
        except OSError:
            out.append({"path": a, "bytes": None, "mtime_ns": None})
    return out


def spec_base(paths, camera, settings) -> dict:
    """``{"camera", "settings", "images"}`` of a HIL spec dict: the camera's table (a ``Camera`` or its
    table), the settings' table (a ``Frozen`` model, a table or None) and the images' entries (stat now)."""
    return {"camera": camera.to_dict() if hasattr(camera, "to_dict") else dict(camera),
            "settings": settings.to_dict() if isinstance(settings, Frozen) else dict(settings or {}),
            "images": image_entries(paths)}


def n_cases(spec) -> int:
    """Cases of a HIL run: one per image of its spec."""
    return len(spec.images)


def rows_table(rows: list[dict], schema: pa.Schema) -> pa.Table:
    """Arrow table of ``schema`` from row dicts (a key a row does not have is null)."""
    return pa.table({f.name: pa.array([r.get(f.name) for r in rows], type=f.type) for f in schema}, schema=schema)


def check_unchanged(entry: ImageEntry):
    """Raise ImageError (naming the file) unless the file is as it was when the run was planned."""
    if entry.bytes is None:
        raise ImageError("file not found (when the run was planned)", source=entry.path)
    try:
        st = os.stat(entry.path)
    except OSError:
        raise ImageError("file not found (it existed when the run was planned)", source=entry.path) from None
    if st.st_size != entry.bytes or st.st_mtime_ns != entry.mtime_ns:
        raise ImageError(f"changed since the run was planned ({entry.bytes} -> {st.st_size} bytes, modified "
                         "again); start a new run for the new file", source=entry.path)


def expand_inputs(items) -> list[Path]:
    """Image paths; a folder argument expands to its images (natural order).  Missing files are kept
    (they become error rows)."""
    out = []
    for it in items:
        p = Path(it)
        out.extend(list_images(p) if p.is_dir() else [p])
    return out


def fixed_point(normalise, value, rounds: int = 4):
    """``normalise`` applied until the value stops changing (at most ``rounds`` times): canonical forms
    whose float conversions (um <-> m) could otherwise move the last digit on every round trip."""
    for _ in range(rounds):
        nxt = normalise(value)
        if nxt == value:
            return nxt
        value = nxt
    return value


SHOWN_SKIPS = 5
"""Skipped images a HIL command names one by one on stderr; the rest are counted in one line saying where every
one is listed."""


class SkipNotes:
    """The stderr lines of images a HIL command skips: each of the first :data:`SHOWN_SKIPS` as it comes
    (``dualsight: <reason>; skipped, the other images go on``), the rest counted; :meth:`finish` prints one line
    with their count and ``rest_at`` (where every one is listed) when there were more.  ``outcome`` and ``rest``
    word other notes on images the same way (``hil star``'s NaN pixels: ``; ignored``, ``more images with NaN or
    infinite pixels``)."""

    def __init__(self, file=None, *, outcome: str = "skipped, the other images go on",
                 rest: str = "more images skipped"):
        self.file = file
        self.count = 0
        self.outcome = outcome
        self.rest = rest

    def __call__(self, message: str):
        self.count += 1
        if self.count <= SHOWN_SKIPS:
            print(f"dualsight: {message}; {self.outcome}", file=self.file or sys.stderr)

    def finish(self, rest_at: str):
        if self.count > SHOWN_SKIPS:
            print(f"dualsight: {self.count - SHOWN_SKIPS} {self.rest} ({self.count} in all); {rest_at}",
                  file=self.file or sys.stderr)
