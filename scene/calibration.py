"""Camera calibration from chessboard photos.

Method: Zhang (2000) / Bouguet's Camera Calibration Toolbox (2013) as OpenCV implements it: the inner corners of
every photo (:mod:`dualsight.scene.chessboard`: ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``), then
``cv2.calibrateCameraExtended`` (closed-form initialisation and Levenberg-Marquardt over intrinsics, distortion
k1, k2, p1, p2, k3 and one board pose per image).
The default flags, ``cv2.CALIB_FIX_ASPECT_RATIO`` (= 2, with aspect ratio fx/fy = 1), are the ones of
OpenCV's reference calibration of its ``left*.jpg`` samples (``left_intrinsics.yml``: ``flags: 2``).
The two steps are separate functions: :func:`dualsight.scene.chessboard.find_view` (one photo -> its corners;
the per-case work of the ``calibrate`` job kind, jobs/kinds/calibrate.py) and :func:`solve_calibration` (all
views -> the camera); :func:`calibrate_chessboard` does both in-process, and :func:`calibrate_main` also writes
the camera file (:func:`dualsight.scene.camera_file.write_camera_toml`).

Conventions
    The resulting :class:`~dualsight.scene.camera.Camera` uses dualsight's pixel convention (pixel
    coordinates from the image's top-left *corner*): ``cx = cx_opencv + 0.5``, ``cy = cy_opencv + 0.5``.
    Board poses are OpenCV's: ``rvec`` (Rodrigues vector, rad) and ``tvec`` (m) map board coordinates
    (origin at the first detected inner corner, x along the board's ``board[0]`` corners, z into the
    board) into the camera frame (+x right, +y down, +z out through the lens) -- the same camera frame
    as dualsight's.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from dualsight.errors import ConfigError, ImageError, InputError
from dualsight.scene.imageio import list_images
from dualsight.scene.camera import Camera
from dualsight.scene.camera_file import write_camera_toml
from dualsight.scene.chessboard import FIND_FLAGS_DEFAULT, ViewCorners, board_points, find_view

__all__ = ["CALIB_FLAGS_DEFAULT", "PLACEHOLDER_PITCH_M", "BoardView", "CalibrationResult", "check_settings",
           "parse_board", "calibrate_chessboard", "solve_calibration", "calibrate_main", "format_summary"]

#: cv2.CALIB_FIX_ASPECT_RATIO, as in OpenCV's reference left_intrinsics.yml ("flags: 2").
CALIB_FLAGS_DEFAULT = 2

#: Placeholder pixel pitch (m) when the caller does not know it; only fx, fy (pixels) are measured.
PLACEHOLDER_PITCH_M = 1e-6

SHOWN = 5
"""Images named one by one (with their reasons) where a calibration lists the photos it could not use; the rest are
counted, and the caller says where every one is listed (``rest_at``)."""


def _listed(items: list[str], sep: str, rest_at: str | None) -> str:
    """The first :data:`SHOWN` of ``items`` joined by ``sep``, then "and N more" (and where) when there are more."""
    if len(items) <= SHOWN:
        return sep.join(items)
    return (sep.join(items[:SHOWN]) + f"{sep}and {len(items) - SHOWN} more"
            + (f" ({rest_at})" if rest_at else ""))


@dataclass(frozen=True, eq=False)
class BoardView:
    """One photo in which the board was found.

    Attributes
    ----------
    path : the image file.
    rvec : (3,) Rodrigues rotation vector (rad), board -> camera.
    tvec : (3,) translation (m): the board origin (first inner corner) in the camera frame.
    distance_m : distance from the camera's optical centre to the centre of the inner-corner grid (m).
    rms_px : RMS reprojection error of this view's corners (px, Euclidean per corner).
    corners_px : (N, 2) detected corners (col, row), dualsight convention (from the top-left corner).
    """

    path: Path
    rvec: np.ndarray
    tvec: np.ndarray
    distance_m: float
    rms_px: float
    corners_px: np.ndarray

@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Outcome of :func:`calibrate_chessboard`.

    Attributes
    ----------
    camera : the calibrated camera (fx, fy in px; cx, cy in dualsight convention; distortion
        (k1, k2, p1, p2, k3); pixel pitch as given, else ``PLACEHOLDER_PITCH_M``).
    rms_px : RMS reprojection error over all corners of all views (px), the value
        ``cv2.calibrateCamera`` returns (sqrt of mean squared Euclidean corner error).
    views : the views used, in input order.
    not_found : images in which the board was not found.
    unreadable : (path, reason) of images that could not be read or had another size.
    board : inner corners (per row, per column), e.g. (9, 6).
    square_m : side of one square (m).
    flags : cv2.calibrateCamera flags used.
    pixel_pitch_known : False when the pitch is the placeholder (then ``focal_length_mm`` is None).
    std : one-sigma uncertainties of fx, fy, cx, cy, k1, k2, p1, p2, k3 from the fit's covariance
        (``cv2.calibrateCameraExtended``'s ``stdDeviationsIntrinsics``), pixels / unitless.
    """

    camera: Camera
    rms_px: float
    views: tuple[BoardView, ...]
    not_found: tuple[Path, ...]
    unreadable: tuple[tuple[Path, str], ...]
    board: tuple[int, int]
    square_m: float
    flags: int
    pixel_pitch_known: bool
    std: dict = field(default_factory=dict)

    @property
    def focal_length_mm(self) -> float | None:
        """Mean focal length (mm) if the pixel pitch is known, else None."""
        return self.camera.focal_length_m * 1e3 if self.pixel_pitch_known else None

    @property
    def distances_m(self) -> np.ndarray:
        """(n_views,) distances to the board centre (m)."""
        return np.array([v.distance_m for v in self.views])


