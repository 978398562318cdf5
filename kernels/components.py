"""The output of the labeller (:mod:`dualsight.kernels.labelling`): :class:`Components`, the connected
components of a batch of segments with their runs and moment sums (a leaf: numpy only).

Moment sums (float64, pixel centres at (col + 0.5, row + 0.5); ``I = value - offset``, ``w`` the coverage):

    0 n      1 sum x    2 sum y    3 sum x^2   4 sum x y   5 sum y^2         (whole pixels)
    6 sum I  7 sum I x  8 sum I y                                            (intensity)
    9 sum w  10 sum w x 11 sum w y 12 sum w x^2 13 sum w x y 14 sum w y^2   (coverage)
"""

from dataclasses import dataclass

import numpy as np

__all__ = ["NSTAT", "STAT_NAMES", "Components"]

NSTAT = 15
STAT_NAMES = ("n", "sx", "sy", "sxx", "sxy", "syy", "sI", "sIx", "sIy", "sw", "swx", "swy", "swxx", "swxy", "swyy")


@dataclass(frozen=True, eq=False)
class Components:
    """Connected components of a batch of segments, and the runs of foreground pixels they are made of.

    Components are numbered segment by segment, in the raster order of their first pixel; runs are in
    raster order (segment, row, column).

    Attributes
    ----------
    npix : (NC,) int32 pixels of each component.
    box : (NC, 4) int32 inclusive bounding box [x0, y0, x1, y1] (image columns and rows).
    seg : (NC,) int32 segment of each component.
    offsets : (NS + 1,) int64; segment s's components are [offsets[s], offsets[s + 1]).
    seg_stats : (NS, NSTAT) float64 sums (module docstring) over all foreground pixels of each segment.
    run_c0, run_c1 : (R,) int32 image columns of each run, half-open [c0, c1).
    run_row : (R,) int32 image row of each run.
    run_seg : (R,) int32 segment of each run.
    run_label : (R,) int32 component of each run.
    run_sums : (R, 5) float64 sums of each run: sum I, sum I x, sum w, sum w x, sum w x^2.
    seg_runs : (NS + 1,) int32; segment s's runs are [seg_runs[s], seg_runs[s + 1]).
    comp_moments : (NC, NSTAT) float64 moment sums of each component (read through :meth:`moments`).
    """

    npix: np.ndarray
    box: np.ndarray
    seg: np.ndarray
    offsets: np.ndarray
    seg_stats: np.ndarray
    run_c0: np.ndarray
    run_c1: np.ndarray
    run_row: np.ndarray
    run_seg: np.ndarray
    run_label: np.ndarray
    run_sums: np.ndarray
    seg_runs: np.ndarray
    comp_moments: np.ndarray

    def __len__(self) -> int:
        return len(self.seg)

    @property
    def counts(self) -> np.ndarray:
        """(NS,) components per segment."""
        return np.diff(self.offsets)

    def moments(self, which=None) -> np.ndarray:
        """(K, NSTAT) float64 moment sums (module docstring) of components ``which`` ((K,) distinct indices;
        None = all), each the sum of its runs' sums in raster order (so bit-identical whatever else is asked)."""
        if which is None:
            return self.comp_moments.copy()
        return self.comp_moments[np.asarray(which, dtype=np.int64).reshape(-1)]

    def paint(self, out: np.ndarray, runs, values) -> np.ndarray:
        """Write ``values`` (a scalar or one value per selected run) into ``out[seg, row, col]`` over the pixels
        of the selected ``runs`` (indices or a bool mask over the runs) and return ``out``.  For dense frames
        (:func:`label_frames`, segment b = frame b) ``out`` is (B, H, W).  Vectorised over runs and pixels."""
        runs = np.flatnonzero(runs) if np.asarray(runs).dtype == bool else np.asarray(runs, dtype=np.int64)
        lens = (self.run_c1[runs] - self.run_c0[runs]).astype(np.int64)
        total = int(lens.sum())
        if total == 0:
            return out
        first = np.cumsum(lens) - lens
        xx = np.repeat(self.run_c0[runs].astype(np.int64), lens) + (np.arange(total) - np.repeat(first, lens))
        vals = values if np.ndim(values) == 0 else np.repeat(np.asarray(values), lens)
        out[np.repeat(self.run_seg[runs], lens), np.repeat(self.run_row[runs], lens), xx] = vals
        return out

    def label_image(self, shape) -> np.ndarray:
        """(B, H, W) int32 label image of dense frames: 0 = background, k + 1 - offsets[b] for component k
        of frame b (so 1..n per frame, like OpenCV's ``connectedComponents``)."""
        out = np.zeros(shape, np.int32)
        lab = self.run_label.astype(np.int64)
        return self.paint(out, np.arange(lab.size), lab + 1 - self.offsets[self.run_seg])
