"""``patches/`` installs as ``raytun3r_plugin.patches`` (never a global ``patches``), in a wheel
and in the editable install, and the shipped network's files are package data."""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parent.parent


def test_editable_install_maps_patches_into_the_package():
    module = importlib.import_module("raytun3r_plugin.patches.da3")
    assert Path(module.__file__).resolve() == (ROOT / "patches" / "da3.py").resolve()
    assert importlib.util.find_spec("patches") is None or "raytun3r" not in str(
        importlib.util.find_spec("patches").origin
    )


# What a build of the tree leaves or needs none of: the wheel is built from a copy, so the build's
# own build/ and egg-info land in tmp_path, not in the working tree.
_NOT_SOURCE = shutil.ignore_patterns(
    ".git", "build", "dist", "*.egg-info", "__pycache__", ".*_cache", "runs", "outputs", "site"
)


def test_wheel_contains_patches_under_the_package(tmp_path):
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=_NOT_SOURCE)
    out = tmp_path / "wheel"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(source),
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    wheel = next(out.glob("raytun3r-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in ("da3", "da3_networks", "vggt", "pi3", "da3_default", "__init__"):
        assert f"raytun3r_plugin/patches/{module}.py" in names
    assert not any(name.startswith("patches/") for name in names)
    assert "raytun3r_plugin/data/raytun3r-da3-tiny.safetensors" in names
    assert not any(name.startswith("tests/") for name in names)


_FOREIGN_PATCHES = """
import importlib.abc, importlib.util, sys

class OtherClone(importlib.abc.MetaPathFinder):
    # What an editable install of another clone does: map the patches package to its folder.
    def find_spec(self, name, path=None, target=None):
        if name == "raytun3r_plugin.patches":
            return importlib.util.spec_from_file_location(name, {init!r}, submodule_search_locations=[{folder!r}])
        return None

sys.meta_path.insert(0, OtherClone())
sys.path.insert(0, {root!r})
{statement}
"""


def _run_with_foreign_patches(tmp_path, statement: str) -> subprocess.CompletedProcess:
    folder = tmp_path / "other-clone" / "patches"
    folder.mkdir(parents=True)
    (folder / "__init__.py").write_text("FOREIGN = True\n")
    script = _FOREIGN_PATCHES.format(
        init=str(folder / "__init__.py"), folder=str(folder), root=str(ROOT), statement=statement
    )
    return subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )


def test_patches_from_another_tree_fail_loudly_at_import(tmp_path):
    for statement in ("import raytun3r_plugin", "import raytun3r_plugin.patches"):
        result = _run_with_foreign_patches(tmp_path / statement.split()[-1], statement)
        assert result.returncode != 0, statement
        assert "SplitInstallError" in result.stderr, result.stderr
        assert str(ROOT / "raytun3r_plugin") in result.stderr  # both trees are named
        assert "other-clone" in result.stderr and "pip install -e ." in result.stderr


def test_layout_rule_accepts_the_source_tree_and_the_wheel(tmp_path):
    from raytun3r_plugin._layout import same_tree

    assert same_tree(
        tmp_path / "clone" / "raytun3r_plugin", tmp_path / "clone" / "patches"
    )  # source / editable
    assert same_tree(
        tmp_path / "site" / "raytun3r_plugin", tmp_path / "site" / "raytun3r_plugin" / "patches"
    )  # wheel
    assert not same_tree(tmp_path / "clone" / "raytun3r_plugin", tmp_path / "other" / "patches")
