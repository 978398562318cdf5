"""The leaf layer: batched array kernels (Taichi on the CPU, numpy, OpenCV): arrays in, arrays out, no file
reading (images and PSF files are read in :mod:`dualsight.scene`: ``imageio``, ``psf_file``).

Star tracker: ``sensor_config`` (the sensor model) -> ``star_psf`` / ``psf_models`` (a measured PSF as an array:
``psf_image``) -> ``starfield`` (render, with ``sky_noise``'s tables) -> ``detect`` (global threshold; smooth
background: ``background``) or ``detect_local`` (real sensors: ``detect_background`` -> ``detect_candidates`` ->
``detect_psf``; compiled passes ``detect_passes``) -> ``voting``, ``voting_select``.  Proximity: ``points`` ->
``prox_*``; ``blobs``.  Shared: ``labelling`` (the one labeller), ``rng``, ``digest``, ``taichi_runtime`` (lazy
Taichi start, KernelCache).

Imports allowed: numpy, taichi, OpenCV, pydantic (the configs' field bounds) and, of the project, only the root
utilities ``dualsight.errors``, ``dualsight.config``, ``dualsight.version`` and ``dualsight.allocator``.

Taichi's environment (no banner, no version check) is set by the root package before any module can import
taichi; the runtime starts at the first kernel call (:func:`dualsight.kernels.taichi_runtime.ensure_init`).
"""
