"""``raytun3r bench`` and ``raytun3r demo`` end to end."""

from __future__ import annotations

import json

import pytest

from raytun3r_plugin.apps.cli import main

pytest.importorskip("depth_anything_3")


def test_bench_quick(tmp_path, capsys, monkeypatch):
    from depth_anything_3.utils.logger import logger

    monkeypatch.delenv("DA3_LOG_LEVEL", raising=False)
    monkeypatch.setattr(logger, "level", 2)  # DA3's INFO
    assert main(["bench", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    # Adaptation windows are 3-view forwards, on which DA3 logs at INFO: the CLI shows warnings only
    # and gives library callers their level back.
    assert "[INFO" not in out and logger.level == 2
    for method in ("vanilla", "center-ph", "raytun3r, no adapter", "raytun3r"):
        assert f"| {method} |" in out
    assert (
        "lower_than_vanilla" in out
        and "Target (raytun3r's mean d_reproj and AbsRel below vanilla's): met in" in out
    )
    assert (tmp_path / "results.md").is_file()
    results = json.loads((tmp_path / "results.json").read_text())
    assert {r["method"] for r in results["sequences"]} == {
        "vanilla",
        "center-ph",
        "multi-ph",
        "raytun3r, no adapter",
        "raytun3r",
        "raytun3r, supervised",
    }
    assert "gap_closed" in out and "Target (below 'raytun3r, no adapter' on both)" in out
    assert all(r["sequences"] == 1 for r in results["summary"])
    # Multi-PH is scored on every sequence; the baselines only on request.
    assert "| multi-ph |" in out and "| lora |" not in out
    assert "| params | ms_per_frame | x_vanilla |" in out


def test_bench_quick_with_baselines(tmp_path, capsys):
    assert main(["bench", "--quick", "--baselines", "lora,caltok", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| lora |" in out and "| calibration tokens |" in out
    results = json.loads((tmp_path / "results.json").read_text())
    rows = {r["method"]: r for r in results["sequences"]}
    assert rows["vanilla"]["x_vanilla"] == 1.0 and rows["multi-ph"]["params"] == 0
    assert rows["lora"]["params"] > rows["calibration tokens"]["params"] > 0
    from raytun3r_plugin.apps.benchmark import sequence_seed

    lora = tmp_path / f"DS_195_indoor_{sequence_seed(2, 0, 0)}_lora"  # the cell's own seed
    assert (lora / "adapter_model.safetensors").is_file()


def test_bench_refuses_an_unknown_baseline_before_loading_anything(tmp_path, capsys):
    assert main(["bench", "--quick", "--baselines", "lora,peft", "--out", str(tmp_path)]) == 2
    assert "unknown baseline" in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()


def test_eval_help_lists_every_method(capsys):
    from raytun3r_plugin.apps.evaluation import METHODS

    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for method in METHODS:
        assert method in text.split("--method METHOD")[-1].split("--adapter")[0]


def _demo(out, jobs: int) -> int:
    return main(
        ["demo", "--out", str(out), "--steps", "3", "--size", "84", "--sequences", "2"]
        + ["--jobs", str(jobs)]
    )


def test_demo_runs_on_the_built_in_default(tmp_path, capsys):
    assert _demo(tmp_path, 2) == 0  # two worker processes, whatever this machine's CPU count
    out = capsys.readouterr().out
    assert "jobs:    2 processes, 1 thread each" in out
    assert "raytun3r-da3-tiny-v3" in out and "trained by raytun3r on pinhole renders only" in out
    for label in (
        "vanilla (unpatched)",
        "Center-PH",
        "raytun3r, no adapter",
        "raytun3r, adapted (3 steps",
        "raytun3r, supervised (3 steps",
    ):
        assert label in out
    assert "Mean over 2 held-out sequences" in out and "/2" in out  # per-sequence win counts
    # The demo says what its indoor table leaves out, and what its fits use.
    assert "These are indoor sequences" in out and "pinhole-view teacher alone" in out
    assert "pinhole-view teacher weight 10" in out
    assert "centre + left + right views (weights centre 1, left 0.3, right 0.3)" in out
    for k in (0, 1):
        assert (tmp_path / f"seq{k}" / "adapter.safetensors").is_file() and (
            tmp_path / f"seq{k}" / "adapter.losses.png"
        ).is_file()
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert len(metrics["rows"]) == 2 * 5

    # In this process: the same rows in the same order (sequence by sequence), so the workers
    # neither mixed sequences up nor scored another one. The rows before any fit only differ by
    # the order of float sums (one thread against this process's pool).
    assert _demo(tmp_path / "in_process", 1) == 0
    assert "jobs:    1 process\n" in capsys.readouterr().out
    alone = json.loads((tmp_path / "in_process" / "metrics.json").read_text())["rows"]
    assert [(r["seed"], r["method"]) for r in alone] == [
        (r["seed"], r["method"]) for r in metrics["rows"]
    ]
    assert [r["seed"] for r in alone] == [1000] * 5 + [1001] * 5
    for a, b in zip(alone, metrics["rows"], strict=True):
        if "adapted" not in a["method"] and "supervised" not in a["method"]:
            for metric in ("abs_rel", "d_reproj_px", "rot_deg"):
                assert a[metric] == pytest.approx(b[metric], rel=1e-3, abs=1e-4), (a, metric)
    zero = [r["abs_rel"] for r in alone if r["method"] == "raytun3r, no adapter"]
    assert abs(zero[0] - zero[1]) > 1e-3  # the comparison above can tell the sequences apart


def test_demo_refuses_a_job_count_below_one(tmp_path, capsys):
    assert _demo(tmp_path, 0) == 2
    assert "--jobs must be at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "metrics.json").exists()


def test_demo_jobs_default_to_the_cpus_and_the_sequences():
    import os

    from raytun3r_plugin.apps.workers import cpu_jobs

    assert cpu_jobs(1) == 1 and cpu_jobs(0) == 1
    assert 1 <= cpu_jobs(64) <= (os.cpu_count() or 1)
    assert cpu_jobs(64) == min(64, len(os.sched_getaffinity(0)))