# ---------------------------------------------------------------------------------------------- calibration
def check_settings(board, square_m, pixel_pitch_m=None) -> tuple[int, int]:
    """Validated board (two integers >= 2); ConfigError for a bad board, square or pixel pitch."""
    board = _check_board(board)
    if isinstance(square_m, bool) or not (isinstance(square_m, (int, float)) and math.isfinite(square_m)
                                          and square_m > 0):
        raise ConfigError(f"square size must be > 0 m, got {square_m!r}", field="--square")
    if pixel_pitch_m is not None and not (math.isfinite(pixel_pitch_m) and pixel_pitch_m > 0):
        raise ConfigError(f"pixel pitch must be > 0 m, got {pixel_pitch_m!r}", field="--pixel-pitch")
    return board

def calibrate_chessboard(paths: Iterable[str | Path], board: tuple[int, int] = (9, 6), square_m: float = 0.025,
                         pixel_pitch_m: float | None = None, flags: int = CALIB_FLAGS_DEFAULT,
                         aspect_ratio: float = 1.0, find_flags: int = FIND_FLAGS_DEFAULT,
                         min_views: int = 3) -> CalibrationResult:
    """Calibrate a camera from photos of a flat chessboard: :func:`find_view` per photo, then
    :func:`solve_calibration`.

    Parameters
    ----------
    paths : image files (any format :func:`read_image` reads; colour is converted to gray, 16-bit
        data scaled to 8 bit for corner detection).
    board : inner corners per row and per column (a 10x7-square board has 9x6 inner corners).
    square_m : side of one square (m); sets the scale of ``tvec`` and distances only.
    pixel_pitch_m : physical pixel size (m), for the focal length in mm; None if unknown.
    flags : ``cv2.calibrateCamera`` flags (default ``CALIB_FIX_ASPECT_RATIO``).
    aspect_ratio : fx / fy held fixed when ``CALIB_FIX_ASPECT_RATIO`` is set.
    find_flags : ``cv2.findChessboardCorners`` flags.
    min_views : fewest views with a detected board needed.

    Raises
    ------
    InputError if the board or square is invalid or the board is found in fewer than ``min_views``
    images (the message lists the images where it was not found and the unreadable ones).
    """
    board = check_settings(board, square_m, pixel_pitch_m)
    views = [find_view(p, board, find_flags) for p in paths]
    return solve_calibration(views, board=board, square_m=square_m, pixel_pitch_m=pixel_pitch_m, flags=flags,
                             aspect_ratio=aspect_ratio, min_views=min_views)

