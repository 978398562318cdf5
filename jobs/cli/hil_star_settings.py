"""The ``hil_star`` settings of ``dualsight hil star``'s method options over a ``--config`` table: what the command
(jobs/cli/hil_star_command.py) and ``dualsight.solve`` (with the options' defaults from the command's parser) both
build a run's settings with.
"""

from __future__ import annotations

__all__ = ["settings_from_args"]


def settings_from_args(args, config: dict | None, epoch: float):
    """The ``hil_star`` settings of the command line's method options over the ``--config`` table."""
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table      # Taichi (the detectors' configs)

    return settings_from_table(config, source=str(args.config) if args.config else "hil star",
                               method=args.method, compare=not args.no_compare, detector=args.detector,
                               background_block_px=args.background_block, limit_arcsec=args.limit_arcsec,
                               mag_limit=args.mag_limit, epoch_jyear=epoch,
                               tolerance_arcsec=args.tolerance_arcsec, max_stars=args.max_stars,
                               k_sigma=args.k_sigma, min_pixels=args.min_pixels)
