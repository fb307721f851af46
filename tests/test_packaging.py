"""``patches/`` installs as ``raytun3r_plugin.patches`` (never a global ``patches``), in a wheel
and in the editable install, and the shipped network's files are package data."""

from __future__ import annotations

import importlib
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parent.parent


def test_editable_install_maps_patches_into_the_package():
    module = importlib.import_module("raytun3r_plugin.patches.da3")
    assert Path(module.__file__).resolve() == (ROOT / "patches" / "da3.py").resolve()
    assert importlib.util.find_spec("patches") is None or "raytun3r" not in str(importlib.util.find_spec("patches").origin)


def test_wheel_contains_patches_under_the_package(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path)],
        check=True, capture_output=True, text=True,
    )
    wheel = next(tmp_path.glob("raytun3r-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in ("da3", "vggt", "pi3", "da3_default", "__init__"):
        assert f"raytun3r_plugin/patches/{module}.py" in names
    assert not any(name.startswith("patches/") for name in names)
    assert "raytun3r_plugin/data/raytun3r-da3-tiny.safetensors" in names
    assert not any(name.startswith("tests/") for name in names)
