"""Aggregation of the synthetic fisheye benchmark: per-sequence rows -> per-cell means and the target."""

from __future__ import annotations

import json
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
from tests.helpers import load_script


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


def test_cell_sequences_name_the_cells_and_seeds_of_the_benchmark():
    from raytun3r_plugin.apps.benchmark import DEVELOPMENT_SEED, cell_sequences

    everything = list(cell_sequences(None, SEQUENCES_PER_CELL))
    assert [seed for _, _, seed in everything] == [
        sequence_seed(c, s, k)
        for c in range(len(CAMERAS))
        for s in range(len(SCENES))
        for k in range(SEQUENCES_PER_CELL)
    ]
    chosen = list(cell_sequences(["DS 195 outdoor", "KB4 185 indoor"], 2, DEVELOPMENT_SEED))
    assert [(spec.label, scene, seed) for spec, scene, seed in chosen] == [
        ("KB4 185", "indoor", sequence_seed(1, 0, 0, DEVELOPMENT_SEED)),
        ("KB4 185", "indoor", sequence_seed(1, 0, 1, DEVELOPMENT_SEED)),
        ("DS 195", "outdoor", sequence_seed(2, 1, 0, DEVELOPMENT_SEED)),
        ("DS 195", "outdoor", sequence_seed(2, 1, 1, DEVELOPMENT_SEED)),
    ]
    # From the k-th sequence on: the seeds a run with more sequences gives those sequences.
    later = list(cell_sequences(["KB4 185 indoor"], 2, DEVELOPMENT_SEED, first=3))
    assert [seed for _, _, seed in later] == [
        sequence_seed(1, 0, k, DEVELOPMENT_SEED) for k in (3, 4)
    ]


def test_a_partial_run_scores_the_full_runs_sequences(monkeypatch, tmp_path):
    from raytun3r_plugin.apps import benchmark

    seeds = []

    class Stop(Exception):
        pass

    def record(model, camera, label, scene, seed, **kwargs):
        seeds.append((label, scene, seed))
        if len(seeds) == 2:
            raise Stop
        return []

    monkeypatch.setattr(benchmark, "sequence_rows", record)
    with pytest.raises(Stop):
        benchmark.run_benchmark(
            None, tmp_path, cameras=(CAMERAS[2],), scenes=("outdoor",), sequences=2
        )
    # DS 195 (camera 2), outdoor (scene 1): the seeds of that cell in the full benchmark.
    assert seeds == [
        ("DS 195", "outdoor", sequence_seed(2, 1, 0)),
        ("DS 195", "outdoor", sequence_seed(2, 1, 1)),
    ]


def test_run_benchmark_passes_the_recipe_and_its_changes_to_every_sequences_fit(
    monkeypatch, tmp_path
):
    """``fisheye_synthetic.py --recipe NAME --teacher-views ...``: the recipe and the changes
    reach each sequence's fit settings, and a run without them fits the library's default
    recipe: three teacher views, the sides at 0.3."""
    from raytun3r_plugin.apps import benchmark

    seen = []

    class Stop(Exception):
        pass

    def record(model, camera, label, scene, seed, **kwargs):
        seen.append((kwargs["recipe"], kwargs["fit_changes"]))
        raise Stop

    monkeypatch.setattr(benchmark, "sequence_rows", record)
    centre = {"teacher_views": ("centre",), "weights": {"pose": 1.0}}
    for recipe, changes in (("default", None), ("targets", centre)):
        with pytest.raises(Stop):
            benchmark.run_benchmark(
                None,
                tmp_path,
                cameras=(CAMERAS[1],),
                scenes=("outdoor",),
                recipe=recipe,
                fit_changes=changes,
            )
    assert seen == [("default", None), ("targets", centre)]
    # What sequence_rows builds from them (its adapt_config call).
    shipped = benchmark.adapt_config(112, 1, recipe="default")
    assert shipped.teacher_views == ("centre", "left", "right")
    assert shipped.teacher_view_weights == {"centre": 1.0, "left": 0.3, "right": 0.3}
    changed = benchmark.adapt_config(112, 1, recipe="targets", **centre)
    assert changed.pose_source == "targets" and changed.teacher_views == ("centre",)
    assert changed.recipe_record()["changes"] == {"steps": [300, 1], "input_size": [None, 112]}


def test_benchmark_script_turns_its_options_into_the_recipes_changes():
    """``--lr``, ``--teacher-weight`` and ``--pose-windows`` become ``AdaptConfig`` changes that
    the fit records against its recipe; options left out change nothing."""
    import argparse

    from raytun3r_plugin.apps import benchmark

    script = load_script("fisheye_synthetic", "benchmarks")
    unset = dict.fromkeys(
        (
            *("pose_weight", "teacher_weight", "pose_source", "pose_windows", "lr"),
            *("lr_without_teacher", "teacher_views"),
        ),
    )
    options = argparse.Namespace(**unset, teacher_view_weights=None)
    assert script.fit_changes(options) == {}
    options.lr, options.teacher_weight, options.pose_windows = 0.01, 5.0, "unreprojected"
    changes = script.fit_changes(options)
    assert changes == {"lr": 0.01, "weights": {"teacher": 5.0}, "pose_windows": "unreprojected"}
    record = benchmark.adapt_config(112, 1, recipe="default", **changes).recipe_record()
    assert record["changes"]["lr"] == [3e-3, 0.01]
    # "all" is left out of the fit's identity, so the recipe side of the record is empty.
    assert record["changes"]["pose_windows"] == [None, "unreprojected"]


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


