"""Defaults of the HIL commands that the command-line parser needs without importing the job modules
(the parser is built on every ``dualsight`` call; the job modules pull in Taichi, pyarrow and OpenCV)."""

DEFAULT_THRESHOLD = 230.0
"""``hil prox`` binary threshold in image units: the reference's best threshold on its 8-bit HIL images
(Sec. 2.4, Figure 8)."""
