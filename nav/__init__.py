"""The flight algorithms over observations: star identification by geometric voting (``starid`` chaining
``pair_index``, ``votes``, ``candidates``, ``verify``, ``cliques``, ``attitude_check``, ``residual_check``,
``widen``, ``chance``; settings in ``voting_config``), attitude and its errors (``observations``, ``attitude``,
``star_solution``, ``errors``, ``truth_match``, ``hil_score``), the blobber's direction and range (``blobber``,
``range``) and the camera fitted from the sky (``distortion_fit``, ``distortion_procedure``).

Imports allowed: numpy, pydantic, ``dualsight.kernels``, ``dualsight.scene``, ``dualsight.catalogs`` and the root
utilities; nav knows nothing of storage, runners or drawing (no warehouse, jobs or viz; no pyarrow, duckdb,
matplotlib or rerun).
"""
