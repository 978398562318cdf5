"""The Parquet lake and its SQL: ``lake.py`` (layout, atomic self-describing shards, manifests, journals, locks),
``shards.py`` (a shard file's identity and checks), ``paths.py`` (the default lake and the run-id rule, without
pyarrow), ``query.py`` (DuckDB's read-only views, the report SQL of ``sql/*.sql``, tables as text).  It moves
Arrow tables and JSON and knows no algorithm: it imports pyarrow, DuckDB, scene (angle units) and the root
utilities, never nav, kernels, catalogs, jobs or Taichi (import-linter contract ``warehouse-no-algorithm``).
"""
