"""Replay: a case re-rendered (or its real image re-read) bit-identically from its row, verified against the row
(frame digest and every stored metric) and recorded for rerun (``cases.py`` for every kind, ``prox.py`` for
proximity cases and trajectory videos, ``run.py`` for the cases of a run chosen by SQL).  Imports the kinds, the engine's ``job_module``, the warehouse and
viz/recording.py; never cli.
"""
