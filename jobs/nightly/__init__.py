"""The nightly regression job: ``suite.py`` (the suites and their job specs), ``run.py`` (one night: run every
job, compare it with the accepted baseline, keep the verdicts), ``compare.py`` (metrics by SQL), ``stats.py``
(Fisher, bootstrap and permutation tests), ``store.py`` (the ``nightly_verdicts`` dataset and the baseline),
``text.py`` (what the command prints).  Imports the engine, the kinds (to make the specs) and the warehouse; the
command itself is jobs/cli/nightly.py.
"""
