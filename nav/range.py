"""Range from blob size (reference Eq. 1) and the resolvable range of a camera (reference Sec. 2.3, Fig. 5).

Pure numpy; every function is vectorised over a leading batch axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def range_eq1(n_blob, area_m2, focal_length_m: float, pixel_pitch_m: float) -> np.ndarray:
    """Reference Eq. 1 (Walker & Spencer 2012): rho = f sqrt(A / (N_blob p^2)).

    Parameters
    ----------
    n_blob : (B,) number of pixels the object illuminates (may be fractional).
    area_m2 : (B,) projected area A of the object (m^2), e.g. A_mean from the projected-area table.
    focal_length_m, pixel_pitch_m : f and p (m).

    Returns
    -------
    (B,) range (m); NaN where n_blob <= 0.
    """
    n = np.asarray(n_blob, dtype=np.float64)
    a = np.asarray(area_m2, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n > 0, focal_length_m * np.sqrt(a / (n * pixel_pitch_m ** 2)), np.nan)


def range_oblique(n_blob, area_m2, fx: float, fy: float, cos_field) -> np.ndarray:
    """Eq. 1 corrected for the field angle theta of the line of sight.

    A patch of area A seen at range rho and field angle theta subtends the solid angle A / rho^2,
    and the pinhole maps solid angle to image area f^2 / cos^3(theta) (pixels: fx fy / cos^3), so
    N = fx fy A / (rho^2 cos^3 theta) and rho = sqrt(fx fy A / (N cos^3 theta)).  theta = 0 is Eq. 1.
    """
    n = np.asarray(n_blob, dtype=np.float64)
    a = np.asarray(area_m2, dtype=np.float64)
    c3 = np.asarray(cos_field, dtype=np.float64) ** 3
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n > 0, np.sqrt(fx * fy * a / (n * c3)), np.nan)


@dataclass(frozen=True)
class ResolvableRange:
    """Nearest and farthest range (m) at which a camera resolves an object of characteristic size h.

    Attributes
    ----------
    near_fit_m : h spans the frame's *short* side (rows): f_px h / H.  The whole object is still in the
        frame (a blob with a centre and an area); nearer, it is cut by the frame edges.  This is the
        nearest resolvable range.
    near_fill_m : h spans the frame's *long* side (columns): f_px h / W.  A face h x h then covers every
        pixel (the object "fills the entire frame") but overflows the short side.
    far_m : the object covers 2 x 2 pixels (h spans 2 pixels): f_px h / 2.
    reference_near_m : the reference's way to 8.4 cm, f (h/2) / (H p) -- see :func:`resolvable_range`.
    """

    near_fit_m: float
    near_fill_m: float
    far_m: float
    reference_near_m: float

    @property
    def near_m(self) -> float:
        return self.near_fit_m


def resolvable_range(camera, size_m: float) -> ResolvableRange:
    """Resolvable range by similar triangles (reference Sec. 2.3, Fig. 5): rho = f h / (n p) when the
    object of size h spans n pixels of pitch p (in pixels: rho = f_px h / n).

    For the reference's Table 1 camera (1024 x 768 px, 4.65 um, f = 6 mm, f_px = 1290.3) and
    h = 0.1 m:

    * farthest, h over 2 pixels: f h / (2 p) = 6 mm x 0.1 m / 9.3 um = **64.5 m** (the reference's 64 m);
    * nearest, h spanning the 768-pixel short side (3.571 mm of sensor): 6 mm x 0.1 m / 3.571 mm
      = **16.8 cm** -- the whole 0.1 m face just fits in the frame's height (and uses 768 of the
      1024 columns);
    * h spanning the 1024-pixel long side (4.762 mm): **12.6 cm** -- the face then covers every
      pixel, but is cut at top and bottom.

    The reference's 8.4 cm is half of 16.8 cm: 6 mm x 0.05 m / 3.571 mm = 8.40 cm, i.e. *half* the
    object (h/2 = 5 cm) against the *whole* sensor height -- the similar triangles of Fig. 5 mix the
    half-size of the object (measured from the boresight) with the full size of the sensor; with
    the half-height of the sensor (1.786 mm) it would give 16.8 cm again.  At 8.4 cm a 0.1 m face
    spans 1536 rows, twice the frame height.  (For a 3U CubeSat seen broadside, its 0.3 m length
    along the long side fits from 37.8 cm.)
    """
    fx, fy = float(camera.fx), float(camera.fy)
    W, H = int(camera.width), int(camera.height)
    h = float(size_m)
    # short and long side in pixels with their focal lengths in pixels along that axis
    (n_short, f_short), (n_long, f_long) = sorted([(H, fy), (W, fx)])
    far = 0.5 * (fx + fy) * h / 2.0
    return ResolvableRange(near_fit_m=f_short * h / n_short, near_fill_m=f_long * h / n_long, far_m=far,
                           reference_near_m=f_short * (h / 2.0) / n_short)
