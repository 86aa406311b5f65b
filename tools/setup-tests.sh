#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine:
#   - the project with its test extras (pytest, selenium), editable;
#   - Debian's chromium + chromium-driver for the viewer's browser test, ffmpeg for the
#     ns-render video verbs, and libusb-1.0-0 (open3d, which ns-export imports, loads
#     libusb-1.0.so.0) (apt; sudo when not root).
# Without apt (another OS) the browser test is skipped and says why; everything else runs.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -e ".[test]"
if command -v chromium >/dev/null && command -v chromedriver >/dev/null && command -v ffmpeg >/dev/null \
        && { ldconfig -p 2>/dev/null | grep "libusb-1.0.so.0" >/dev/null; }; then
    echo "chromium, chromedriver, ffmpeg and libusb present"
elif command -v apt-get >/dev/null; then
    SUDO=""
    if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
    $SUDO apt-get install -y --no-install-recommends chromium chromium-driver ffmpeg libusb-1.0-0 \
        || { $SUDO apt-get update && $SUDO apt-get install -y --no-install-recommends chromium chromium-driver ffmpeg libusb-1.0-0; } \
        || echo "could not install chromium/ffmpeg/libusb (the browser test, the ns-render video tests and ns-export may fail or be skipped)"
else
    echo "no apt-get: install chromium and chromedriver yourself for the browser test"
fi
