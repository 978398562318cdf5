"""The one engine every job runs on: ``runner.py`` (run identity, plan, shards, executors, resume, the
``JOB_KINDS`` table), ``dask_executor.py`` (shards on a Dask cluster), ``lakecheck.py`` (verify and repair every
run), ``specs.py`` (preset + TOML + flags -> a spec dict, and the memory check), ``errors.py`` (its errors).

The engine imports the warehouse, scene (TOML files) and the root utilities.  It reaches the job kinds only
through ``JOB_KINDS`` (importlib of a fixed table of module names, never a user-supplied path) and never imports
cli or reports.
"""
