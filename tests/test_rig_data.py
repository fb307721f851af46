"""Rig data and the joint rig fit: ``render_rig``, ``Rig``, the TUM-VI / ETH3D rig builders and
``adapt_rig`` (docs/rigs.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

import raytun3r_plugin as rt
from raytun3r_plugin.adaptation import AdaptConfig
from raytun3r_plugin.adaptation.rig import adapt_rig, rig_artifact_paths
from raytun3r_plugin.datasets._common import invert_pose
from raytun3r_plugin.datasets.rig import (
    load_eth3d_rig_set,
    load_tumvi_rig,
    rig_from_sequences,
)
from raytun3r_plugin.errors import DatasetError, InputError
from raytun3r_plugin.synthetic.generate import render_rig, scene_of, stereo_extrinsics
from tests.helpers import assert_same_snapshot, fisheye, snapshot
from tests.test_datasets import T0, T_CAM_IMU, H, W, rigid, rot, tumvi_fixture, write_png
from tests.test_datasets_readers import CAM5_FROM_CAM4, eth3d_fixture

CAM1_FROM_CAM0 = rigid(rot([0.0, 1.0, 0.1], 3.0), [-0.11, 0.001, 0.0])


@pytest.fixture(scope="module")
def stereo():
    cameras = {
        "left": fisheye(56, 56, 190.0),
        "right": fisheye(56, 56, 165.0, k1=0.03),
    }
    return render_rig("indoor", cameras, n_frames=6, seed=7, flow_px=5.0)


def test_render_rig_sees_one_scene_from_a_rigid_rig(stereo):
    left, right = stereo.sequences["left"], stereo.sequences["right"]
    relative = right.cam_from_world @ invert_pose(left.cam_from_world)
    np.testing.assert_allclose(
        relative, np.broadcast_to(stereo_extrinsics()["right"], relative.shape), atol=1e-12
    )
    assert scene_of(left) is scene_of(right)
    # The baseline puts the right camera 0.1 m to the left camera's right.
    centres = [invert_pose(seq.cam_from_world)[:, :3, 3] for seq in (left, right)]
    np.testing.assert_allclose(np.linalg.norm(centres[1] - centres[0], axis=1), 0.1, atol=1e-12)
    views = stereo.views([2, 4])
    assert views.shape == (4, 56, 56, 3)
    assert np.array_equal(views[1], right.image(2)) and np.array_equal(views[2], left.image(4))
    assert not np.array_equal(views[0], views[1])


def test_render_rig_refuses_cameras_of_two_sizes():
    with pytest.raises(InputError, match="one image size"):
        render_rig("indoor", {"left": fisheye(56, 56), "right": fisheye(70, 56)}, n_frames=2)


def test_rig_from_sequences_measures_and_checks_the_extrinsics(stereo):
    left, right = stereo.sequences["left"], stereo.sequences["right"]
    rig = rig_from_sequences({"left": left, "right": right})
    np.testing.assert_allclose(rig.cam_from_rig["right"], stereo_extrinsics()["right"], atol=1e-9)
    np.testing.assert_allclose(rig.cam_from_rig["left"], np.eye(4), atol=1e-12)
    # A camera that moves against the other is not a rig.
    moved = right.subset(range(len(right)))
    moved.cam_from_world = moved.cam_from_world.copy()
    moved.cam_from_world[3, 0, 3] += 0.05
    with pytest.raises(DatasetError, match="rigid rig"):
        rig_from_sequences({"left": left, "right": moved})
    # Frames are matched by time: a camera shifted by half a frame shares no instant.
    late = right.subset(range(len(right)))
    late.timestamps = late.timestamps + 0.05
    with pytest.raises(DatasetError, match="no instant"):
        rig_from_sequences({"left": left, "right": late}, stereo.cam_from_rig)


def test_tumvi_rig_takes_its_extrinsics_from_the_camchain(tmp_path):
    root = tmp_path / "dataset-room1_512_16"
    images = tumvi_fixture(root)
    chain = yaml.safe_load((root / "camchain.yaml").read_text())
    chain["cam1"] = json.loads(json.dumps(chain["cam0"]))  # a copy: no YAML aliases
    chain["cam1"]["T_cam_imu"] = (CAM1_FROM_CAM0 @ T_CAM_IMU).tolist()
    chain["cam1"]["intrinsics"] = [4.6, 4.6, 6.0, 4.7]  # its own lens
    (root / "camchain.yaml").write_text(yaml.safe_dump(chain, sort_keys=False))
    cam1 = root / "mav0" / "cam1"
    (cam1 / "data").mkdir(parents=True)
    (cam1 / "data.csv").write_text(
        "\n".join(["#timestamp [ns],filename"] + [f"{t},{t}.png" for t in images]) + "\n"
    )
    for t in images:
        write_png(cam1 / "data" / f"{t}.png", 20000, dtype=np.uint16, channels=1)
    rig = load_tumvi_rig(root)
    assert rig.names == ["cam0", "cam1"] and len(rig) == len(rig.sequences["cam0"])
    np.testing.assert_allclose(rig.cam_from_rig["cam1"], CAM1_FROM_CAM0, atol=1e-9)
    assert rig.meta["extrinsics"] == "camchain T_cam_imu"
    views = rig.views([0])
    assert views.shape == (2, H, W, 3) and np.allclose(views[1], 20000 / 65535)
    assert int(rig.sequences["cam1"].meta["per_frame"]["timestamp_ns"][0]) >= T0


def test_eth3d_rig_set_puts_the_reference_first(tmp_path):
    scene = tmp_path / "delivery_area"
    eth3d_fixture(scene)
    rig = load_eth3d_rig_set(scene)
    assert rig.names == ["images_rig_cam4", "images_rig_cam5"] and len(rig) == 3
    np.testing.assert_allclose(rig.cam_from_rig["images_rig_cam5"], CAM5_FROM_CAM4, atol=1e-9)
    assert rig.views([1]).shape == (2, H, W, 3)


def test_adapt_rig_fits_each_camera_in_one_forward(stereo, tmp_path):
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    torch.manual_seed(0)
    model = build_tiny_network(seed=0).eval()
    before = snapshot(model)
    views_seen = []
    original = type(model).forward

    def spy(self, x, *args, **kwargs):
        views_seen.append(int(x.shape[1]))
        return original(self, x, *args, **kwargs)

    type(model).forward = spy
    try:
        # No guard here: its checks are forwards too (tests/test_rig_fit_loop.py has them).
        config = AdaptConfig.from_recipe(
            "matches",
            steps=3,
            input_size=56,
            n_windows=2,
            checkpoint_every=0,
            min_parallax_px=0.0,
            guard=False,
        )
        fitted = adapt_rig(model, stereo, config, out_dir=tmp_path, progress=False)
    finally:
        type(model).forward = original
    assert set(fitted) == {"left", "right"}
    # One forward per step, with every camera's window in it.
    assert views_seen == [6, 6, 6]
    for name, adapter in fitted.items():
        info = adapter.training_info
        assert info["rig"]["cameras"] == ["left", "right"] and info["rig"]["camera"] == name
        assert info["steps"] == 3 and info["rig"]["views_per_forward"] == 6
        assert info["verdict"]["status"] == "ok" and "parallax_gate" not in info
        assert adapter.camera.width == 56
        moved = sum(float(p.detach().abs().sum()) for p in adapter.parameters())
        assert moved > 0.0  # each camera's tables got gradient from its own views
    assert not torch.equal(fitted["left"].pe["radial"], fitted["right"].pe["radial"])
    assert rt.handle_of(model) is None
    assert_same_snapshot(model, before)
    paths = rig_artifact_paths(tmp_path, ["left", "right"])
    for path in paths.values():
        assert path.is_file(), path
    log = [json.loads(line) for line in paths["log"].read_text().splitlines()]
    assert len(log) == 3 and {"left:loss", "right:loss", "loss"} <= set(log[0])
    reloaded = rt.Adapter.load(paths["adapter:right"])
    assert torch.equal(reloaded.pe["radial"], fitted["right"].pe["radial"])
    # The fitted pair applies as a rig.
    with rt.apply(
        model, [fitted["left"].camera, fitted["right"].camera], [fitted["left"], fitted["right"]]
    ) as handle:
        assert handle.is_rig


def _run_reader_rig(rig):
    """A reader's rig through a patched DA3 net: its cameras resized to the 84 x 70 input."""
    import cv2

    from raytun3r_plugin import predict
    from tests.backbones import make

    model = make("da3")
    before = snapshot(model)
    cameras = [camera.resized(84, 70) for camera in rig.cameras]
    views = rig.views([0, 1])
    images = np.stack([cv2.resize(v, (84, 70), interpolation=cv2.INTER_AREA) for v in views])
    batch = torch.from_numpy(images).permute(0, 3, 1, 2)[None].float()
    with torch.no_grad():
        plain = predict(model, batch).depth
        with rt.apply(model, cameras) as handle:
            assert handle.is_rig and len(handle.cameras) == len(rig.names)
            patched = predict(model, batch).depth
    assert torch.isfinite(patched).all() and not torch.equal(patched, plain)
    assert_same_snapshot(model, before)


