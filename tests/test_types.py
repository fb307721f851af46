"""The typed leaves of the core pass mypy (configuration: ``[tool.mypy]`` in pyproject.toml).

Gradual typing: the list grows as modules get complete annotations; a module on it may not
regress. Neighbours outside the list are followed silently, so only these files are judged.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent

CHECKED = [
    "raytun3r_plugin/errors.py",
    "raytun3r_plugin/atomic_files.py",
    "raytun3r_plugin/poses.py",
    "raytun3r_plugin/preprocess.py",
    "raytun3r_plugin/registry.py",
    "raytun3r_plugin/patching.py",
    "raytun3r_plugin/patch_wrapper.py",
    "raytun3r_plugin/patch_state.py",
    "raytun3r_plugin/patch_checks.py",
    "raytun3r_plugin/hooks.py",
    "raytun3r_plugin/adapter.py",
    "raytun3r_plugin/geometry.py",
    "raytun3r_plugin/size_geometry.py",
    "raytun3r_plugin/cameras/",
    "raytun3r_plugin/datasets/rig.py",
    "raytun3r_plugin/adaptation/rig.py",
    "raytun3r_plugin/adaptation/rig_step.py",
    "raytun3r_plugin/adaptation/loop.py",
    "raytun3r_plugin/adaptation/guard.py",
    "raytun3r_plugin/adaptation/checkpoint.py",
    "raytun3r_plugin/adaptation/intrinsics.py",
    "raytun3r_plugin/adaptation/intrinsics_solver.py",
    "raytun3r_plugin/adaptation/matches.py",
    "raytun3r_plugin/adaptation/train.py",
    "raytun3r_plugin/adaptation/recipes.py",
    "raytun3r_plugin/adaptation/evaluation.py",
    "raytun3r_plugin/adaptation/target_scale.py",
    "raytun3r_plugin/adaptation/parallax.py",
    "raytun3r_plugin/adaptation/pose_gate.py",
    "raytun3r_plugin/adaptation/config.py",
    "raytun3r_plugin/adaptation/settings_check.py",
    "raytun3r_plugin/adaptation/step.py",
    "raytun3r_plugin/adaptation/windows.py",
    "raytun3r_plugin/apps/adapter_report.py",
    "raytun3r_plugin/adaptation/check.py",
    "raytun3r_plugin/pinhole_views.py",
    "raytun3r_plugin/exports/",
    "raytun3r_plugin/apps/cli_exports.py",
    "raytun3r_plugin/apps/fits.py",
    "raytun3r_plugin/apps/workers.py",
    "raytun3r_plugin/apps/demo.py",
    "raytun3r_plugin/apps/benchmark.py",
    "raytun3r_plugin/apps/benchmark_text.py",
    "raytun3r_plugin/figures.py",
    "raytun3r_plugin/datasets/fiord.py",
    "raytun3r_plugin/apps/browser.py",
    "raytun3r_plugin/apps/report.py",
    "raytun3r_plugin/apps/sequence_methods.py",
    "raytun3r_plugin/cluster.py",
    "raytun3r_plugin/threads.py",
    "raytun3r_plugin/apps/fleet.py",
    "raytun3r_plugin/apps/fleet_manifest.py",
    "raytun3r_plugin/apps/cli_fleet.py",
]


def _mypy(paths: list[str], cwd: Path) -> subprocess.CompletedProcess:
    # --no-incremental: no .mypy_cache left in the tree, and no stale cache hiding an error.
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "--no-incremental",
            "--config-file",
            str(ROOT / "pyproject.toml"),
            *paths,
        ],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )


@pytest.mark.skipif(
    importlib.util.find_spec("mypy") is None,
    reason="mypy is not installed (pip install -e '.[test]')",
)
def test_typed_core_modules_pass_mypy():
    result = _mypy(CHECKED, ROOT)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-1000:]


@pytest.mark.skipif(
    importlib.util.find_spec("mypy") is None,
    reason="mypy is not installed (pip install -e '.[test]')",
)
def test_mypy_reports_a_type_error(tmp_path):
    """The run above can fail: the same command and configuration reject a wrong annotation."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f(x: int) -> str:\n    return x\n")
    result = _mypy([str(bad)], tmp_path)
    assert result.returncode == 1 and "bad.py:2: error" in result.stdout, result.stdout
