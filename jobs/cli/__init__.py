"""The ``dualsight`` command line: ``main.py`` (the parser, the ``COMMAND_KINDS`` table, the star, sql, runs,
replay, report, selftest and lake commands, one-line errors and exit statuses), ``args.py`` (options shared by the
command groups), one module per command group (``prox``, ``hil_star``, ``hil_prox``, ``calibrate``, ``nightly``,
``peer``; ``hil_star_settings.py``: hil star's options -> settings, shared with ``dualsight.solve``).  A command
that needs Taichi, the lake or the scene stack runs from ``<group>_command.py`` or imports its kind, report or
replay module when it runs, so that ``dualsight --help`` imports neither numpy nor pydantic.

cli may import every other part of jobs and everything below it; nothing imports cli but ``dualsight.api`` (the
``hil star`` options and settings).
"""
