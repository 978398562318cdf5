"""Taichi CPU kernels, batched over cases (leaves: arrays in, arrays out).

Importing this package only sets Taichi's environment (no version check over the network, no banner on
stdout, which would corrupt ``--json`` output); the runtime itself is initialised lazily by
:func:`dualsight.kernels._runtime.ensure_init` at the first kernel call.
"""

import os as _os

_os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
