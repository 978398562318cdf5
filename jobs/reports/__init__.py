"""What a run's reports print: text, JSON and the self-contained HTML page of a run (``star``, ``prox``,
``hil_star``, ``hil_prox``, ``fit_distortion``, ``html``), every number read back from the lake by the warehouse
SQL.  Reports may import the kinds (their datasets; re-rendering the worst cases), the warehouse, nav (threshold
choice) and viz, which draws their figures; they never import cli.
"""
