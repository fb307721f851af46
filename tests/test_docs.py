"""The front door and the reference pages stay true: the README is short and points at files that
exist, and the command-line reference is the parser's own text."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).parent.parent


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_command_line_reference_is_the_parsers_text():
    reference = _script("cli_reference").reference()
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
