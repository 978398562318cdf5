"""Pinhole camera with optional Brown-Conrady distortion; projection and back-projection.

Conventions (DESIGN.md):
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
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualsight.errors import ConfigError

_DIST_LEN = 5
MAX_SIDE_PX = 65536
"""Largest image side the kernels address (pixel indices are 32-bit per row and column)."""


@dataclass(frozen=True)
class Camera:
    """Intrinsics of a pinhole camera.

    Attributes
    ----------
    width, height : image size in pixels.
    pixel_pitch_m : physical pixel size (m), square pixels.
    fx, fy : focal length in pixels along columns and rows.
    cx, cy : principal point in pixels (dualsight convention: from the top-left corner).
    distortion : (k1, k2, p1, p2, k3), OpenCV's radial-tangential model on normalised coordinates.
    bit_depth : ADC bits of the sensor (used by renderers to quantise).
    """

    width: int
    height: int
    pixel_pitch_m: float
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = field(default=(0.0,) * _DIST_LEN)
    bit_depth: int = 12

    def __post_init__(self):
        _check_camera(self, source="camera")

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
        """Build from a ``[camera]`` table (see module docstring); errors name ``source`` and the key."""
        def need(key):
            if key not in table:
                raise ConfigError(f"missing key '{key}'", source=source, field=f"camera.{key}")
            return table[key]

        def num(key, lo, hi, integer=False, default=None):
            v = table.get(key, default) if default is not None else need(key)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool)
            if integer:
                ok = ok and float(v).is_integer()
            if not ok or not (lo < v <= hi) or (isinstance(v, float) and not math.isfinite(v)):
                kind = "an integer" if integer else "a number"
                raise ConfigError(f"must be {kind} in ({lo}, {hi}], got {v!r}", source=source, field=f"camera.{key}")
            return int(v) if integer else float(v)

        known = {"width", "height", "pixel_pitch_um", "focal_length_mm", "fx", "fy", "cx", "cy",
                 "distortion", "bit_depth", "name", "notes"}
        unknown = sorted(set(table) - known)
        if unknown:
            raise ConfigError(f"unknown key(s) {unknown}; allowed: {sorted(known)}", source=source, field="camera")
        w = num("width", 0, 100_000, integer=True)
        h = num("height", 0, 100_000, integer=True)
        pitch = num("pixel_pitch_um", 0, 1000.0) * 1e-6
        if "fx" in table or "fy" in table:
            fx = num("fx", 0, 1e7)
            fy = num("fy", 0, 1e7, default=fx)
        else:
            f_mm = table.get("focal_length_mm")
            if f_mm is None:
                raise ConfigError("missing key 'focal_length_mm' (or fx/fy in pixels)", source=source,
                                  field="camera.focal_length_mm")
            fmm = num("focal_length_mm", 0, 10_000.0)
            fx = fy = fmm * 1e-3 / pitch
        cx = num("cx", -1e6, 1e6, default=w / 2.0) if "cx" in table else w / 2.0
        cy = num("cy", -1e6, 1e6, default=h / 2.0) if "cy" in table else h / 2.0
        dist = table.get("distortion", [0.0] * _DIST_LEN)
        if (not isinstance(dist, list) or not 1 <= len(dist) <= _DIST_LEN
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in dist)):
            raise ConfigError(f"must be a list of 1-5 numbers [k1, k2, p1, p2, k3], got {dist!r}",
                              source=source, field="camera.distortion")
        d = [float(x) for x in dist] + [0.0] * (_DIST_LEN - len(dist))
        bits = num("bit_depth", 0, 32, integer=True, default=12) if "bit_depth" in table else 12
        cam = object.__new__(cls)
        for k, v in dict(width=w, height=h, pixel_pitch_m=pitch, fx=fx, fy=fy, cx=cx, cy=cy,
                         distortion=tuple(d), bit_depth=bits).items():
            object.__setattr__(cam, k, v)
        _check_camera(cam, source=source)
        return cam

    @classmethod
    def from_toml(cls, path: str | Path) -> "Camera":
        """Read a camera file (TOML with a ``[camera]`` table)."""
        path = Path(path)
        data = read_toml(path)
        if "camera" not in data or not isinstance(data["camera"], dict):
            raise ConfigError("missing table [camera]", source=str(path), field="camera")
        return cls.from_dict(data["camera"], source=str(path))

    def to_dict(self) -> dict:
        """The ``[camera]`` table (round-trips through :meth:`from_dict`)."""
        return {"width": self.width, "height": self.height, "pixel_pitch_um": self.pixel_pitch_m * 1e6,
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": list(self.distortion), "bit_depth": self.bit_depth}

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

    @property
    def has_distortion(self) -> bool:
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
    import os
    import stat

    path = Path(path)
    try:
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError("is not a regular file (a device, pipe or folder); give a TOML file",
                                  source=str(path))
            data = fh.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError(f"is larger than {MAX_CONFIG_BYTES // 1024} KiB; a configuration file is a few kB",
                              source=str(path))
        return tomllib.loads(data.decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError("file not found", source=str(path)) from None
    except IsADirectoryError:
        raise ConfigError("is a folder, expected a TOML file", source=str(path)) from None
    except PermissionError:
        raise ConfigError("cannot be read (permission denied)", source=str(path)) from None
    except OSError as e:
        raise ConfigError(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"is not UTF-8 text ({e.reason})", source=str(path)) from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"is not valid TOML: {e}", source=str(path)) from None
    except RecursionError:
        raise ConfigError("is nested too deeply", source=str(path)) from None


def _check_camera(cam: Camera, source: str):
    checks = [
        ("width", cam.width, isinstance(cam.width, int) and 0 < cam.width <= MAX_SIDE_PX, f"an integer in [1, {MAX_SIDE_PX}]"),
        ("height", cam.height, isinstance(cam.height, int) and 0 < cam.height <= MAX_SIDE_PX, f"an integer in [1, {MAX_SIDE_PX}]"),
        ("pixel_pitch_um", cam.pixel_pitch_m * 1e6, math.isfinite(cam.pixel_pitch_m) and cam.pixel_pitch_m > 0,
         "> 0 um"),
        ("fx", cam.fx, math.isfinite(cam.fx) and cam.fx > 0, "> 0 px (focal length must be positive)"),
        ("fy", cam.fy, math.isfinite(cam.fy) and cam.fy > 0, "> 0 px (focal length must be positive)"),
        ("cx", cam.cx, math.isfinite(cam.cx), "finite"),
        ("cy", cam.cy, math.isfinite(cam.cy), "finite"),
        ("distortion", cam.distortion,
         len(cam.distortion) == _DIST_LEN and all(math.isfinite(x) for x in cam.distortion), "5 finite numbers"),
        ("bit_depth", cam.bit_depth, 1 <= cam.bit_depth <= 32, "in [1, 32]"),
    ]
    for key, value, ok, allowed in checks:
        if not ok:
            raise ConfigError(f"must be {allowed}, got {value!r}", source=source, field=f"camera.{key}")
