#!/usr/bin/env bash
# Installs raytun3r and everything it needs on a fresh machine (CPU only, no model hub).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
# torch first and pinned: an unpinned torch would pull a multi-GB CUDA build; 2.13.0 is the CPU
# build this machine keeps on disk.
"$PY" -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[da3,test,cluster,deploy]"
# Depth Anything 3 declares heavy dependencies and pins numpy<2; its code needs only what the
# [da3] extra installed above, so it goes in without its declared dependencies.
"$PY" -m pip install --quiet --disable-pip-version-check --no-deps "depth-anything-3==0.1.1"
# Headless Chromium renders `raytun3r report` pages in tests/test_report.py (the test skips without
# it). Debian's package is `chromium`; installed here where it is missing and apt-get can run.
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1 \
    && ! command -v google-chrome >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo -n"; fi
    if command -v apt-get >/dev/null 2>&1 && { [ "$(id -u)" = "0" ] || [ -n "$SUDO" ]; }; then
        $SUDO apt-get install -y -qq chromium >/dev/null 2>&1 \
            || { $SUDO apt-get update -qq >/dev/null && $SUDO apt-get install -y -qq chromium >/dev/null; } \
            || echo "install.sh: could not install chromium; tests/test_report.py will skip" >&2
    else
        echo "install.sh: no chromium and no apt-get to install it; tests/test_report.py will skip" >&2
    fi
fi
# The fleet tests list the sockets Ray listens on with `ss` (iproute2; tests/test_fleet.py skips
# that check without it).
if ! command -v ss >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo -n"; fi
    $SUDO apt-get install -y -qq iproute2 >/dev/null 2>&1 \
        || { $SUDO apt-get update -qq >/dev/null 2>&1 && $SUDO apt-get install -y -qq iproute2 >/dev/null 2>&1; } \
        || echo "install.sh: could not install iproute2 (ss); tests/test_fleet.py skips its socket check" >&2
fi
"$PY" -c "import raytun3r_plugin, raytun3r_plugin.patches, depth_anything_3.model.da3; print('raytun3r', raytun3r_plugin.__version__, 'installed')"