def solve_calibration(views: Iterable[ViewCorners], board: tuple[int, int] = (9, 6), square_m: float = 0.025,
                      pixel_pitch_m: float | None = None, flags: int = CALIB_FLAGS_DEFAULT, aspect_ratio: float = 1.0,
                      min_views: int = 3, rest_at: str | None = None) -> CalibrationResult:
    """The calibration from the corners of every photo (in input order): the first readable photo sets the
    image size (others of another size count as unreadable), then ``cv2.calibrateCameraExtended`` (module
    docstring) and each board's pose, distance and reprojection error.  Parameters and errors as
    :func:`calibrate_chessboard`; the error names the first :data:`SHOWN` photos of each list and counts the
    rest, which ``rest_at`` says where to find."""
    import cv2

    board = check_settings(board, square_m, pixel_pitch_m)
    views = list(views)
    obj = board_points(board, square_m)
    found, not_found, unreadable = [], [], []
    size, bit_depth = None, 8
    for v in views:
        if v.error is not None:
            unreadable.append((v.path, v.error))
            continue
        if size is None:
            size, bit_depth = (v.width, v.height), v.bit_depth or 8
        elif (v.width, v.height) != size:
            unreadable.append((v.path, f"size {v.width}x{v.height} differs from the first image's {size[0]}x{size[1]}"))
            continue
        if v.corners is None:
            not_found.append(v.path)
        else:
            found.append((v.path, np.asarray(v.corners, np.float32).reshape(-1, 2)))

    if len(found) < min_views:
        msg = f"chessboard {board[0]}x{board[1]} found in {len(found)} of {len(views)} images; need >= {min_views}"
        if not_found:
            msg += (f"; not found in{f' {len(not_found)} images' if len(not_found) > SHOWN else ''}: "
                    + _listed([p.name for p in not_found], ", ", rest_at))
        if unreadable:
            msg += (f"; unreadable{f' {len(unreadable)} images' if len(unreadable) > SHOWN else ''}: "
                    + _listed([f"{p.name} ({r})" for p, r in unreadable], "; ", rest_at))
        raise InputError(msg)

    k0 = np.array([[aspect_ratio, 0, size[0] / 2 - 0.5], [0, 1.0, size[1] / 2 - 0.5], [0, 0, 1]])
    objs = [obj] * len(found)
    imgs = [c.reshape(-1, 1, 2).astype(np.float32) for _, c in found]
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)     # OpenCV's threaded solver moves the 9th digit from call to call: one thread repeats
    try:
        rms, K, dist, rvecs, tvecs, std_in, _std_ex, _per_view = cv2.calibrateCameraExtended(
            objs, imgs, size, k0, None, flags=flags)
    finally:
        cv2.setNumThreads(threads)

    centre = np.array([(board[0] - 1) / 2 * square_m, (board[1] - 1) / 2 * square_m, 0.0])
    out = []
    for (p, c), rv, tv in zip(found, rvecs, tvecs):
        rv, tv = rv.ravel().astype(float), tv.ravel().astype(float)
        proj, _ = cv2.projectPoints(obj, rv, tv, K, dist)
        err = proj.reshape(-1, 2) - c
        R, _ = cv2.Rodrigues(rv)
        out.append(BoardView(path=p, rvec=rv, tvec=tv, distance_m=float(np.linalg.norm(R @ centre + tv)),
                             rms_px=float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))),
                             corners_px=c.astype(np.float64) + 0.5))

    pitch = pixel_pitch_m if pixel_pitch_m is not None else PLACEHOLDER_PITCH_M
    camera = Camera.from_opencv(K, dist, size[0], size[1], pitch, bit_depth=int(bit_depth))
    s = np.asarray(std_in, dtype=float).ravel()
    std = dict(zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), (float(x) for x in s[:9])))
    if flags & CALIB_FLAGS_DEFAULT:  # fx = aspect * fy is not a free parameter; OpenCV reports 0 for it
        std["fx"] = aspect_ratio * std["fy"]
    return CalibrationResult(camera=camera, rms_px=float(rms), views=tuple(out), not_found=tuple(not_found),
                             unreadable=tuple(unreadable), board=board, square_m=float(square_m), flags=int(flags),
                             pixel_pitch_known=pixel_pitch_m is not None, std=std)

