"""Every example script runs (tiny settings) and does what it says."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("depth_anything_3")
EXAMPLES = Path(__file__).parent.parent / "examples"


def run(script: str, *args: str) -> str:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_fit_apply_evaluate(tmp_path):
    adapter = tmp_path / "cam.safetensors"
    out = run(
        "fit_adapter.py", "--out", str(adapter), "--size", "84", "--steps", "2", "--n-frames", "6"
    )
    assert adapter.is_file() and "saved" in out
    out = run("apply_shared_adapter.py", "--adapter", str(adapter), "--size", "84")
    assert "model restored: True" in out
    assert "depth (1, 3, 84, 84)" in out
    out = run("evaluate.py", "--adapter", str(adapter), "--frames", "6", "--size", "84")
    assert "| vanilla |" in out and "| center-ph |" in out and "| raytun3r |" in out
