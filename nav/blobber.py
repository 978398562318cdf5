"""The blobber (Walker & Spencer 2012; reference Sec. 2.1): direction and range to a nearby spacecraft.

Per frame (batched over B frames):

1. threshold the image and label its blobs (kernels/blobs.py); the target is the largest blob
   (or, ``target="all"``, every foreground pixel);
2. centre of brightness (intensity-weighted centroid, pixel centres at +0.5) -> unit vector in the
   camera frame through ``Camera.backproject``;
3. second central moments of the blob -> 2x2 covariance -> eigenvalues lambda_1 >= lambda_2 ->
   major/minor axes (full lengths of the equivalent uniform ellipse, 4 sqrt(lambda)) and the axis
   ratio sqrt(lambda_1 / lambda_2);
4. projected area from the table (catalogs/areas.py) at the observed axis ratio: A_min, A_mean (or
   another curve), A_max;
5. range by Eq. 1, rho = f sqrt(A / (N_blob p^2)): minimum from A_min, estimate from A_mean,
   maximum from A_max; relative position = range x unit vector.

Estimators (named, side by side):

``paper`` -- exactly the reference: N_blob is the whole-pixel count of the blob, moments of the
    binary blob (pixel centres), A from the ``mean`` curve, Eq. 1 as printed.
``subpixel`` -- N_blob is the blob's summed coverage (the fraction of every pixel the object covers;
    from the ``accurate`` renderer, or 1 per foreground pixel for images without coverage, e.g.
    real photos), moments weighted by coverage plus each pixel's own variance 1/12 (Sheppard's
    correction, so that a filled a x b rectangle has covariance diag(a^2, b^2)/12 exactly as the
    table's continuous silhouettes), the area curve that minimises the mean squared relative range
    error (``relopt``, see catalogs/areas.py), and Eq. 1 corrected for the field angle theta of the
    line of sight, rho = sqrt(fx fy A / (N cos^3 theta)) (nav/range.py: ``range_oblique``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from dualsight.config import check_fields
from dualsight.kernels.blobs import label_blobs
from dualsight.nav.blobber_names import AreaCurve, Estimator, Target
from dualsight.nav.range import range_eq1, range_oblique

_DEFAULT_CURVE = {"paper": "mean", "subpixel": "relopt"}


@dataclass(frozen=True)
class BlobberConfig:
    """Blobber settings.

    Every field's range is part of its type (pydantic ``Field``), checked when a TOML table is validated
    (``dualsight.config.validate``) and when the dataclass is built in Python (ValueError naming the
    field, the value and the allowed range).

    Attributes
    ----------
    estimator : "paper" (reference Eq. 1 exactly) or "subpixel" (see module docstring).
    threshold : foreground is ``image > threshold`` (image units: rendered intensity or ADU), in
        [0, 1e12]; 0 = every lit pixel of a rendered image (a negative threshold would make the whole
        frame one blob; 1e12 is above any ADU or rendered radiance, as the prox spec's bound).
    connectivity : 8 or 4.
    target : "largest" blob or "all" foreground pixels as one blob.
    area_curve : table curve for the range estimate ("min", "mean", "max", "median", "relopt");
        None = the estimator's default ("mean" for paper, "relopt" for subpixel).
    min_pixels : a frame whose target blob has fewer whole pixels is "not found" (NaN outputs); an
        integer in [1, 2^32] (the pixels of the largest frame, 65536^2).
    """

    estimator: Estimator = "paper"
    threshold: Annotated[float, Field(ge=0.0, le=1e12)] = 0.0
    connectivity: Literal[4, 8] = 8
    target: Target = "largest"
    area_curve: AreaCurve | None = None
    min_pixels: Annotated[int, Field(ge=1, le=2 ** 32)] = 1

    def __post_init__(self):
        check_fields(self, units={"min_pixels": "px"})

    @property
    def curve(self) -> str:
        return self.area_curve or _DEFAULT_CURVE[self.estimator]


@dataclass(frozen=True)
class BlobResult:
    """Blobber outputs, one row per frame (NaN where ``found`` is False).

    Attributes
    ----------
    found : (B,) bool.  n_blobs : (B,) number of blobs in the frame.
    n_pixels : (B,) whole pixels in the target blob.  n_coverage : (B,) summed coverage of those pixels.
    n_blob : (B,) the N_blob used in Eq. 1 (n_pixels for paper, n_coverage for subpixel).
    cob_px : (B, 2) centre of brightness (col, row), pixels from the top-left corner.
    centre_px : (B, 2) the blob's geometric centre (col, row): the mean of its pixels' centres (``paper``) or
        weighted by their coverage (``subpixel``: the centroid of the silhouette), whatever their brightness.
    unit : (B, 3) unit vector to the COB, camera frame.
    cov_px : (B, 2, 2) second central moments of the blob (px^2) used for the axes.
    major_px, minor_px : (B,) axis lengths 4 sqrt(lambda) (px).  axis_ratio : (B,) >= 1.
    angle_rad : (B,) major-axis direction from +col towards +row.
    area_rel_min, area_rel_est, area_rel_max : (B,) A/A0 from the table.
    range_min, range_est, range_max : (B,) m.
    position : (B, 3) range_est x unit (m, camera frame).
    box : (B, 4) [x0, y0, x1, y1] inclusive bounding box of the largest blob.
    """

    found: np.ndarray
    n_blobs: np.ndarray
    n_pixels: np.ndarray
    n_coverage: np.ndarray
    n_blob: np.ndarray
    cob_px: np.ndarray
    unit: np.ndarray
    centre_px: np.ndarray
    cov_px: np.ndarray
    major_px: np.ndarray
    minor_px: np.ndarray
    axis_ratio: np.ndarray
    angle_rad: np.ndarray
    area_rel_min: np.ndarray
    area_rel_est: np.ndarray
    area_rel_max: np.ndarray
    range_min: np.ndarray
    range_est: np.ndarray
    range_max: np.ndarray
    position: np.ndarray
    box: np.ndarray

    def as_columns(self, prefix: str = "") -> dict:
        """Flat dict of 1-D columns (vectors split into _x/_y/_z), e.g. for an Arrow record batch."""
        out = {}
        for k, v in self.__dict__.items():
            v = np.asarray(v)
            if v.ndim == 1:
                out[prefix + k] = v
            elif k == "cov_px":
                out[prefix + "cov_xx"] = v[:, 0, 0]
                out[prefix + "cov_xy"] = v[:, 0, 1]
                out[prefix + "cov_yy"] = v[:, 1, 1]
            elif k == "box":
                for i, s in enumerate(("x0", "y0", "x1", "y1")):
                    out[f"{prefix}box_{s}"] = v[:, i]
            else:
                for i, s in enumerate("xyz"[: v.shape[1]]):
                    out[f"{prefix}{k}_{s}"] = v[:, i]
        return out


def moments_to_axes(cxx, cxy, cyy):
    """Eigen-decomposition of 2x2 covariances [[cxx, cxy], [cxy, cyy]] (closed form).

    Returns lambda_1 >= lambda_2 >= 0, the axis ratio sqrt(lambda_1/lambda_2) (1 when both are 0,
    inf when only lambda_2 is 0) and the major-axis angle atan2(2 cxy, cxx - cyy) / 2.
    """
    cxx, cxy, cyy = (np.asarray(a, dtype=np.float64) for a in (cxx, cxy, cyy))
    tr = 0.5 * (cxx + cyy)
    d = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
    l1, l2 = tr + d, np.maximum(tr - d, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(l1 > 0, np.sqrt(l1 / l2), 1.0)
    return l1, l2, ratio, 0.5 * np.arctan2(2 * cxy, cxx - cyy)


def run_blobber(images, camera, table, config: BlobberConfig = BlobberConfig(), coverage=None) -> BlobResult:
    """Run the blobber on a batch of images.

    Parameters
    ----------
    images : (B, H, W) or (H, W) float images (target bright on dark).
    camera : scene.camera.Camera (focal length, pixel pitch, backprojection).
    table : catalogs.areas.AreaTable of the target's shape.
    config : BlobberConfig.
    coverage : optional (B, H, W) per-pixel coverage (the accurate renderer's); used by ``subpixel``.
    """
    cfg = config
    lab = label_blobs(images, cfg.threshold, coverage if cfg.estimator == "subpixel" else None, cfg.connectivity)
    S = lab["best"] if cfg.target == "largest" else lab["all"]
    n_pix = S[:, 0]
    found = n_pix >= cfg.min_pixels
    with np.errstate(divide="ignore", invalid="ignore"):
        if cfg.estimator == "paper":
            w, sx, sy, sxx, sxy, syy = S[:, 0], S[:, 1], S[:, 2], S[:, 3], S[:, 4], S[:, 5]
            extra = 0.0
        else:
            w, sx, sy, sxx, sxy, syy = S[:, 9], S[:, 10], S[:, 11], S[:, 12], S[:, 13], S[:, 14]
            extra = 1.0 / 12.0
        mx, my = sx / w, sy / w
        cxx = sxx / w - mx * mx + extra
        cxy = sxy / w - mx * my
        cyy = syy / w - my * my + extra
        # centre of brightness; falls back to the geometric centroid where the blob has no flux
        sI = S[:, 6]
        cob = np.where((sI > 0)[:, None], np.stack([S[:, 7] / sI, S[:, 8] / sI], -1), np.stack([mx, my], -1))
    l1, l2, ratio, angle = moments_to_axes(cxx, cxy, cyy)
    unit = camera.backproject(np.where(found[:, None], cob, np.array([camera.cx, camera.cy])))
    n_blob = n_pix if cfg.estimator == "paper" else S[:, 9]
    r = np.where(found, ratio, np.nan)
    a_min, a_est, a_max = table.lookup(r, "min"), table.lookup(r, cfg.curve), table.lookup(r, "max")
    A0 = table.A0_m2
    if cfg.estimator == "paper":
        f, p = camera.focal_length_m, camera.pixel_pitch_m
        rng = [range_eq1(n_blob, a * A0, f, p) for a in (a_min, a_est, a_max)]
    else:
        rng = [range_oblique(n_blob, a * A0, camera.fx, camera.fy, unit[:, 2]) for a in (a_min, a_est, a_max)]
    nan = np.where(found, 1.0, np.nan)
    cov = np.stack([np.stack([cxx, cxy], -1), np.stack([cxy, cyy], -1)], -2) * nan[:, None, None]
    return BlobResult(
        found=found, n_blobs=lab["n_blobs"].astype(np.int64), n_pixels=n_pix.astype(np.int64),
        n_coverage=S[:, 9].copy(), n_blob=np.asarray(n_blob, dtype=np.float64) * nan,
        cob_px=cob * nan[:, None], unit=unit * nan[:, None], centre_px=np.stack([mx, my], -1) * nan[:, None],
        cov_px=cov,
        major_px=4.0 * np.sqrt(l1) * nan, minor_px=4.0 * np.sqrt(l2) * nan, axis_ratio=r,
        angle_rad=angle * nan, area_rel_min=a_min, area_rel_est=a_est, area_rel_max=a_max,
        range_min=rng[0] * nan, range_est=rng[1] * nan, range_max=rng[2] * nan,
        position=rng[1][:, None] * unit * nan[:, None], box=lab["box"])
