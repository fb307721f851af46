"""The front door and the reference pages stay true: the README is short and points at files that
exist, and the command-line reference is the parser's own text."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import load_script

ROOT = Path(__file__).parent.parent


def test_the_command_line_reference_is_the_parsers_text():
    reference = load_script("cli_reference").reference()
    assert (ROOT / "docs" / "cli.md").read_text() == reference, (
        "docs/cli.md is stale: run `python scripts/cli_reference.py`"
    )
    assert "## raytun3r adapt" in reference and "--recipe NAME" in reference


def test_the_readme_is_a_short_front_door_that_points_at_real_files():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    # No issue numbers, test counts or one day's timings: those belong in the docs.
    assert not re.search(r"\bissues? \d+", text, re.I)
    assert not re.search(r"\d+ tests\b|\d+ passed", text)
    assert "today's machine" not in text
    for section in ("## Install", "## Set-up", "## Citation", "## Licence"):
        assert section in text
    assert "./scripts/install.sh && python3 -m pytest -q" in text  # what .ci/run calls
    named = set(re.findall(r"(docs/[\w./-]+\.(?:md|png))", text))
    assert "docs/results.md" in named and "docs/images/depth_before_after.png" in named
    missing = sorted(path for path in named if not (ROOT / path).is_file())
    assert not missing, f"README names files that do not exist: {missing}"


def test_the_results_page_holds_the_benchmarks_table_markers():
    text = (ROOT / "docs" / "results.md").read_text()
    start, end = text.index("<!-- bench:start -->"), text.index("<!-- bench:end -->")
    assert start < end and "| camera | scene | method |" in text[start:end]


def _build(config: Path, site: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def test_the_docs_site_builds_strictly_and_a_broken_link_fails_it(tmp_path):
    pytest.importorskip(
        "mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')"
    )
    built = _build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert built.returncode == 0, built.stdout + built.stderr
    for page in ("index.html", "cli/index.html", "api/index.html", "recipes/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "from_recipe" in api and "held_out_reprojection" in api  # from the docstrings
    # The same site with one broken link: strict mode refuses it.
    copy = tmp_path / "copy"
    shutil.copytree(ROOT / "docs", copy / "docs")
    shutil.copy(ROOT / "mkdocs.yml", copy / "mkdocs.yml")
    index = copy / "docs" / "index.md"
    index.write_text(index.read_text() + "\nSee [the missing page](missing.md).\n")
    broken = _build(copy / "mkdocs.yml", tmp_path / "broken")
    assert broken.returncode != 0 and "missing.md" in broken.stdout + broken.stderr
