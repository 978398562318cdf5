"""Pinhole camera with optional Brown-Conrady distortion; projection and back-projection.

Conventions (docs/architecture.md):
    camera frame  +x along increasing column, +y along increasing row, +z out through the lens;
    pixels        continuous (col, row) measured from the image's top-left *corner*, so the
                  top-left pixel's centre is (0.5, 0.5) and the image centre is (W/2, H/2).

OpenCV measures pixel coordinates from the top-left pixel's *centre*: a principal point
``cx_cv`` from ``cv2.calibrateCamera`` is ``cx = cx_cv + 0.5`` here (same for ``cy``).
Use :meth:`Camera.from_opencv` / :meth:`Camera.opencv_matrix` to convert.

A camera file is TOML with a ``[camera]`` table::

    [camera]
    width = 1024            # pixels
    height = 768            # pixels
    pixel_pitch_um = 4.65   # micrometres
    focal_length_mm = 17.0  # or fx/fy (pixels) instead
    # fx = 3655.9           # pixels, optional (overrides focal_length_mm)
    # fy = 3655.9
    # cx = 512.0            # pixels, dualsight convention (default width/2)
    # cy = 384.0
    # distortion = [k1, k2, p1, p2, k3]   # OpenCV's model, optional

Beside ``[camera]`` a camera file may hold only the tables of :data:`CAMERA_FILE_TABLES` (what ``dualsight
calibrate`` and ``hil star --fit-distortion`` write, scene/camera_file.py); any other top-level table or key is
refused with the allowed names, as an unknown key inside ``[camera]`` is.
"""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import pydantic
from pydantic import Field

from dualsight.config import check_fields, printable_key, validate
from dualsight.errors import ConfigError, read_user_file

_DIST_LEN = 5
MAX_SIDE_PX = 65536
"""Largest image side the kernels address (pixel indices are 32-bit per row and column)."""
MAX_FOCAL_PX = 1e7
"""Largest focal length in pixels: 0.4 deg across the largest image (65536 px), narrower than any star
tracker or navigation camera; the smallest, 1 px, is a ~180 deg field of view, beyond any pinhole model."""
MAX_PRINCIPAL_PX = 1e6
"""Largest distance (px) of the principal point from the image corner: ~15 x the largest image side."""
PIXEL_PITCH_RANGE_M = (1e-8, 1e-3)
"""Pixel pitch range (m): real pixels are ~0.5-50 um; 10 nm leaves room for supersampled virtual
cameras (e.g. 32 x finer than a 4.65 um sensor), 1 mm is beyond any imaging sensor."""

_Side = Annotated[int, Field(ge=1, le=MAX_SIDE_PX)]
_Focal = Annotated[float, Field(ge=1.0, le=MAX_FOCAL_PX)]
_Principal = Annotated[float, Field(ge=-MAX_PRINCIPAL_PX, le=MAX_PRINCIPAL_PX)]
_BitDepth = Annotated[int, Field(ge=1, le=32)]
_PsfSigma = Annotated[float, Field(ge=0.2, le=20.0)]
_UNITS = {"width": "px", "height": "px", "pixel_pitch_m": "m", "fx": "px", "fy": "px", "cx": "px", "cy": "px",
          "bit_depth": "bits", "psf_sigma_px": "px"}


