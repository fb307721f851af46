"""Aggregation of the synthetic fisheye benchmark: per-sequence rows -> per-cell means and the target."""

from __future__ import annotations

import math

import pytest

from raytun3r_plugin.apps.benchmark import (
    CAMERAS,
    HELD_OUT_SEED,
    SCENES,
    SEQUENCES_PER_CELL,
    sequence_seed,
    summarise,
    targets_met,
)


def row(
    camera: str,
    scene: str,
    method: str,
    seed: int,
    d_reproj: float,
    abs_rel: float,
    adapt_s: float = math.nan,
) -> dict:
    return {
        "camera": camera,
        "scene": scene,
        "method": method,
        "seed": seed,
        "rot_deg": 1.0,
        "trans_deg": 90.0,
        "d_reproj_px": d_reproj,
        "abs_rel": abs_rel,
        "delta_1.25": 0.5,
        "coverage": 1.0,
        "adapt_s": adapt_s,
    }


def test_seeds_are_held_out_distinct_and_keep_the_first_sequences():
    seeds = [
        sequence_seed(c, s, k)
        for c in range(len(CAMERAS))
        for s in range(len(SCENES))
        for k in range(SEQUENCES_PER_CELL)
    ]
    assert len(set(seeds)) == len(seeds) and min(seeds) >= HELD_OUT_SEED
    # k = 0 are the sequences of the one-sequence-per-cell benchmark, so earlier tables stay comparable.
    assert [sequence_seed(c, s, 0) for c in range(3) for s in range(2)] == [
        HELD_OUT_SEED + 10 * c + s for c in range(3) for s in range(2)
    ]


def test_summarise_means_per_cell_and_counts_paired_wins():
    rows = [
        row("KB4 120", "indoor", "vanilla", 1, 1.0, 0.20),
        row("KB4 120", "indoor", "raytun3r", 1, 0.5, 0.10, 30.0),
        row("KB4 120", "indoor", "vanilla", 2, 1.0, 0.20),
        row("KB4 120", "indoor", "raytun3r", 2, 1.2, 0.15, 40.0),
    ]
    summary = {r["method"]: r for r in summarise(rows)}
    ours = summary["raytun3r"]
    assert ours["sequences"] == 2
    assert (
        ours["d_reproj_px"] == pytest.approx(0.85)
        and ours["abs_rel"] == pytest.approx(0.125)
        and ours["adapt_s"] == pytest.approx(35.0)
    )
    assert ours["lower_than_vanilla"] == "d_reproj_px 1/2, abs_rel 2/2"
    assert (
        math.isnan(summary["vanilla"]["adapt_s"]) and "lower_than_vanilla" not in summary["vanilla"]
    )


def test_targets_met_needs_every_metric_lower_in_the_mean():
    rows = [
        row("KB4 120", "indoor", "vanilla", 1, 1.0, 0.20),
        row("KB4 120", "indoor", "raytun3r", 1, 0.9, 0.19),
        row("DS 195", "outdoor", "vanilla", 2, 2.0, 0.20),
        row("DS 195", "outdoor", "raytun3r", 2, 1.5, 0.21),
        # The zero-adapter row beating vanilla does not count for the fitted method.
        row("DS 195", "outdoor", "raytun3r, no adapter", 2, 1.0, 0.10),
    ]
    assert targets_met(summarise(rows)) == ["KB4 120 indoor"]
