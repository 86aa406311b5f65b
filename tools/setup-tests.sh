#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine:
#   - the project with its test extras (pytest, selenium), editable;
#   - Debian's chromium + chromium-driver for the viewer's browser test (apt; sudo when not root).
# Without apt (another OS) the browser test is skipped and says why; everything else runs.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -e ".[test]"
if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then
    echo "chromium and chromedriver present"
elif command -v apt-get >/dev/null; then
    SUDO=""
    if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
    $SUDO apt-get install -y --no-install-recommends chromium chromium-driver \
        || { $SUDO apt-get update && $SUDO apt-get install -y --no-install-recommends chromium chromium-driver; } \
        || echo "could not install chromium (the browser test will be skipped)"
else
    echo "no apt-get: install chromium and chromedriver yourself for the browser test"
fi
