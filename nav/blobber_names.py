"""The blobber's named choices, importable without the blobber's kernels (the CLI parser lists them)."""

from typing import Literal, get_args

Estimator = Literal["paper", "subpixel"]
"""Range estimators: the reference's Eq. 1 on whole pixels, or dualsight's sub-pixel area estimate."""
Target = Literal["largest", "all"]
"""Which blob is the target: the largest one, or all foreground pixels together."""
AreaCurve = Literal["min", "mean", "max", "median", "relopt"]
"""Which curve of the area table converts the blob's axis ratio into an area."""
ESTIMATORS = get_args(Estimator)
TARGETS = get_args(Target)