def test_unknown_baseline_is_refused_and_order_is_fixed():
    from raytun3r_plugin.apps.benchmark import check_baselines
    from raytun3r_plugin.errors import InputError

    assert check_baselines(["caltok", "lora", "lora"]) == ("lora", "caltok")
    with pytest.raises(InputError, match="unknown baseline"):
        check_baselines(["lora", "adapter"])


def test_params_summary_stays_an_integer():
    rows = [
        {**row("KB4 120", "indoor", "raytun3r", seed, 1.0, 0.2), "params": 3604} for seed in (1, 2)
    ]
    assert summarise(rows)[0]["params"] == 3604


#: The tiny benchmark: one cell (DS 195 indoor), 6 + 4 frames at 84 px, 3 steps.
TINY_BENCH = {
    "size": 84,
    "n_adapt": 6,
    "n_eval": 4,
    "steps": 3,
    "sequences": 1,
    "cameras": CAMERAS[-1:],
    "scenes": ("indoor",),
}


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory):
    """The tiny benchmark (1 sequence, 6 + 4 frames, 3 steps) with and without the baselines."""
    pytest.importorskip("depth_anything_3")
    import torch

    from raytun3r_plugin.apps.benchmark import run_benchmark
    from raytun3r_plugin.apps.demo import default_network

    torch.manual_seed(0)
    model, _ = default_network()
    settings = TINY_BENCH
    results, tables = {}, {}
    for key, baselines in (("plain", ()), ("baselines", ("caltok", "lora"))):
        out = tmp_path_factory.mktemp(key)
        tables[key] = run_benchmark(model, out, baselines=baselines, **settings)
        results[key] = json.loads((out / "results.json").read_text()), out
    return model, results, tables


def test_bench_rows_have_params_and_time_relative_to_vanilla(tiny_bench):
    from raytun3r_plugin.adapter import Adapter
    from raytun3r_plugin.baselines import CalibrationTokens, LoraWeights

    model, results, _ = tiny_bench
    data, out = results["baselines"]
    rows = {r["method"]: r for r in data["sequences"]}
    assert list(rows) == [
        "vanilla",
        "center-ph",
        "multi-ph",
        "raytun3r, no adapter",
        "raytun3r",
        "raytun3r, supervised",
        "lora",
        "calibration tokens",
    ]
    assert rows["vanilla"]["x_vanilla"] == 1.0
    for r in rows.values():
        assert r["ms_per_frame"] > 0
        assert r["x_vanilla"] == pytest.approx(r["ms_per_frame"] / rows["vanilla"]["ms_per_frame"])
    for name in ("vanilla", "center-ph", "multi-ph", "raytun3r, no adapter"):
        assert rows[name]["params"] == 0
    # Multi-PH runs five images per frame: never as cheap as vanilla's one.
    assert rows["multi-ph"]["x_vanilla"] > 1.5
    stem = out / f"DS_195_indoor_{sequence_seed(2, 0, 0)}"  # its seed in the full benchmark
    adapter = Adapter.load(f"{stem}.safetensors")
    assert rows["raytun3r"]["params"] == adapter.num_parameters()["total"] > 0
    supervised = Adapter.load(f"{stem}_supervised.safetensors")
    assert rows["raytun3r, supervised"]["params"] == supervised.num_parameters()["total"]
    lora = LoraWeights.load(f"{stem}_lora")
    assert rows["lora"]["params"] == sum(p.numel() for p in lora.parameters()) > 0
    tokens = CalibrationTokens.load(f"{stem}_caltok.safetensors")
    assert rows["calibration tokens"]["params"] == tokens.tokens.numel() > 0
    # The fits changed what they tune (3 steps are enough to move it off the start).
    assert float(lora.lora_B[0].detach().abs().max()) > 0
    assert rows["lora"]["adapt_s"] > 0 and rows["calibration tokens"]["adapt_s"] > 0
    # The baselines were removed after scoring: the model is unhooked again.
    from raytun3r_plugin.baselines import inject_calibration_tokens, inject_lora

    inject_lora(model).remove()
    inject_calibration_tokens(model).remove()


def test_the_text_a_document_gets_is_the_results_file_with_its_rotation_table(tiny_bench):
    _, results, tables = tiny_bench
    _, out = results["plain"]
    assert (out / "results.md").read_text() == tables["plain"] + "\n"
    assert "Rotation error (deg) of the network's own pose" in tables["plain"]


