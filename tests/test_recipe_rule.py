"""``experiments/recipe_rule.py``: the verdicts of the recipe rules are computed, not typed, so
the arithmetic that decides them is checked here on rows whose answers are known."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rule():
    return load_script("recipe_rule", "experiments")


def _row(method, camera, scene, seed, abs_rel, rot=1.0, d_reproj=1.0):
    return {
        "method": method,
        "camera": camera,
        "scene": scene,
        "seed": seed,
        "abs_rel": abs_rel,
        "rot_deg": rot,
        "d_reproj_px": d_reproj,
        "adapt_s": 1.0,
    }


def _run(tmp_path, name, fitted):
    """Two wide-lens sequences, zero adapter 0.20 and supervised 0.10 on each."""
    rows = []
    for seed, value in zip((1, 2), fitted, strict=True):
        for method, abs_rel in (
            ("vanilla", 0.3),
            ("raytun3r, no adapter", 0.2),
            ("raytun3r, supervised", 0.1),
            ("raytun3r", value),
        ):
            rows.append(_row(method, "KB4 185", "indoor", seed, abs_rel, rot=2.0 + value))
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"sequences": rows}))
    return str(path)


def test_gap_and_worse_sequences_are_counted_against_this_runs_zero_adapter(rule, tmp_path):
    new = _run(tmp_path, "new", (0.15, 0.15))  # half the gap on each
    old = _run(tmp_path, "old", (0.19, 0.21))  # 0.05 of it pooled; seed 2 is 5 % worse
    table = rule.by_sequence([new])
    lines = rule.report(table)
    assert lines[0].startswith("(a) pooled wide-lens gap closed: 0.500 over 2")
    compared = rule.compare(table, rule.reference_rows([old], "raytun3r"))
    assert "reference: pooled wide-lens AbsRel 0.2000, gap closed 0.000" in compared
    assert "this run: pooled wide-lens AbsRel 0.1500, gap closed 0.500" in compared
    assert any(
        line.startswith("reference: 1 sequences worse") and "2)" in line for line in compared
    )
    assert any(line.startswith("this run: 0 sequences worse") for line in compared)
    assert any("AbsRel reference 0.2000 this run 0.1500 (-25.0 %)" in line for line in compared)


def test_the_wide_lenses_are_every_benchmark_lens_of_185_degrees_and_wider(rule):
    """The new lens models count as wide (a new-lens run gets (a) and (b)); KB4 120 does not."""
    assert set(rule.WIDE) == {"KB4 185", "DS 195", "UCM 200", "EUCM 210"}
    rows = []
    for method, abs_rel in (
        ("vanilla", 0.3),
        ("raytun3r, no adapter", 0.2),
        ("raytun3r, supervised", 0.1),
        ("raytun3r", 0.15),
    ):
        rows.append(_row(method, "UCM 200", "outdoor", 1, abs_rel))
        rows.append(_row(method, "KB4 120", "indoor", 2, abs_rel + 0.1))
    table = {(r["camera"], r["scene"], r["seed"]): {} for r in rows}
    for r in rows:
        table[(r["camera"], r["scene"], r["seed"])][r["method"]] = r
    assert rule.report(table)[0] == "(a) pooled wide-lens gap closed: 0.500 over 1"


def test_reference_rows_read_the_resample_scripts_rows(rule, tmp_path):
    path = tmp_path / "rows.json"
    rows = [
        {
            "camera": "DS 195",
            "scene": "outdoor",
            "seed": 7,
            "default recipe, central": {"abs_rel": 0.2, "rot_deg": 1.0, "d_reproj_px": 1.0},
        }
    ]
    path.write_text(json.dumps(rows))
    read = rule.reference_rows([str(path)], "default recipe, central")
    assert read == {("DS 195", "outdoor", 7): rows[0]["default recipe, central"]}
