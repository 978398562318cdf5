"""A chessboard's inner corners: on the board plane, and found in one photo -- the first stage of a camera
calibration (:mod:`dualsight.scene.calibration` solves the camera from them), the per-photo work of the
``calibrate`` job kind (jobs/kinds/calibrate.py).

Method: OpenCV's ``cv2.findChessboardCorners`` (inner corners; the flags of OpenCV's calibration sample) and
``cv2.cornerSubPix`` (11x11 window, as OpenCV's ``samples/cpp/calibration.cpp``) on an 8-bit gray copy of the
photo (16-bit and float data scaled by their full scale).  Corners are (col, row) in OpenCV's pixel convention
(pixel centres at integers).  The board's own coordinates (:func:`board_points`) are OpenCV's: origin at the
first inner corner, x along the board's ``board[0]`` corners, z = 0 on the board, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualsight.errors import ImageError
from dualsight.kernels.digest import frame_digest, to_int64
from dualsight.scene.imageio import Image, read_image

__all__ = ["FIND_FLAGS_DEFAULT", "board_points", "find_corners", "ViewCorners", "find_view"]

#: Corner detection flags of OpenCV's calibration sample.
FIND_FLAGS_DEFAULT = 1 | 2 | 8  # CALIB_CB_ADAPTIVE_THRESH | CALIB_CB_NORMALIZE_IMAGE | CALIB_CB_FAST_CHECK


def board_points(board: tuple[int, int], square_m: float) -> np.ndarray:
    """(N, 3) float32 inner-corner coordinates on the board plane (m), OpenCV's order:
    x fastest along ``board[0]``, z = 0; N = board[0] * board[1]."""
    nx, ny = board
    g = np.zeros((nx * ny, 3), np.float32)
    g[:, :2] = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2) * square_m
    return g

def find_corners(gray8: np.ndarray, board: tuple[int, int], find_flags: int = FIND_FLAGS_DEFAULT,
                 window: int = 11) -> np.ndarray | None:
    """Sub-pixel inner corners of a chessboard in an 8-bit gray image.

    Returns
    -------
    (N, 2) float32 corners (col, row) in OpenCV's convention (pixel centres at integers), or None
    when the board is not found.
    """
    import cv2

    ok, c = cv2.findChessboardCorners(gray8, tuple(board), flags=find_flags)
    if not ok or c is None:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-4)  # as OpenCV's calibration sample
    c = cv2.cornerSubPix(gray8, c, (window, window), (-1, -1), crit)
    return c.reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class ViewCorners:
    """What one photo gave: its size, and the board's inner corners or why there are none.

    Attributes
    ----------
    path : the image file.
    width, height, bit_depth : the image (None when it could not be read).
    corners : (N, 2) float32 corners (col, row) in OpenCV's convention (pixel centres at integers), or
        None when the board was not found or the image could not be read.
    error : why the image could not be read (None if it was).
    digest : the decoded frame's digest as int64 (:mod:`dualsight.kernels.digest`), None if unread.
    """

    path: Path
    width: int | None = None
    height: int | None = None
    bit_depth: int | None = None
    corners: np.ndarray | None = None
    error: str | None = None
    digest: int | None = None

def find_view(path: str | Path, board: tuple[int, int] = (9, 6), find_flags: int = FIND_FLAGS_DEFAULT) -> ViewCorners:
    """Read one photo (gray; 16-bit / float scaled to 8 bit) and find the board's sub-pixel inner corners."""
    path = Path(path)
    try:
        img = read_image(path, as_gray=True)
    except ImageError as e:
        return ViewCorners(path, error=e.detail)
    return ViewCorners(path, img.width, img.height, img.bit_depth or 8,
                       find_corners(_to_gray8(img), board, find_flags),
                       digest=int(to_int64(frame_digest(img.pixels[None]))[0]))

def _to_gray8(img: Image) -> np.ndarray:
    """8-bit gray copy of an image for corner detection (16-bit/float scaled by their full scale)."""
    a = img.pixels if img.pixels.ndim == 2 else img.pixels[..., 0]
    if a.dtype == np.uint8:
        return a
    if img.bit_depth is None:  # float: assume [0, 1] unless larger values occur
        scale = 255.0 / max(1.0, float(np.nanmax(a)))
    else:
        scale = 255.0 / img.full_scale
    return np.clip(np.nan_to_num(a.astype(np.float64) * scale), 0, 255).astype(np.uint8)
