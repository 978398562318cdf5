"""Binary segmentation of real photos of a target (proximity hardware in the loop, reference Sec. 2.4).

In the reference's order: optional undistortion, optional inversion (a dark object on a light
background), binary threshold on ANY colour channel, border clearing, opening then closing.

* :func:`score_image`: (H, W) "any channel" score, so that ``score >= T`` is exactly "any colour channel
  >= T" (after the optional inversion v -> full_scale - v per channel).
* :func:`binarize`: that comparison.
* :func:`clear_border`: the outer PX pixels to background (frame-grabber edges).
* :func:`morphology`: opening with a K x K square, then closing (OpenCV ``morphologyEx``, ``MORPH_RECT``,
  anchor at the centre, OpenCV's default border handling, so the frame edge neither erodes nor dilates);
  K <= 1 is off.
* :func:`foreground_masks`: all of the above for several thresholds, as float32 binary frames for the
  blobber.
* :func:`undistort_image`: remap to the ideal pinhole with the same fx, fy, cx, cy.

numpy plus OpenCV.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from dualsight.scene.camera import Camera

__all__ = ["score_image", "binarize", "clear_border", "morphology", "foreground_masks", "undistort_image"]


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


def foreground_masks(score: np.ndarray, thresholds, *, border_px: int = 0, open_px: int = 0,
                     close_px: int = 0) -> np.ndarray:
    """(len(thresholds), H, W) float32 binary images (1 foreground): threshold, border, open, close."""
    out = np.empty((len(thresholds),) + score.shape, np.float32)
    for k, t in enumerate(thresholds):  # one threshold at a time: OpenCV morphology per 2-D mask
        m = (score >= np.float32(t)).astype(np.uint8)
        clear_border(m, border_px)
        out[k] = morphology(m, open_px, close_px)
    return out


def undistort_image(pixels: np.ndarray, camera: Camera, fill: float = 0.0) -> tuple[np.ndarray, Camera]:
    """Remap an image to the ideal pinhole with the same fx, fy, cx, cy (no distortion).

    OpenCV ``initUndistortRectifyMap`` + bilinear ``remap``.  Returns the remapped image (same dtype;
    pixels from outside the frame = ``fill``) and the camera without distortion to use with it.  A
    camera without distortion returns the input unchanged."""
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
    cam0 = dataclasses.replace(camera, distortion=(0.0,) * 5)
    return out.astype(a.dtype, copy=False), cam0