def test_a_tumvi_and_an_eth3d_rig_run_through_a_patched_model(tmp_path):
    eth3d = tmp_path / "delivery_area"
    eth3d_fixture(eth3d)
    _run_reader_rig(load_eth3d_rig_set(eth3d))
    root = tmp_path / "dataset-room1_512_16"
    test_tumvi_rig_takes_its_extrinsics_from_the_camchain(tmp_path)
    _run_reader_rig(load_tumvi_rig(root))


def test_adapt_rig_gate_without_signal_leaves_every_camera_as_it_started(stereo):
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    model = build_tiny_network(seed=0).eval()
    config = AdaptConfig.from_recipe(
        "matches", steps=3, input_size=56, n_windows=2, checkpoint_every=0, min_parallax_px=1e9
    )
    fitted = adapt_rig(model, stereo, config, progress=False)
    for adapter in fitted.values():
        info = adapter.training_info
        assert info["verdict"]["status"] == "no signal" and info["steps"] == 0
        assert info["parallax_gate"]["windows_kept"] == 0
        assert all(float(p.detach().abs().sum()) == 0.0 for p in adapter.parameters())


def _write_tumvi_rig(root, rig) -> None:
    """``rig`` (rendered, KB4 cameras) written in the TUM-VI / EuRoC layout: cam0 + cam1 images,
    a Kalibr camchain (equidistant = KB4) and mocap poses of the IMU (= cam0)."""
    import cv2

    from raytun3r_plugin.datasets._common import rot_to_quat

    mav = root / "mav0"
    chain = {}
    times = [T0 + k * 50_000_000 for k in range(len(rig))]
    for name, cam in zip(rig.names, ("cam0", "cam1"), strict=True):
        seq = rig.sequences[name]
        values = seq.camera.values
        chain[cam] = {
            "T_cam_imu": rig.cam_from_rig[name].tolist(),
            "camera_model": "pinhole",
            "distortion_coeffs": [float(values[k]) for k in ("k1", "k2", "k3", "k4")],
            "distortion_model": "equidistant",
            "intrinsics": [float(values[k]) for k in ("fx", "fy", "cx", "cy")],
            "resolution": [int(seq.camera.width), int(seq.camera.height)],
            "rostopic": f"/{cam}/image_raw",
        }
        (mav / cam / "data").mkdir(parents=True)
        rows = ["#timestamp [ns],filename"]
        for k, t in enumerate(times):
            gray = cv2.cvtColor((seq.images[k] * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
            cv2.imwrite(str(mav / cam / "data" / f"{t}.png"), gray)
            rows.append(f"{t},{t}.png")
        (mav / cam / "data.csv").write_text("\n".join(rows) + "\n")
    (root / "camchain.yaml").write_text(yaml.safe_dump(chain, sort_keys=False))
    world_from_imu = invert_pose(rig.sequences[rig.names[0]].cam_from_world)
    rows = [
        "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    ]
    for t, pose in zip(times, world_from_imu, strict=True):
        q = rot_to_quat(pose[:3, :3])
        rows.append(f"{t}," + ",".join(repr(float(x)) for x in [*pose[:3, 3], *q]))
    (mav / "mocap0").mkdir(parents=True)
    (mav / "mocap0" / "data.csv").write_text("\n".join(rows) + "\n")


def test_cli_adapt_rig_on_a_tumvi_rig(tmp_path, capsys):
    from raytun3r_plugin.apps.cli import main

    cameras = {"left": fisheye(56, 56, 190.0), "right": fisheye(56, 56, 170.0, k1=0.03)}
    rendered = render_rig("indoor", cameras, n_frames=6, seed=11, flow_px=5.0)
    root = tmp_path / "dataset-room9_512_16"
    _write_tumvi_rig(root, rendered)
    rig = load_tumvi_rig(root)
    np.testing.assert_allclose(rig.cam_from_rig["cam1"], stereo_extrinsics()["right"], atol=1e-9)
    out = tmp_path / "adapters"
    code = main(
        [
            "adapt-rig",
            "--backbone",
            "raytun3r-da3-tiny",
            str(root),
            "--format",
            "tumvi",
            "--size",
            "56",
            "--steps",
            "2",
            "--windows",
            "2",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "cam0: saved" in text and "cam1: saved" in text
    for cam in ("cam0", "cam1"):
        adapter = rt.Adapter.load(out / f"{cam}.safetensors")
        assert adapter.training_info["rig"]["cameras"] == ["cam0", "cam1"]
        assert adapter.training_info["method"] == "raytun3r rig adaptation"


def test_rig_inputs_are_each_cameras_layout_instant_major(stereo):
    from raytun3r_plugin.preprocess import InputLayout

    images, cameras = stereo.inputs([1, 3], long_side=28)
    assert images.shape == (1, 4, 3, 28, 28) and len(cameras) == 2
    for index, name in enumerate(stereo.names):
        layout = InputLayout.for_camera(stereo.sequences[name].camera, 28)
        expected = layout.frames(stereo.sequences[name].images[[1, 3]])
        assert torch.equal(images[0, index::2], expected)
        assert cameras[index] == layout.native_camera


def test_adapt_rig_cross_camera_terms_give_signal_where_motion_gives_none(monkeypatch):
    """Every temporal window gated off: only the cross-camera terms can move the tables."""
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    from raytun3r_plugin.adaptation import rig as rig_fit

    # Forward driving: the gate finds no parallax in any temporal window (as at 112 px).
    monkeypatch.setattr(
        rig_fit,
        "window_parallax",
        lambda model, adapter, problem, config: [0.0] * len(problem.windows),
    )
    lens = fisheye(56, 56, 185.0)
    rig = render_rig(
        "outdoor",
        {"left": lens, "right": lens},
        stereo_extrinsics(0.4),
        n_frames=6,
        seed=3,
        flow_px=10.0,
    )
    model = build_tiny_network(seed=0).eval()
    config = AdaptConfig.from_recipe(
        "matches", steps=3, input_size=56, n_windows=2, checkpoint_every=0, min_motion_px=0.5
    )
    plain = adapt_rig(model, rig, config, progress=False)
    assert all(a.training_info["verdict"]["status"] == "no signal" for a in plain.values())
    fitted = adapt_rig(model, rig, config, progress=False, cross_camera=True)
    for name, adapter in fitted.items():
        info = adapter.training_info
        assert info["steps"] == 3 and info["rig"]["cross_camera"]["pairs"] > 0
        assert info["rig"]["cross_camera"]["aligned_steps"] == 3
        assert "cross-camera pairs" not in info["rig"]["left_out"]
        assert info["verdict"]["status"] == "ok", (name, info["verdict"])
        assert sum(float(p.detach().abs().sum()) for p in adapter.parameters()) > 0.0
