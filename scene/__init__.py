"""The scene: what the camera looks at and how it sees it, as geometry over arrays, and the files it is read from.

Angle units and attitude math (``units``, ``attitude``, ``pointing``, ``case_rng`` for the cases' random
streams); the camera model and its files (``camera``, ``camera_file``); calibration from chessboard photos
(``chessboard`` -> ``calibration``); stars in the field (``starfield_geometry``); the target spacecraft's point
cloud and motion (``primitives``, ``satellite``, ``motion``) and its segmentation in photos (``segment``); the
truth of real night-sky frames (``skytruth``, ``timescale``); reading image files (``imageio``: PNG, JPEG, TIFF,
FITS, with one-line errors) and a sensor's measured PSF file (``psf_file``: read, checked and hashed into the
spec, handed to the renderer as an array).

Imports allowed: numpy, OpenCV, astropy, pydantic, tomli-w, ``dualsight.kernels`` and the root utilities
(``dualsight.errors``, ``dualsight.config``, ``dualsight.version``, ``dualsight.allocator``); never catalogs, nav,
warehouse, viz or jobs.
"""
