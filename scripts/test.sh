#!/usr/bin/env bash
# Run the test suite (needs the environment made by scripts/quickstart.sh).
# The HTML report is checked in real headless Chromium: Debian's `chromium` package is installed here when it is
# missing and this runs as root with apt (otherwise those tests are skipped, with the reason).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing Debian's chromium for the HTML report tests" >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) >/dev/null 2>&1 \
        || echo "could not install chromium; its tests will be skipped" >&2
fi
exec .venv/bin/python -m pytest -q "$@"
