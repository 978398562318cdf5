"""dualsight: end-to-end test bench for a dual-use small-satellite camera.

The import package's sub-packages live in the repository's top-level folders
(``scene/``, ``nav/``, ``kernels/``, ``catalogs/``, ``jobs/``, ``warehouse/``,
``viz/``), mapped by ``package-dir`` in ``pyproject.toml``.  This folder holds
only the root package itself.
"""

__version__ = "0.1.0"

from dualsight import allocator as _allocator

_allocator.tune()
