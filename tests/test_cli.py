"""The ``raytun3r`` command line, end to end on small synthetic data."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from raytun3r_plugin import Adapter, cameras, synthetic
from raytun3r_plugin.apps.cli import main
from raytun3r_plugin.apps.export import read_ply
from tests.helpers import fisheye, randomise_

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3 import build_network  # noqa: E402

SIZE = 84


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A random da3-small weight file, a camera file and a synthetic sequence folder."""
    import cv2
    from safetensors.torch import save_model

    folder = tmp_path_factory.mktemp("cli")
    torch.manual_seed(0)
    net = build_network("da3-small")
    with torch.no_grad():
        net.backbone.pretrained.pos_embed.normal_(0, 0.02)
    weights = folder / "model.safetensors"
    save_model(net, str(weights))
    camera = fisheye(SIZE, SIZE, 190.0)
    cameras.save(camera, folder / "camera.json")
    seq = synthetic.render_sequence("indoor", camera, n_frames=6, seed=5)
    frames = folder / "frames"
    frames.mkdir()
    for k, image in enumerate(seq.images):
        cv2.imwrite(str(frames / f"{k:04d}.png"), (image[..., ::-1] * 255).round().astype(np.uint8))
    synthetic.write_sequence(seq, folder / "sequence")
    depth = folder / "depth"
    depth.mkdir()
    for k, values in enumerate(seq.depth):
        if k % 2:  # half as .npy in depth units, half as 16-bit PNG in millimetres
            cv2.imwrite(str(depth / f"{k:04d}.png"), np.round(values * 1000).astype(np.uint16))
        else:
            np.save(depth / f"{k:04d}.npy", values)
    return {
        "depth": depth,
        "folder": folder,
        "weights": weights,
        "camera": folder / "camera.json",
        "frames": frames,
        "sequence": folder / "sequence",
        "net": net,
    }


def model_args(setup) -> list[str]:
    """``--backbone`` and ``--weights`` of the module's random da3-small file."""
    return ["--backbone", "da3-small", "--weights", str(setup["weights"])]


def frame_args(setup) -> list[str]:
    """``--frames`` and ``--size`` of the module's synthetic frame folder."""
    return ["--frames", str(setup["frames"]), "--size", str(SIZE)]


