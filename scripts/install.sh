#!/usr/bin/env bash
# Installs raytun3r and everything it needs on a fresh machine (CPU only, no model hub).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
# torch first and pinned: an unpinned torch would pull a multi-GB CUDA build; 2.13.0 is the CPU
# build this machine keeps on disk.
"$PY" -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[da3,test,deploy]"
# Depth Anything 3 declares heavy dependencies and pins numpy<2; its code needs only what the
# [da3] extra installed above, so it goes in without its declared dependencies.
"$PY" -m pip install --quiet --disable-pip-version-check --no-deps "depth-anything-3==0.1.1"
"$PY" -c "import raytun3r_plugin, raytun3r_plugin.patches, depth_anything_3.model.da3; print('raytun3r', raytun3r_plugin.__version__, 'installed')"
