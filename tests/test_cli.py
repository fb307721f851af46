"""The ``raytun3r`` command line, end to end on small synthetic data: adapt, inspect, infer and
eval (bench and demo: tests/test_cli_bench_demo.py; input sizes: tests/test_cli_input_sizes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from raytun3r_plugin import Adapter
from raytun3r_plugin.apps.cli import main
from raytun3r_plugin.exports.files import read_ply
from tests.helpers import fisheye, randomise_

pytest.importorskip("depth_anything_3")
from tests.cli_setup import SIZE, build_cli_setup, frame_args, model_args  # noqa: E402


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The module's weight file, camera file and sequence (tests/cli_setup.py)."""
    return build_cli_setup(tmp_path_factory.mktemp("cli"))


def test_adapt_fits_with_the_backbone_familys_declared_changes(setup, capsys, monkeypatch):
    """A change the backbone's family declares for the recipe reaches ``raytun3r adapt``'s fit,
    its message and its file's record."""
    import dataclasses

    from raytun3r_plugin import registry

    spec = registry.specs()["da3"]
    declared = dataclasses.replace(spec, recipe_changes={"default": {"guard_every": 7}})
    monkeypatch.setitem(registry._SPECS, spec.family, declared)
    adapter = setup["folder"] / "family.safetensors"
    words = ["adapt", *model_args(setup), "--camera", str(setup["camera"]), *frame_args(setup)]
    assert main([*words, "--steps", "2", "--windows", "2", "--out", str(adapter)]) == 0
    assert "the backbone family's: guard_every 7" in capsys.readouterr().err
    info = Adapter.load(adapter).training_info
    assert info["config"]["guard_every"] == 7
    assert info["recipe"]["backbone_changes"] == {"guard_every": 7}
    assert "guard_every" not in info["recipe"]["changes"]


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
