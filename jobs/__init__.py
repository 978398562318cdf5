"""The wiring of dualsight: the job kinds, the one engine that runs them into the lake, and the command line,
reports, replay and nightly job built on them.  No algorithm lives here (scene, nav, kernels, catalogs hold them)
and no drawing (viz).  jobs may import every package below it (warehouse, viz, nav, catalogs, scene, kernels and
the root utilities); only ``dualsight.api`` imports jobs.

Subpackages: ``cli`` (the ``dualsight`` command), ``engine`` (runs a kind's shards), ``kinds`` (one module per
job kind), ``reports``, ``replay``, ``nightly``.
"""
