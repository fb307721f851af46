"""``raytun3r infer --export ...`` end to end on a random da3-small network."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras, synthetic
from raytun3r_plugin.apps.cli import main
from raytun3r_plugin.preprocess import input_layout
from tests.helpers import fisheye

pytest.importorskip("depth_anything_3")
pycolmap = pytest.importorskip("pycolmap")
trimesh = pytest.importorskip("trimesh")
pytest.importorskip("rerun")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Random da3-small weights, a 160 x 128 fisheye (cropped to 154 x 128 at 84 px) with its
    file, a double-sphere file of the same size, and four rendered frames."""
    from raytun3r_plugin.patches.da3_networks import build_network
    from safetensors.torch import save_model

    folder = tmp_path_factory.mktemp("exports_cli")
    torch.manual_seed(0)
    weights = folder / "model.safetensors"
    save_model(build_network("da3-small"), str(weights))
    camera = fisheye(160, 128, 190.0)
    cameras.save(camera, folder / "camera.json")
    cameras.save(cameras.fisheye((160, 128), 195.0, "ds"), folder / "ds.json")
    frames = folder / "frames"
    frames.mkdir()
    for k, image in enumerate(
        synthetic.render_sequence("indoor", camera, n_frames=4, seed=2).images
    ):
        cv2.imwrite(str(frames / f"{k:04d}.png"), (image[..., ::-1] * 255).round().astype(np.uint8))
    return {"folder": folder, "weights": weights, "camera": camera, "frames": frames}


def _infer(inputs, out, *extra, camera="camera.json") -> int:
    return main(
        [
            "infer",
            "--backbone",
            "da3-small",
            "--weights",
            str(inputs["weights"]),
            "--camera",
            str(inputs["folder"] / camera),
            "--frames",
            str(inputs["frames"]),
            "--size",
            "84",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_every_export_from_one_command(inputs, tmp_path, capsys):
    out = tmp_path / "out"
    code = _infer(
        inputs,
        out,
        "--export",
        "colmap",
        "--export",
        "nerfstudio,glb",
        "--export",
        "rerun",
        "--depth-convention",
        "z",
        "--max-points",
        "800",
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "z depth at the frames' resolution (154x128 px)" in printed
    assert "COLMAP projects only rays within 89 deg" in printed and "no Pinhole" in printed
    layout = input_layout(inputs["camera"], 84)
    native = layout.native_camera
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary["exports"]) == ["colmap", "glb", "nerfstudio", "rerun"]
    assert summary["depth"]["convention"] == "z" and summary["depth"]["resolution"] == "frames"
    assert np.load(out / "depth" / "0000.npy").shape == (native.height, native.width)

    reconstruction = pycolmap.Reconstruction(str(out / "colmap" / "sparse" / "0"))
    camera = reconstruction.cameras[1]
    assert camera.model_name == "OPENCV_FISHEYE" and (camera.width, camera.height) == (154, 128)
    assert np.allclose(camera.params[2:4], [native.values["cx"] + 0.5, native.values["cy"] + 0.5])
    assert reconstruction.num_images() == 4 and reconstruction.num_points3D() > 100
    assert all(
        (out / "colmap" / "images" / image.name).is_file()
        for image in reconstruction.images.values()
    )

    meta = json.loads((out / "nerfstudio" / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (154, 128) and meta["depth_convention"].startswith("z")
    assert len(meta["frames"]) == 4
    loaded = trimesh.load(out / "scene.glb", force="scene")
    assert len(loaded.geometry) == 5 and (out / "recording.rrd").stat().st_size > 1000


def test_a_refused_export_writes_nothing(inputs, tmp_path, capsys):
    """A double-sphere lens needs a fitted OPENCV_FISHEYE for COLMAP: with a threshold below
    its error the command fails naming the alternatives, and the output folder is not made."""
    out = tmp_path / "out"
    code = _infer(inputs, out, "--export", "colmap", "--max-fit-error-px", "1e-9", camera="ds.json")
    assert code == 2
    error = capsys.readouterr().err
    assert "no 'ds' lens" in error and "glb or rerun" in error
    assert not out.exists()


def test_an_unknown_export_is_refused_before_the_network_runs(
    inputs, tmp_path, capsys, monkeypatch
):
    from raytun3r_plugin.apps import cli

    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded")

    monkeypatch.setattr(cli, "_load_model", no_model)
    assert _infer(inputs, tmp_path / "out", "--export", "ply") == 2
    assert "unknown export ['ply']" in capsys.readouterr().err
