"""The command line on cameras and frames of other sizes: non-square cameras, frames of another
size than the calibration, and one network input for adapt, infer and eval."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from raytun3r_plugin import Adapter, cameras, synthetic
from raytun3r_plugin.apps.cli import main
from tests.helpers import fisheye

pytest.importorskip("depth_anything_3")
from tests.cli_setup import SIZE, build_cli_setup, model_args  # noqa: E402


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The module's weight file, camera file and sequence (tests/cli_setup.py)."""
    return build_cli_setup(tmp_path_factory.mktemp("cli"))


def _one_step_adapt(model: list[str], camera_file, frames, size: int, adapter) -> list[str]:
    """``raytun3r adapt`` of one step on two windows: the fit these tests only need to exist."""
    return [
        "adapt",
        *model,
        *("--camera", str(camera_file), "--frames", str(frames), "--size", str(size)),
        *("--steps", "1", "--windows", "2", "--out", str(adapter)),
    ]


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
    from raytun3r_plugin.preprocess import input_layout

    camera = fisheye(width, height, 190.0)
    camera_file, frames = _write_segment(tmp_path, camera)
    model = model_args(setup)
    adapter = tmp_path / "adapter.safetensors"
    assert main(_one_step_adapt(model, camera_file, frames, size, adapter)) == 0
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
    model = model_args(setup)
    adapter = tmp_path / "adapter.safetensors"
    assert main(_one_step_adapt(model, camera_file, frames, 112, adapter)) == 0
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


@pytest.mark.parametrize(
    ("option", "value", "named"),
    [
        ("--perturb-calibration", "zoom=2", "--perturb-calibration"),
        ("--pair-stride", "two", "--pair-stride"),
        ("--method", "vanilla,fisheye-magic", "fisheye-magic"),
    ],
)
def test_eval_refuses_a_bad_option_before_loading_the_model(
    setup, capsys, monkeypatch, option, value, named
):
    from raytun3r_plugin.apps import cli

    def no_load(*args, **kwargs):
        raise AssertionError("the model was loaded before the options were checked")

    monkeypatch.setattr(cli, "_load_model", no_load)
    code = main(["eval", *model_args(setup), "--dataset", str(setup["sequence"]), option, value])
    assert code == 2
    assert named in capsys.readouterr().err
