"""Taichi CPU kernels, batched over cases (leaves: arrays in, arrays out).

Modules, one stage each:

* star tracker: ``star_psf`` (PSF splat) -> ``starfield`` (sensor model, noise, ADC; ``render_star_fields``)
  -> ``detect`` (threshold, label, centroid; and the sparse noise-free path ``render_and_detect_ideal``)
  -> ``voting`` (geometric voting, step 1: vote counting) -> ``voting_select`` (steps 2-5: candidates,
  verification, acceptance);
* proximity: ``points`` (entry point, ``render``) dispatching to ``prox_splat`` (``paper``) or
  ``prox_triangles`` + ``prox_raster`` (``accurate``), both shading by ``prox_shading`` (Eqs. 2-3) with
  ``prox_geometry``; ``prox_sensor`` (blur, read noise, quantisation); ``blobs`` (the blobber's labelling);
* shared: ``labelling`` (the one connected-component labeller), ``rng`` (the one counter-based random
  number generator), ``_runtime`` (lazy Taichi start, ``KernelCache``).

Importing this package only sets Taichi's environment (no version check over the network, no banner on
stdout, which would corrupt ``--json`` output); the runtime itself is initialised lazily by
:func:`dualsight.kernels._runtime.ensure_init` at the first kernel call.
"""

import os as _os

_os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