@dataclass(frozen=True)
class Camera:
    """Intrinsics of a pinhole camera.

    Every field's range is part of its type (pydantic ``Field``), checked whenever a Camera is built
    (ConfigError naming ``camera.<field>``, the value and the range).

    Attributes
    ----------
    width, height : image size in pixels, integers in [1, 65536] (:data:`MAX_SIDE_PX`).
    pixel_pitch_m : physical pixel size (m), square pixels, in [1e-8, 1e-3] (:data:`PIXEL_PITCH_RANGE_M`).
    fx, fy : focal length in pixels along columns and rows, in [1, 1e7] px (:data:`MAX_FOCAL_PX`).
    cx, cy : principal point in pixels (dualsight convention: from the top-left corner), in
        [-1e6, 1e6] px (:data:`MAX_PRINCIPAL_PX`).
    distortion : (k1, k2, p1, p2, k3), OpenCV's radial-tangential model on normalised coordinates;
        exactly 5 finite numbers (dimensionless).
    bit_depth : ADC bits of the sensor (used by renderers to quantise), an integer in [1, 32].
    psf_sigma_px : the optics' PSF as a Gaussian's standard deviation (px), as calibrated, in [0.2, 20], or None
        (unknown): the real-sensor detector filters each frame at this width and checks it on the frame's bright
        stars (``LocalDetectConfig.psf_sigma_stated_px``) instead of measuring it in a first pass.  Renderers
        take the PSF from the sensor's settings, not from here.
    """

    width: _Side
    height: _Side
    pixel_pitch_m: Annotated[float, Field(ge=PIXEL_PITCH_RANGE_M[0], le=PIXEL_PITCH_RANGE_M[1])]
    fx: _Focal
    fy: _Focal
    cx: _Principal
    cy: _Principal
    distortion: Annotated[tuple[float, ...], Field(min_length=_DIST_LEN, max_length=_DIST_LEN)] = \
        field(default=(0.0,) * _DIST_LEN)
    bit_depth: _BitDepth = 12
    psf_sigma_px: _PsfSigma | None = None

    def __post_init__(self):
        _check_camera(self, source=None)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def pinhole(cls, width: int, height: int, pixel_pitch_m: float, focal_length_m: float,
                distortion=None, bit_depth: int = 12) -> "Camera":
        """Ideal camera with the principal point at the image centre."""
        if not (focal_length_m > 0):
            raise ConfigError(f"focal length must be > 0 m, got {focal_length_m}", field="focal_length_mm")
        if not (pixel_pitch_m > 0):
            raise ConfigError(f"pixel pitch must be > 0 m, got {pixel_pitch_m}", field="pixel_pitch_um")
        f_px = focal_length_m / pixel_pitch_m
        return cls(int(width), int(height), float(pixel_pitch_m), f_px, f_px, width / 2.0, height / 2.0,
                   tuple(distortion) if distortion is not None else (0.0,) * _DIST_LEN, int(bit_depth))

    @classmethod
    def from_opencv(cls, K, dist, width: int, height: int, pixel_pitch_m: float, bit_depth: int = 8) -> "Camera":
        """From an OpenCV camera matrix (pixel centres at integers) and distortion vector."""
        K = np.asarray(K, dtype=float)
        d = np.zeros(_DIST_LEN)
        dv = np.asarray(dist, dtype=float).ravel()[:_DIST_LEN]
        d[: dv.size] = dv
        return cls(int(width), int(height), float(pixel_pitch_m), float(K[0, 0]), float(K[1, 1]),
                   float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5, tuple(float(x) for x in d), int(bit_depth))

    @classmethod
    def from_dict(cls, table: dict, source: str = "camera") -> "Camera":
        """Build from a ``[camera]`` table (see module docstring; the layout is :class:`CameraTable`),
        validated by ``dualsight.config.validate``; errors name ``source`` and ``camera.<key>``."""
        return cls.from_table(validate_table(CameraTable, table, source=source, section="camera"), source=source)

    @classmethod
    def from_table(cls, t: "CameraTable", source: str = "camera") -> "Camera":
        """Build from a validated :class:`CameraTable` (friendly units: um, mm); the rules that tie keys
        together (focal length given as fx/fy or as focal_length_mm) are checked here."""
        if t.pixel_pitch_um is None and t.fx is None:
            raise ConfigError("missing key 'pixel_pitch_um' (needed to turn focal_length_mm into pixels; or give "
                              "fx and fy in pixels)", source=source, field="camera.pixel_pitch_um")
        pitch = t.pixel_pitch_um * 1e-6 if t.pixel_pitch_um is not None else UNKNOWN_PITCH_M
        if t.fx is not None:
            fx, fy, derived = t.fx, (t.fy if t.fy is not None else t.fx), False
        elif t.fy is not None:
            raise ConfigError("missing key 'fx' (fy is given; give fx, and fy if it differs)", source=source,
                              field="camera.fx")
        elif t.focal_length_mm is None:
            raise ConfigError("missing key 'focal_length_mm' (or fx/fy in pixels)", source=source,
                              field="camera.focal_length_mm")
        else:
            fx = fy = t.focal_length_mm * 1e-3 / pitch
            derived = True
        d = tuple(t.distortion) + (0.0,) * (_DIST_LEN - len(t.distortion))
        cx = t.cx if t.cx is not None else t.width / 2.0
        cy = t.cy if t.cy is not None else t.height / 2.0
        try:
            return cls(t.width, t.height, pitch, fx, fy, cx, cy, d, t.bit_depth, t.psf_sigma_px)
        except ConfigError as e:
            if derived and e.field in ("camera.fx", "camera.fy"):
                raise ConfigError(f"focal_length_mm / pixel_pitch_um gives a focal length of {fx:g} px, outside "
                                  f"[1, {MAX_FOCAL_PX:g}] px", source=source, field="camera.focal_length_mm") from None
            raise ConfigError(e.detail, source=source, field=e.field) from None

    @classmethod
    def from_toml(cls, path: str | Path) -> "Camera":
        """Read a camera file (TOML with a ``[camera]`` table)."""
        path = Path(path)
        data = read_toml(path)
        if "camera" not in data or not isinstance(data["camera"], dict):
            raise ConfigError("missing table [camera]", source=str(path), field="camera")
        check_camera_file_tables(data, source=str(path))
        return cls.from_dict(data["camera"], source=str(path))

    def to_dict(self) -> dict:
        """The ``[camera]`` table (round-trips through :meth:`from_dict`; ``psf_sigma_px`` only when stated)."""
        return {"width": self.width, "height": self.height, "pixel_pitch_um": self.pixel_pitch_m * 1e6,
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": list(self.distortion), "bit_depth": self.bit_depth,
                **({} if self.psf_sigma_px is None else {"psf_sigma_px": self.psf_sigma_px})}

    # ------------------------------------------------------------------ derived
    @property
    def focal_length_m(self) -> float:
        """Mean focal length (m) = mean(fx, fy) * pixel pitch."""
        return 0.5 * (self.fx + self.fy) * self.pixel_pitch_m

    @property
    def fov_rad(self) -> tuple[float, float, float]:
        """(horizontal, vertical, diagonal) full field of view (rad) of the ideal pinhole, centred."""
        hw, hh = self.width / 2.0, self.height / 2.0
        fh = 2 * math.atan(hw / self.fx)
        fv = 2 * math.atan(hh / self.fy)
        fd = 2 * math.atan(math.hypot(hw / self.fx, hh / self.fy))
        return fh, fv, fd

    @functools.cached_property
    def has_distortion(self) -> bool:
        """Any non-zero distortion coefficient (cached: a tracker asks several times per frame)."""
        return any(abs(x) > 0 for x in self.distortion)

    def opencv_matrix(self) -> np.ndarray:
        """3x3 OpenCV camera matrix (pixel centres at integers)."""
        return np.array([[self.fx, 0, self.cx - 0.5], [0, self.fy, self.cy - 0.5], [0, 0, 1.0]])

    # ------------------------------------------------------------------ geometry
    def project(self, v_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame vectors to pixels.

        Parameters
        ----------
        v_cam : (..., 3) vectors in the camera frame (any length).

        Returns
        -------
        px : (..., 2) float64 continuous pixel coordinates (col, row) from the top-left corner.
        in_front : (...,) bool, z > 0 (points behind the camera get NaN coordinates).

        Pinhole model u = fx x/z + cx, v = fy y/z + cy, with OpenCV's distortion
        (Brown 1966; Bouguet's toolbox) applied to the normalised coordinates.
        """
        v = np.asarray(v_cam, dtype=np.float64)
        z = v[..., 2]
        front = z > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(front, v[..., 0] / z, np.nan)
            y = np.where(front, v[..., 1] / z, np.nan)
        if self.has_distortion:
            x, y = distort(x, y, self.distortion)
        px = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
        return px, front

    def backproject(self, px: np.ndarray) -> np.ndarray:
        """Unit vectors in the camera frame for pixel coordinates.

        Parameters
        ----------
        px : (..., 2) continuous (col, row) pixel coordinates.

        Returns
        -------
        (..., 3) float64 unit vectors (z > 0).
        """
        p = np.asarray(px, dtype=np.float64)
        x = (p[..., 0] - self.cx) / self.fx
        y = (p[..., 1] - self.cy) / self.fy
        if self.has_distortion:
            x, y = undistort(x, y, self.distortion)
        v = np.stack([x, y, np.ones_like(x)], axis=-1)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def in_image(self, px: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(...,) bool: pixel coordinates inside the image (shrunk by ``margin`` px)."""
        p = np.asarray(px)
        return ((p[..., 0] >= margin) & (p[..., 0] < self.width - margin)
                & (p[..., 1] >= margin) & (p[..., 1] < self.height - margin))


def distort(x: np.ndarray, y: np.ndarray, d) -> tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV's radial-tangential distortion to normalised coordinates (x, y)."""
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, d, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by fixed-point iteration (as OpenCV's ``undistortPoints``)."""
    k1, k2, p1, p2, k3 = d
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):  # iterations over the whole array, not over points
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


MAX_CONFIG_BYTES = 1 << 20
"""Configuration files over 1 MiB are refused (a camera, spec or satellite file is a few kB)."""


def read_toml(path: Path) -> dict:
    """Read a TOML file (a regular file of at most 1 MiB), turning every failure into a ConfigError naming it."""
    data = read_user_file(path, ConfigError, what="TOML file", max_bytes=MAX_CONFIG_BYTES)
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"is not UTF-8 text ({e.reason})", source=str(path)) from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"is not valid TOML: {e}", source=str(path)) from None
    except RecursionError:
        raise ConfigError("is nested too deeply", source=str(path)) from None


