"""Drawing: rerun recordings (``recording.py``), figures (``figures.py``: matplotlib on Agg, saving, PNG bytes and
thumbnails; ``prox_figures``, ``star_figures``, ``threshold_sweep``, ``overlay``, ``nightly_html``) and
self-contained HTML pages (``html_page.py``).  viz draws the arrays and query results it is given: it imports
numpy, matplotlib, OpenCV, rerun, the layers below it and the root utilities, and never jobs, ``dualsight.api``
or Taichi (import-linter contract ``viz-no-jobs``).
"""
