#!/usr/bin/env bash
# Set up a virtual environment with every dependency, then run the main job on the embedded default
# (the paper's star-tracker Monte Carlo, 200 cases, in-process, into ./lake) and print its report.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e '.[dev]'
.venv/bin/dualsight star run --preset paper --cases 200 --seed 1 --run quickstart
.venv/bin/dualsight star report --run quickstart
