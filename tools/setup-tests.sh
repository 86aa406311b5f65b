#!/usr/bin/env bash
# Set up everything the test suite needs on a fresh machine:
#   - the project with its test extras (pytest, selenium, ray, pycolmap, ruff), editable;
#   - Debian's chromium + chromium-driver for the viewer's browser test, ffmpeg for the
#     ns-render video verbs, and libusb-1.0-0 (open3d, which ns-export imports, loads
#     libusb-1.0.so.0) (apt; sudo when not root).
# It fails, naming what is missing, when it cannot provide one of them: under CI=true the tests that
# need it would fail too (tests/prerequisites.py), and outside CI they would be skipped unseen.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -e ".[test]"

missing_tools() {
    local missing=()
    command -v chromium >/dev/null || command -v chromium-browser >/dev/null || missing+=(chromium)
    command -v chromedriver >/dev/null || missing+=(chromedriver)
    command -v ffmpeg >/dev/null || missing+=(ffmpeg)
    { ldconfig -p 2>/dev/null | grep "libusb-1.0.so.0" >/dev/null; } || missing+=(libusb-1.0)
    echo "${missing[*]}"
}

missing=$(missing_tools)
if [ -n "$missing" ] && command -v apt-get >/dev/null; then
    SUDO=""
    if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
    packages=(chromium chromium-driver ffmpeg libusb-1.0-0)
    $SUDO apt-get install -y --no-install-recommends "${packages[@]}" \
        || { $SUDO apt-get update && $SUDO apt-get install -y --no-install-recommends "${packages[@]}"; } \
        || true
    missing=$(missing_tools)
fi
if [ -n "$missing" ]; then
    echo "tools/setup-tests.sh: could not install: $missing" >&2
    echo "  the browser test needs chromium and chromedriver, the ns-render video tests ffmpeg, ns-export libusb-1.0;" >&2
    echo "  install them with your system's package manager, then run this again" >&2
    exit 1
fi
echo "chromium, chromedriver, ffmpeg and libusb present"