def calibrate_main(folder: str | Path, board="9x6", square: float = 0.025, output: str | Path | None = None,
                   pixel_pitch_um: float | None = None, *, quiet: bool = False) -> CalibrationResult:
    """In-process calibration of a folder (the ``dualsight calibrate`` command runs the same steps as a job of
    the engine, jobs/cli/calibrate.py).

    Calibrates from every image in ``folder`` (natural order), prints :func:`format_summary` unless
    ``quiet``, and writes the camera file to ``output`` if given.  ``board`` is "9x6" or (9, 6);
    ``square`` in metres; ``pixel_pitch_um`` in micrometres (None: unknown).
    """
    paths = list_images(folder)
    if not paths:
        raise ImageError("no images (.png .jpg .jpeg .tif .tiff .fits .fit .fts) in this folder", source=str(folder))
    result = calibrate_chessboard(paths, board=parse_board(board), square_m=float(square),
                                  pixel_pitch_m=None if pixel_pitch_um is None else float(pixel_pitch_um) * 1e-6)
    if output is not None:
        write_camera_toml(result, output, name=Path(folder).name)
    if not quiet:
        print(format_summary(result) + (f"\nwrote {output}" if output is not None else ""))
    return result

def parse_board(board) -> tuple[int, int]:
    """"9x6" (or (9, 6)) -> (9, 6): inner corners per row and per column."""
    if isinstance(board, str):
        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", board)
        if not m:
            raise ConfigError(f"must look like 9x6 (inner corners), got {board!r}", field="--board")
        board = (int(m.group(1)), int(m.group(2)))
    return _check_board(board)

def format_summary(result: CalibrationResult, rest_at: str | None = None) -> str:
    """Readable multi-line summary of a calibration; of the photos without a board and the unreadable ones the
    first :data:`SHOWN` of each are named, the rest counted (``rest_at``: where every one is listed)."""
    c = result.camera
    fh, fv, fd = (math.degrees(a) for a in c.fov_rad)
    sd = {k: result.std.get(k, float("nan")) for k in ("fx", "fy", "cx", "cy")}
    lines = [
        f"chessboard {result.board[0]}x{result.board[1]} inner corners, square {result.square_m * 1e3:g} mm; "
        f"board found in {len(result.views)} image(s)",
        f"image         {c.width} x {c.height} px, {c.bit_depth} bit",
        f"fx, fy        {c.fx:.3f} +- {sd['fx']:.3f}, {c.fy:.3f} +- {sd['fy']:.3f} px",
        f"cx, cy        {c.cx:.3f} +- {sd['cx']:.3f}, {c.cy:.3f} +- {sd['cy']:.3f} px from the top-left corner "
        f"(OpenCV convention: {c.cx - 0.5:.3f}, {c.cy - 0.5:.3f})",
        "focal length  " + (f"{result.focal_length_mm:.4f} mm at {c.pixel_pitch_m * 1e6:g} um pixels"
                            if result.pixel_pitch_known else "unknown in mm (pixel pitch not given)"),
        "distortion    k1 k2 p1 p2 k3 = " + " ".join(f"{x:.6g}" for x in c.distortion),
        f"field of view {fh:.2f} x {fv:.2f} deg (diagonal {fd:.2f})",
        f"RMS reprojection error {result.rms_px:.4f} px",
        f"{'image':<24} {'rms_px':>7} {'dist_m':>7}",
    ]
    lines += [f"{v.path.name:<24} {v.rms_px:7.3f} {v.distance_m:7.4f}" for v in result.views]
    if result.not_found:
        n = len(result.not_found)
        lines.append(f"board not found in{f' {n} images' if n > SHOWN else ''}: "
                     + _listed([p.name for p in result.not_found], ", ", rest_at))
    for p, why in result.unreadable[:SHOWN]:
        lines.append(f"unreadable: {p.name}: {why}")
    if len(result.unreadable) > SHOWN:
        lines.append(f"unreadable: {len(result.unreadable) - SHOWN} more images ({len(result.unreadable)} in all)"
                     + (f"; {rest_at}" if rest_at else ""))
    return "\n".join(lines)

def _check_board(board) -> tuple[int, int]:
    try:
        nx, ny = (int(x) for x in board)
        ok = all(float(x).is_integer() for x in board)
    except (TypeError, ValueError):
        ok = False
    if not ok or nx < 2 or ny < 2:
        raise ConfigError(f"must be two integers >= 2 (inner corners per row x per column), got {board!r}",
                          field="--board")
    return nx, ny
