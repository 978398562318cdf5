"""One module per job kind (``star``, ``prox``, ``hil_star``, ``hil_star_sweep``, ``hil_prox``, ``calibrate``,
``peer_star``, ``selftest``), each with its spec, case sampling and ``compute_shard`` (the contract in
jobs/engine/runner.py), and what a kind needs beside it (``star_tables``, ``star_summaries``, ``hil_star_spec``,
``hil_truth``, ``hil_common``, ``hil_defaults``, ``fit_distortion``).

A kind wires the stages of scene, nav, kernels and catalogs and may import them, the engine and the warehouse.
It never imports reports or cli (``peer_star``'s documented ``python -m`` entry runs the ``dualsight`` program
instead).
"""
