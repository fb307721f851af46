"""First contact: ``import raytun3r_plugin as rt`` reaches every subpackage, and stays cheap."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent

_SCRIPT = """
import sys
import raytun3r_plugin as rt
heavy = ("cameras", "datasets", "synthetic", "adaptation", "cli", "evaluation")
assert not any(f"raytun3r_plugin.{name}" in sys.modules for name in heavy), "import raytun3r_plugin must stay cheap"
assert callable(rt.cameras.load) and rt.cameras.KannalaBrandt4
assert callable(rt.datasets.load_sequence)
assert rt.synthetic.__name__ == "raytun3r_plugin.synthetic"
assert callable(rt.adaptation.adapt)
assert rt.metrics.__name__ == "raytun3r_plugin.metrics" and rt.patches.da3
assert "cameras" in dir(rt) and "adaptation" in dir(rt)
try:
    rt.no_such_module
except AttributeError as error:
    assert "no_such_module" in str(error)
else:
    raise SystemExit("rt.no_such_module did not raise")
print("ok")
"""


def test_subpackages_are_attributes_of_the_top_level_package():
    result = subprocess.run(
        [sys.executable, "-c", _SCRIPT], capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"


def test_camera_load_through_the_top_level_name(tmp_path):
    import raytun3r_plugin as rt
    from tests.helpers import fisheye

    path = tmp_path / "cam.json"
    rt.cameras.save(fisheye(), path)
    assert rt.cameras.load(path).model == "kb4"


def test_unknown_attribute_is_an_attribute_error():
    import raytun3r_plugin as rt

    with pytest.raises(AttributeError):
        _ = rt.not_a_subpackage
