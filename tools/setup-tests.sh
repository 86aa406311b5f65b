#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine:
#   - the project with its test extras (pytest, selenium), editable;
#   - Debian's chromium + chromium-driver for the viewer's browser test, and ffmpeg for the
#     ns-render video verbs (apt; sudo when not root).
# Without apt (another OS) the browser test is skipped and says why; everything else runs.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -e ".[test]"
if command -v chromium >/dev/null && command -v chromedriver >/dev/null && command -v ffmpeg >/dev/null; then
    echo "chromium, chromedriver and ffmpeg present"
elif command -v apt-get >/dev/null; then
    SUDO=""
    if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
    $SUDO apt-get install -y --no-install-recommends chromium chromium-driver ffmpeg \
        || { $SUDO apt-get update && $SUDO apt-get install -y --no-install-recommends chromium chromium-driver ffmpeg; } \
        || echo "could not install chromium/ffmpeg (the browser test and the ns-render video tests will be skipped)"
else
    echo "no apt-get: install chromium and chromedriver yourself for the browser test"
fi