def test_adapt_inspect_infer(setup, capsys):
    folder = setup["folder"]
    adapter = folder / "adapter.safetensors"
    code = main(
        [
            "adapt",
            *model_args(setup),
            "--camera",
            str(setup["camera"]),
            *frame_args(setup),
            "--steps",
            "2",
            "--windows",
            "2",
            "--out",
            str(adapter),
        ]
    )
    assert code == 0 and adapter.is_file()
    assert main(["inspect", str(adapter)]) == 0
    text = capsys.readouterr().out
    assert "da3-small" in text and "10,772" in text and "KannalaBrandt4" in text

    out = folder / "infer"
    code = main(
        [
            "infer",
            *model_args(setup),
            "--adapter",
            str(adapter),
            *frame_args(setup),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    assert (
        len(list((out / "depth").glob("*.npy"))) == 6
        and len(list((out / "depth").glob("*.png"))) == 6
    )
    depth = np.load(out / "depth" / "0000.npy")
    assert depth.shape == (SIZE, SIZE) and np.isfinite(depth).all()
    lines = [
        line
        for line in (out / "trajectory.txt").read_text().splitlines()
        if not line.startswith("#")
    ]
    assert len(lines) == 6 and all(len(line.split()) == 8 for line in lines)
    points, colours = read_ply(out / "points.ply")
    assert len(points) > 1000 and np.isfinite(points).all() and colours.dtype == np.uint8


def test_pose_weight_reaches_the_saved_config_and_is_refused_with_depth(setup, tmp_path, capsys):
    adapter = tmp_path / "hybrid.safetensors"
    common = [*model_args(setup), "--camera", str(setup["camera"]), *frame_args(setup)]
    code = main(
        [
            "adapt",
            *common,
            *("--steps", "1", "--windows", "2", "--pose-source", "hybrid"),
            *("--pose-weight", "0.3", "--out", str(adapter)),
        ]
    )
    assert code == 0
    config = Adapter.load(adapter).training_info["config"]
    assert config["pose_source"] == "hybrid" and config["weights"]["pose"] == pytest.approx(0.3)
    refused = tmp_path / "refused.safetensors"
    code = main(
        ["adapt", *common, "--depth", str(tmp_path), "--pose-weight", "0.3", "--out", str(refused)]
    )
    assert code == 2 and not refused.exists()
    assert "--pose-weight" in capsys.readouterr().err


def test_teacher_options_reach_the_saved_config_and_bad_mixes_are_refused(setup, tmp_path, capsys):
    common = [*model_args(setup), "--camera", str(setup["camera"]), *frame_args(setup)]
    common += ["--steps", "1", "--windows", "2"]
    taught = tmp_path / "taught.safetensors"
    assert main(["adapt", *common, "--teacher", "5", "--out", str(taught)]) == 0
    config = Adapter.load(taught).training_info["config"]
    assert config["weights"]["teacher"] == 5.0 and config["weights"]["reproj"] == 1.0
    # The default recipe's views and weights, its teacher weight changed.
    assert config["teacher_views"] == ["centre", "left", "right"]
    assert config["teacher_view_weights"] == {"centre": 1.0, "left": 0.3, "right": 0.3}
    assert config["teacher_fov_deg"] == 110.0
    record = Adapter.load(taught).training_info["recipe"]
    assert record["name"] == "default" and record["changes"]["weights.teacher"] == [10.0, 5.0]
    alone = tmp_path / "alone.safetensors"
    code = main(
        [
            "adapt",
            *common,
            *("--teacher-only", "--teacher-views", "centre", "left", "--teacher-fov", "90"),
            *("--out", str(alone)),
        ]
    )
    assert code == 0
    config = Adapter.load(alone).training_info["config"]
    assert config["weights"]["teacher"] == 1.0 and config["weights"]["reproj"] == 0.0
    assert config["teacher_views"] == ["centre", "left"] and config["teacher_fov_deg"] == 90.0
    assert config["lr"] == pytest.approx(3e-2)
    assert "teacher_view_weights" not in config  # the mean over the views, the default
    weighted = tmp_path / "weighted.safetensors"
    views = ("--teacher-views", "centre", "left", "--teacher-view-weights", "centre=1", "left=0.3")
    assert main(["adapt", *common, "--teacher", "10", *views, "--out", str(weighted)]) == 0
    config = Adapter.load(weighted).training_info["config"]
    assert config["teacher_view_weights"] == {"centre": 1.0, "left": 0.3}
    capsys.readouterr()
    refused = tmp_path / "refused.safetensors"
    for extra, message in (
        (["--depth", str(tmp_path), "--teacher", "1"], "depth loss alone"),
        (["--teacher-only", "--teacher", "1"], "leave out --teacher"),
        (["--recipe", "matches", "--teacher-fov", "90"], "add --teacher WEIGHT"),
        (["--recipe", "matches", "--teacher-view-weights", "centre=1"], "add --teacher WEIGHT"),
        (["--recipe", "paper", "--teacher-only"], "leave out --recipe paper"),
        (["--teacher", "1", "--teacher-view-weights", "centre=x"], "centre must be a number"),
        (["--teacher", "1", "--teacher-view-weights", "front=1"], "expected centre=X"),
        (["--teacher", "1", "--teacher-view-weights", "centre=1", "centre=2"], "at most once"),
        (["--teacher", "1", "--teacher-view-weights", "left=1"], "naming exactly the teacher"),
    ):
        assert main(["adapt", *common, *extra, "--out", str(refused)]) == 2
        assert message in capsys.readouterr().err
        assert not refused.exists()


def test_adapt_fits_one_adapter_on_several_segments(setup, tmp_path, capsys):
    common = [
        "adapt",
        *model_args(setup),
        *("--camera", str(setup["camera"]), "--size", str(SIZE)),
        *("--frames", str(setup["frames"]), str(setup["frames"])),
        *("--steps", "2", "--windows", "2"),
    ]
    adapter = tmp_path / "two.safetensors"
    code = main(
        [*common, "--depth", str(setup["depth"]), str(setup["depth"]), "--out", str(adapter)]
    )
    assert code == 0
    info = Adapter.load(adapter).training_info
    assert info["supervision"]["segments"] == 2 and len(info["segment"]["segments"]) == 2
    capsys.readouterr()
    refused = tmp_path / "refused.safetensors"
    assert main([*common, "--depth", str(setup["depth"]), "--out", str(refused)]) == 2
    assert "one folder per --frames segment: 2 segments, 1 depth folders" in capsys.readouterr().err
    assert not refused.exists()


def test_supervised_adapt_from_a_depth_folder_and_the_pe_picture(setup, tmp_path, capsys):
    import cv2

    adapter = tmp_path / "supervised.safetensors"
    code = main(
        [
            "adapt",
            *model_args(setup),
            "--camera",
            str(setup["camera"]),
            *frame_args(setup),
            "--steps",
            "3",
            "--windows",
            "2",
            "--depth",
            str(setup["depth"]),
            "--out",
            str(adapter),
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "supervised.losses.csv" in out and (tmp_path / "supervised.losses.png").is_file()
    info = Adapter.load(adapter).training_info
    assert info["supervision"]["kind"] == "depth" and info["supervision"]["coverage"] > 0.9
    assert info["config"]["lr"] == 3e-2 and info["final_losses"]["depth"] > 0
    picture = tmp_path / "pe.png"
    assert main(["inspect", str(adapter), "--picture", str(picture)]) == 0
    image = cv2.imread(str(picture))
    assert image is not None and image.shape[0] >= 320 and image.std() > 10

    (setup["depth"] / "0003.png").rename(tmp_path / "moved.png")
    try:
        capsys.readouterr()
        assert (
            main(
                [
                    "adapt",
                    *model_args(setup),
                    "--camera",
                    str(setup["camera"]),
                    *frame_args(setup),
                    "--steps",
                    "1",
                    "--depth",
                    str(setup["depth"]),
                    "--out",
                    str(tmp_path / "none.safetensors"),
                ]
            )
            == 2
        )
        assert "no depth file for frame '0003'" in capsys.readouterr().err
        assert not (tmp_path / "none.safetensors").exists()
    finally:
        (tmp_path / "moved.png").rename(setup["depth"] / "0003.png")


def test_mask_reaches_adaptation_and_inference(setup, tmp_path, capsys):
    import cv2

    mask = np.full((SIZE, SIZE), 255, np.uint8)
    mask[int(0.7 * SIZE) :] = 0  # the vehicle's body
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    common = [
        *model_args(setup),
        *frame_args(setup),
    ]
    adapter = tmp_path / "adapter.safetensors"
    code = main(
        [
            "adapt",
            *common,
            "--camera",
            str(setup["camera"]),
            "--steps",
            "1",
            "--windows",
            "2",
            "--mask",
            str(tmp_path / "mask.png"),
            "--out",
            str(adapter),
        ]
    )
    assert code == 0
    lens = fisheye(SIZE, SIZE, 190.0).valid_mask().numpy()
    recorded = Adapter.load(adapter).training_info["segment"]["mask"]["valid_fraction"]
    assert recorded == pytest.approx(float((lens & (mask > 0)).mean()), abs=1e-4)

    depths = {}
    for name, extra in (("plain", []), ("masked", ["--mask", str(tmp_path / "mask.png")])):
        assert (
            main(
                [
                    "infer",
                    *common,
                    "--camera",
                    str(setup["camera"]),
                    *extra,
                    "--out",
                    str(tmp_path / name),
                ]
            )
            == 0
        )
        depths[name] = np.load(tmp_path / name / "depth" / "0000.npy")
    # The masked patches become border tokens, so the prediction changes.
    assert not np.allclose(depths["plain"], depths["masked"])

    cv2.imwrite(str(tmp_path / "small.png"), mask[:-1])
    capsys.readouterr()
    assert (
        main(
            [
                "infer",
                *common,
                "--camera",
                str(setup["camera"]),
                "--mask",
                str(tmp_path / "small.png"),
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert f"mask is {SIZE}x{SIZE - 1} px, the frames are {SIZE}x{SIZE}" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_eval_prints_a_table_for_each_method(setup, capsys):
    code = main(
        [
            "eval",
            *model_args(setup),
            "--dataset",
            str(setup["sequence"]),
            "--size",
            str(SIZE),
            "--method",
            "vanilla,center-ph,raytun3r",
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "| vanilla |" in out and "| center-ph |" in out and "| raytun3r |" in out


def test_errors_are_reported_not_raised(setup, tmp_path, capsys):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a safetensors file")
    assert main(["inspect", str(bad)]) == 2
    assert "not a readable safetensors file" in capsys.readouterr().err
    other = randomise_(
        __import__("raytun3r_plugin").Adapter.for_model(setup["net"], fisheye(SIZE, SIZE, 150.0))
    )
    other.save(tmp_path / "other.safetensors")
    code = main(
        [
            "infer",
            *model_args(setup),
            "--adapter",
            str(tmp_path / "other.safetensors"),
            "--camera",
            str(setup["camera"]),
            *frame_args(setup),
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 2 and "pass strict=False" in capsys.readouterr().err


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


def _write_segment(folder, camera, n_frames: int = 6, seed: int = 5, render_camera=None):
    """A camera file for ``camera`` and a PNG frame folder rendered through ``render_camera``
    (default: ``camera``); returns (camera file, frame folder)."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    cameras.save(camera, folder / "camera.json")
    frames = folder / "frames"
    frames.mkdir()
    for k, image in enumerate(
        synthetic.render_sequence(
            "indoor", render_camera or camera, n_frames=n_frames, seed=seed
        ).images
    ):
        cv2.imwrite(str(frames / f"{k:04d}.png"), (image[..., ::-1] * 255).round().astype(np.uint8))
    return folder / "camera.json", frames


# Non-square cameras (issue 17): adapt and infer used to lay these out differently, and the strict
# camera check refused the adapter just fitted.
NON_SQUARE = [
    (160, 128, 84, (3, 0, 154, 128)),  # a 1280x1024-shaped camera: crop
    (128, 160, 112, (4, 0, 120, 160)),  # portrait: crop
    (160, 121, 112, None),  # a 0.8% stretch, no crop (the old infer cropped one row)
]


@pytest.mark.parametrize(("width", "height", "size", "crop"), NON_SQUARE)
def test_adapt_then_infer_on_a_non_square_camera(setup, tmp_path, width, height, size, crop):
    from raytun3r_plugin import Adapter
    from raytun3r_plugin.preprocess import input_layout

    camera = fisheye(width, height, 190.0)
    camera_file, frames = _write_segment(tmp_path, camera)
    model = ["--backbone", "da3-small", "--weights", str(setup["weights"])]
    adapter = tmp_path / "adapter.safetensors"
    assert (
        main(
            [
                "adapt",
                *model,
                "--camera",
                str(camera_file),
                "--frames",
                str(frames),
                "--size",
                str(size),
                "--steps",
                "1",
                "--windows",
                "2",
                "--out",
                str(adapter),
            ]
        )
        == 0
    )
    layout = input_layout(camera, size)
    assert layout.crop == crop
    fitted = Adapter.load(adapter)
    assert fitted.training_info["input"] == layout.record()
    assert fitted.camera.to_dict() == layout.native_camera.to_dict()

    # Strict (the default): the same camera and frames are accepted, and prepared alike.
    out = tmp_path / "infer"
    assert (
        main(
            [
                "infer",
                *model,
                "--adapter",
                str(adapter),
                "--camera",
                str(camera_file),
                "--frames",
                str(frames),
                "--size",
                str(size),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    depth = np.load(out / "depth" / "0000.npy")
    # At the frames' resolution (the crop's, when the layout crops), 0 outside the lens circle.
    assert depth.shape == (layout.native_camera.height, layout.native_camera.width)
    assert np.isfinite(depth).all() and (depth[layout.native_camera.valid_mask().numpy()] > 0).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["depth"]["camera"] == json.loads(layout.native_camera.to_json())
    assert summary["input_size"] == [layout.width, layout.height]
    assert summary["camera"] == json.loads(layout.camera.to_json())

    # Without --camera and --size: the adapter's camera (its crop undone) and its long side.
    again = tmp_path / "again"
    assert (
        main(
            [
                "infer",
                *model,
                "--adapter",
                str(adapter),
                "--frames",
                str(frames),
                "--out",
                str(again),
            ]
        )
        == 0
    )
    assert np.array_equal(np.load(again / "depth" / "0000.npy"), depth)


def test_infer_rescales_the_camera_to_frames_of_another_size(setup, tmp_path, capsys):
    camera = fisheye(160, 120, 190.0)
    camera_file, frames = _write_segment(tmp_path / "native", camera)
    model = ["--backbone", "da3-small", "--weights", str(setup["weights"])]
    adapter = tmp_path / "adapter.safetensors"
    assert (
        main(
            [
                "adapt",
                *model,
                "--camera",
                str(camera_file),
                "--frames",
                str(frames),
                "--size",
                "112",
                "--steps",
                "1",
                "--windows",
                "2",
                "--out",
                str(adapter),
            ]
        )
        == 0
    )
    # The same calibration, frames recorded at twice the size: a pure resize of the camera.
    _, large = _write_segment(
        tmp_path / "large", camera, n_frames=3, render_camera=camera.resized(320, 240)
    )
    out = tmp_path / "infer"
    assert (
        main(
            [
                "infer",
                *model,
                "--adapter",
                str(adapter),
                "--camera",
                str(camera_file),
                "--frames",
                str(large),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    # Depth at the frames' resolution by default; the network saw 112 x 84.
    assert np.load(out / "depth" / "0000.npy").shape == (240, 320)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["camera"] == json.loads(camera.resized(320, 240).resized(112, 84).to_json())
    assert summary["depth"]["resolution"] == "frames"
    assert summary["depth"]["camera"] == json.loads(camera.resized(320, 240).to_json())
    # Frames of another aspect ratio are not a resize of this camera: an error, not a stretch.
    _, other = _write_segment(
        tmp_path / "other", camera, n_frames=2, render_camera=fisheye(160, 100, 190.0)
    )
    capsys.readouterr()
    assert (
        main(
            [
                "infer",
                *model,
                "--adapter",
                str(adapter),
                "--camera",
                str(camera_file),
                "--frames",
                str(other),
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "only a pure resize" in capsys.readouterr().err


def test_adapt_infer_and_eval_feed_the_network_the_same_input(setup, tmp_path, monkeypatch):
    """The three paths from native frames to the network share one preparation."""
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.problem import prepare_problem
    from raytun3r_plugin.apps import inference
    from raytun3r_plugin.apps.evaluation import fit_sequence
    from raytun3r_plugin.datasets import Sequence
    from raytun3r_plugin.images import read_frames

    camera = fisheye(160, 128, 190.0)  # needs a crop at 84 px
    camera_file, frames = _write_segment(tmp_path, camera)
    native, _ = read_frames(frames)
    problem = prepare_problem(camera, native, AdaptConfig(input_size=84, n_windows=2, steps=1))
    evaluated = fit_sequence(
        Sequence(
            name="s",
            camera=camera,
            timestamps=np.arange(len(native)),
            cam_from_world=None,
            images=native,
        ),
        84,
    )
    seen = {}
    real = inference.predict_with_camera

    def spy(model, camera, adapter, images, **kwargs):
        seen.update(camera=camera, images=images)
        return real(model, camera, adapter, images, **kwargs)

    monkeypatch.setattr(inference, "predict_with_camera", spy)
    assert (
        main(
            [
                "infer",
                *model_args(setup),
                "--camera",
                str(camera_file),
                "--frames",
                str(frames),
                "--size",
                "84",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    for frame, adapted in problem.inputs.items():
        assert torch.equal(seen["images"][0, frame], adapted)
        assert torch.equal(torch.from_numpy(evaluated.images[frame]).permute(2, 0, 1), adapted)
    # And the same cameras: infer patches with adapt's camera, eval scores with its input camera.
    assert seen["camera"].to_dict() == problem.layout.native_camera.to_dict()
    assert evaluated.camera.to_dict() == problem.layout.camera.to_dict()


def test_eval_with_a_perturbed_calibration_reports_both_rows(setup, capsys):
    code = main(
        [
            "eval",
            *model_args(setup),
            "--dataset",
            str(setup["sequence"]),
            "--size",
            str(SIZE),
            "--method",
            "raytun3r",
            "--perturb-calibration",
            "focal=0.1,principal=0.02",
            "--pair-stride",
            "2",
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "| raytun3r |" in out
    assert "| raytun3r (calibration focal +0.1, principal +0.02) |" in out
    assert "trans_folded_deg" in out and "protocol: pair stride 2 (given)" in out
    assert (
        main(
            [
                "eval",
                *model_args(setup),
                "--dataset",
                str(setup["sequence"]),
                "--perturb-calibration",
                "zoom=2",
            ]
        )
        == 2
    )