CAMERA_FILE_TABLES = ("camera", "calibration", "distortion_fit", "source")
"""The top-level tables a camera file may hold: ``[camera]``; ``[calibration]`` (``dualsight calibrate``),
``[distortion_fit]`` (``hil star --fit-distortion``) and ``[source]`` (where the camera came from), written by
scene/camera_file.py's ``write_camera_toml``."""


def check_camera_file_tables(data: dict, *, source: str):
    """ConfigError naming the first top-level key of a camera file's TOML ``data`` that is not one of
    :data:`CAMERA_FILE_TABLES` or is not a table, with the allowed names."""
    allowed = ", ".join(sorted(CAMERA_FILE_TABLES))
    for key, value in data.items():
        if key not in CAMERA_FILE_TABLES:
            what = "table" if isinstance(value, dict) else "key"
            raise ConfigError(f"unknown {what}; a camera file holds only the tables {allowed}", source=source,
                              field=printable_key(key))
        if not isinstance(value, dict):
            raise ConfigError("must be a table", source=source, field=key)


def validate_table(model, table, *, source: str, section: str | None):
    """:func:`dualsight.config.validate` (the one configuration layer) for the scene's file readers; a key that
    cannot be printed on one line (e.g. holding a newline) is named escaped."""
    try:
        return validate(model, table, source=source, section=section)
    except ConfigError as e:
        if e.field is not None and not e.field.isprintable():
            raise ConfigError(e.detail, source=e.source, field=e.field.encode("unicode_escape").decode("ascii")) \
                from None
        raise