def test_baselines_are_off_by_default_and_change_neither_targets_nor_gap(tiny_bench):
    _, results, tables = tiny_bench
    plain, with_baselines = results["plain"][0], results["baselines"][0]
    assert {r["method"] for r in plain["sequences"]}.isdisjoint({"lora", "calibration tokens"})
    assert "| multi-ph |" in tables["plain"] and "| lora |" not in tables["plain"]
    assert "| lora |" in tables["baselines"] and "| calibration tokens |" in tables["baselines"]
    assert plain["target_met_cells"] == with_baselines["target_met_cells"]
    assert (
        plain["target_met_cells_vs_zero_adapter"]
        == with_baselines["target_met_cells_vs_zero_adapter"]
    )
    shared = {r["method"]: r for r in plain["summary"]}
    for r in with_baselines["summary"]:
        if r["method"] in shared:
            assert ("gap_closed" in r) == ("gap_closed" in shared[r["method"]])
            for key in (
                "d_reproj_px",
                "abs_rel",
                "params",
                *(["gap_closed"] * ("gap_closed" in r)),
            ):
                assert r[key] == pytest.approx(shared[r["method"]][key], nan_ok=True)
        else:
            assert "gap_closed" not in r
    # The header's target lines are the same text.
    assert (
        tables["plain"].split("Target", 1)[1].split("\n")[0]
        == (tables["baselines"].split("Target", 1)[1].split("\n")[0])
    )


def test_rotation_effect_compares_the_fit_with_vanilla_and_center_ph_per_sequence(tiny_bench):
    from raytun3r_plugin.apps.benchmark import ZERO_ADAPTER, rotation_effect

    rows = [
        {"camera": "C", "scene": "indoor", "seed": seed, "method": method, "rot_deg": value}
        for seed, values in ((1, (4.0, 3.0, 5.0, 1.0, 6.0)), (2, (2.0, 1.0, 2.0, 3.0, 2.0)))
        for method, value in zip(
            ("vanilla", "center-ph", ZERO_ADAPTER, "raytun3r", "raytun3r, supervised"),
            values,
            strict=True,
        )
    ]
    (row,) = rotation_effect(rows)
    assert row["rot_vanilla"] == 3.0 and row["rot_adapted"] == 2.0
    assert row["vanilla_over_adapted"] == 1.5
    assert row["adapted_below_vanilla"] == "1/2" and row["adapted_below_center_ph"] == "1/2"
    assert row["adapted_below_no_adapter"] == "1/2"
    # The benchmark writes the same table from its own rows.
    _, results, _ = tiny_bench
    data, out = results["plain"]
    assert data["rotation"] == rotation_effect(data["sequences"])
    assert "rotation_effect" in (out / "results.md").read_text()


def test_bench_in_worker_processes_scores_the_same_sequences_in_order(tmp_path):
    """``run_benchmark(jobs=2)``: the model sent to two one-thread Ray workers, rows put back in
    task order; against the in-process run the rows before any fit differ only by the order of
    float sums, and the header says the timings are one thread's."""
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.apps.benchmark import run_benchmark
    from raytun3r_plugin.apps.demo import default_network
    from raytun3r_plugin.errors import InputError

    model, _ = default_network()
    settings = {**TINY_BENCH, "steps": 2, "sequences": 2}
    with pytest.raises(InputError, match="jobs must be at least 1, got 0"):
        run_benchmark(model, tmp_path / "none", jobs=0, **settings)
    assert not (tmp_path / "none").exists()
    tables, rows = {}, {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        tables[jobs] = run_benchmark(model, out, jobs=jobs, **settings)
        rows[jobs] = json.loads((out / "results.json").read_text())["sequences"]
    assert "2 Ray workers of one thread each" in tables[2]
    assert "Ray workers" not in tables[1]
    keys = [(r["seed"], r["method"]) for r in rows[1]]
    assert keys == [(r["seed"], r["method"]) for r in rows[2]]
    seeds = [sequence_seed(2, 0, k) for k in (0, 1)]
    assert [seed for seed, _ in keys] == [seeds[0]] * 6 + [seeds[1]] * 6
    for a, b in zip(rows[1], rows[2], strict=True):
        if a["method"] in ("vanilla", "center-ph", "multi-ph", "raytun3r, no adapter"):
            for metric in ("abs_rel", "d_reproj_px"):
                assert a[metric] == pytest.approx(b[metric], rel=1e-3, abs=1e-4), (a, metric)
    zero = [r["abs_rel"] for r in rows[1] if r["method"] == "raytun3r, no adapter"]
    assert abs(zero[0] - zero[1]) > 1e-3  # the comparison can tell the two sequences apart
    for jobs in (1, 2):  # each worker wrote its sequences' adapters
        for seed in seeds:
            assert (tmp_path / f"jobs{jobs}" / f"DS_195_indoor_{seed}.safetensors").is_file()
