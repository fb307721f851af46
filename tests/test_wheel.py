"""The wheel installs anywhere: built from this tree, installed into a fresh virtual environment
away from the repository, it imports and runs a short demo on its packaged network (slow set:
it installs torch into the new environment)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent


def _run(command: list[str], cwd: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{command}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.mark.slow
def test_the_wheel_installs_in_a_fresh_environment_and_runs_the_demo(tmp_path):
    pytest.importorskip("build", reason="pip install build twine")
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "build", "--outdir", str(dist), str(ROOT)], tmp_path)
    wheel = next(dist.glob("raytun3r-*.whl"))
    assert next(dist.glob("raytun3r-*.tar.gz"))
    twine = _run([sys.executable, "-m", "twine", "check", *map(str, dist.iterdir())], tmp_path)
    assert "PASSED" in twine.stdout and "FAILED" not in twine.stdout
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], tmp_path)
    python = venv / "bin" / "python"
    pip = [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    _run([*pip, "torch==2.13.0"], tmp_path)
    _run([*pip, f"{wheel}[da3]"], tmp_path)
    _run([*pip, "--no-deps", "depth-anything-3==0.1.1"], tmp_path)
    away = tmp_path / "elsewhere"
    away.mkdir()
    where = _run(
        [
            str(python),
            "-c",
            "import raytun3r_plugin, raytun3r_plugin.patches; "
            "print(raytun3r_plugin.__file__); print(raytun3r_plugin.patches.__file__)",
        ],
        away,
    ).stdout.split()
    assert all(str(venv) in path and str(ROOT) not in path for path in where), where
    demo = _run(
        [
            str(venv / "bin" / "raytun3r"),
            "demo",
            *("--out", str(away / "demo"), "--steps", "2", "--size", "56"),
            *("--sequences", "1", "--jobs", "1"),
        ],
        away,
    )
    assert "raytun3r-da3-tiny-v3" in demo.stdout and "RANDOM-WEIGHT" not in demo.stdout
    assert "raytun3r, adapted" in demo.stdout