def _check_camera(cam: Camera, source: str | None):
    """Every field of ``cam`` within its declared range (ConfigError naming ``camera.<field>``)."""
    check_fields(cam, lambda name, msg: ConfigError(msg, source=source, field=f"camera.{name}"), _UNITS)


_Finite = Annotated[float, Field(allow_inf_nan=False)]


UNKNOWN_PITCH_M = 1e-6
"""Pixel pitch (m) of a camera file that gives fx, fy in pixels but no pitch: a placeholder that changes no
result (projection, identification and attitude use pixels; the blobber's Eq. 1 uses f / p = fx)."""


class CameraTable(pydantic.BaseModel):
    """The ``[camera]`` table of a camera file (TOML layout, friendly units), validated by pydantic.

    width, height : px, integers in [1, 65536].  pixel_pitch_um : um, in [0.01, 1000] (as
    :data:`PIXEL_PITCH_RANGE_M`); needed only to turn focal_length_mm into pixels: with fx given and no pitch,
    :data:`UNKNOWN_PITCH_M` stands in (every algorithm works in pixels, and Eq. 1's f / p is fx).  focal_length_mm : mm, in (0, 10000] (10 m, beyond any camera of a
    spacecraft); used when fx is absent.  fx, fy : px, in [1, 1e7] (fy defaults to fx).  cx, cy : px, in
    [-1e6, 1e6] (default: the image centre).  distortion : 1-5 numbers [k1, k2, p1, p2, k3] (the rest 0).
    bit_depth : bits, an integer in [1, 32].  psf_sigma_px : px, in [0.2, 20] (optional: the calibrated PSF width,
    :class:`Camera`).  name, notes : free text.
    """

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)
    width: _Side
    height: _Side
    pixel_pitch_um: Annotated[float, Field(ge=PIXEL_PITCH_RANGE_M[0] * 1e6, le=PIXEL_PITCH_RANGE_M[1] * 1e6)] | None = None
    focal_length_mm: Annotated[float, Field(gt=0, le=10_000.0)] | None = None
    fx: _Focal | None = None
    fy: _Focal | None = None
    cx: _Principal | None = None
    cy: _Principal | None = None
    distortion: Annotated[tuple[_Finite, ...], Field(min_length=1, max_length=_DIST_LEN)] = (0.0,) * _DIST_LEN
    bit_depth: _BitDepth = 12
    psf_sigma_px: _PsfSigma | None = None
    name: str | None = None
    notes: str | None = None
