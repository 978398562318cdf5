#!/usr/bin/env bash
# Run the test suite (needs the environment made by scripts/quickstart.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python -m pytest -q "$@"
