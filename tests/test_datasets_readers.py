"""ETH3D rig, Aria Digital Twin and ScanNet++ mask readers on tiny files in each real layout."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from raytun3r_plugin import cameras
from raytun3r_plugin.datasets import (
    detect_kind,
    eth3d_rig_cameras,
    load_adt,
    load_eth3d_rig,
    load_eth3d_rig_all,
    load_scannetpp_transforms,
    load_sequence,
    read_aria_calibration,
)
from raytun3r_plugin.datasets._common import invert_pose, rot_to_quat
from raytun3r_plugin.errors import DatasetError
from tests.test_datasets import H, W, poses, rigid, rot, scannetpp_fixture, write_png

# ------------------------------------------------------------------------------------------
# ETH3D multi-camera rig
# ------------------------------------------------------------------------------------------

TS = [1477843917481127523, 1477843917554855523, 1477843917628583523]
# cam5 relative to cam4 (the reference): 10 cm baseline and a small rotation.
CAM5_FROM_CAM4 = rigid(rot([0.1, 1.0, 0.0], 8.0), [-0.1, 0.002, 0.01])


def eth3d_fixture(scene: Path, names: dict | None = None) -> np.ndarray:
    """A rig scene with cameras 4 and 5; returns the reference camera's cam_from_world."""
    calib = scene / "rig_calibration"
    calib.mkdir(parents=True)
    (calib / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"0 THIN_PRISM_FISHEYE {W} {H} 5.5 5.4 5.6 4.4 0.02 -0.003 1e-4 -2e-4 0.001 0.0 1e-4 0.0\n"
        f"1 THIN_PRISM_FISHEYE {W} {H} 5.3 5.35 5.4 4.6 0.01 0.0 0.0 0.0 0.0 0.0 0.0 0.0\n"
    )
    ref = poses(len(TS), seed=11)
    lines = ["# Image list with two lines of data per image:"]
    k = 0
    for cam_id, folder, X in ((0, "images_rig_cam4", np.eye(4)), (1, "images_rig_cam5", None)):
        for i, t in enumerate(TS):
            T = ref[i] if X is not None else CAM5_FROM_CAM4 @ ref[i]
            nm = (names or {}).get((folder, i), f"{folder}/{t}.png")
            q = rot_to_quat(T[:3, :3])
            vals = " ".join(repr(float(x)) for x in [*q, *T[:3, 3]])
            lines.append(f"{k + 1} {vals} {cam_id} {nm}")
            lines.append("")
            write_png(scene / "images" / folder / f"{t}.png", 40 + k)
            k += 1
    (calib / "images.txt").write_text("\n".join(lines) + "\n")
    return ref


def test_eth3d_rig_reader(tmp_path):
    scene = tmp_path / "delivery_area"
    ref = eth3d_fixture(scene)
    assert eth3d_rig_cameras(scene) == ["images_rig_cam4", "images_rig_cam5"]
    seq = load_eth3d_rig(scene, camera="images_rig_cam5")
    assert isinstance(seq.camera, cameras.ThinPrismFisheye)
    # COLMAP principal point (pixel centre at 0.5) -> raytun3r's (pixel centre at 0).
    assert seq.camera.values["cx"] == pytest.approx(4.9) and seq.camera.values["fx"] == 5.3
    np.testing.assert_allclose(seq.cam_from_world, CAM5_FROM_CAM4[None] @ ref, atol=1e-9)
    np.testing.assert_allclose(seq.timestamps, np.array(TS) * 1e-9)
    assert seq.meta["per_frame"]["timestamp_ns"].tolist() == TS
    assert seq.image_paths[1] == scene / "images" / "images_rig_cam5" / f"{TS[1]}.png"
    assert seq.image(0).shape == (H, W, 3)
    rig = seq.meta["rig"]
    assert rig["ref_camera"] == "images_rig_cam4" and rig["n_shared"] == 3
    np.testing.assert_allclose(rig["cam_from_ref"], CAM5_FROM_CAM4, atol=1e-9)
    assert rig["max_dev_m"] < 1e-9 and rig["max_dev_deg"] < 1e-5
    both = load_eth3d_rig_all(scene)
    np.testing.assert_allclose(
        both["images_rig_cam4"].meta["rig"]["cam_from_ref"], np.eye(4), atol=1e-12
    )
    assert detect_kind(scene) == "eth3d_rig"
    assert len(load_sequence(scene, camera="images_rig_cam4")) == 3


def test_eth3d_rig_depth(tmp_path):
    scene = tmp_path / "s"
    eth3d_fixture(scene)
    ddir = tmp_path / "depth"
    vals = np.full((H, W), 3.5, dtype="<f4")
    vals[0, 0] = np.inf
    vals[1, 2] = np.nan
    for t in TS:
        (ddir / "images_rig_cam4").mkdir(parents=True, exist_ok=True)
        vals.tofile(ddir / "images_rig_cam4" / f"{t}.png")
    seq = load_eth3d_rig(scene, camera="images_rig_cam4", depth_dir=ddir, depth_kind="z")
    assert seq.depth.shape == (3, H, W) and seq.depth_kind == "z"
    assert seq.depth[0, 0, 0] == 0.0 and seq.depth[0, 1, 2] == 0.0 and seq.depth[2, 5, 5] == 3.5
    with pytest.raises(DatasetError, match="depth_kind"):
        load_eth3d_rig(scene, camera="images_rig_cam4", depth_dir=ddir)
    vals[:5].tofile(ddir / "images_rig_cam4" / f"{TS[1]}.png")
    with pytest.raises(DatasetError, match=f"{TS[1]}.png: depth file holds 60"):
        load_eth3d_rig(scene, camera="images_rig_cam4", depth_dir=ddir, depth_kind="z")


def test_eth3d_rig_errors(tmp_path):
    scene = tmp_path / "a"
    eth3d_fixture(scene)
    with pytest.raises(DatasetError, match="several rig cameras"):
        load_eth3d_rig(scene)
    with pytest.raises(DatasetError, match="no images of camera 'images_rig_cam9'"):
        load_eth3d_rig(scene, camera="images_rig_cam9")
    # A NAME without the camera folder, and one whose file name is not a timestamp: the
    # message names images.txt and the line (line 1 is the comment, images start at 2).
    b = tmp_path / "b"
    eth3d_fixture(b, names={("images_rig_cam4", 1): f"{TS[1]}.png"})
    with pytest.raises(DatasetError, match=r"rig_calibration/images.txt:4: NAME"):
        load_eth3d_rig(b, camera="images_rig_cam4")
    c = tmp_path / "c"
    eth3d_fixture(c, names={("images_rig_cam5", 0): "images_rig_cam5/frame_a.png"})
    with pytest.raises(DatasetError, match=r"images.txt:8: .*not an integer timestamp"):
        load_eth3d_rig(c, camera="images_rig_cam5")
    with pytest.raises(DatasetError, match="rig_calibration/cameras.txt: file not found"):
        load_eth3d_rig(tmp_path / "missing")


# ------------------------------------------------------------------------------------------
# Project Aria / Aria Digital Twin
# ------------------------------------------------------------------------------------------

AW, AH = 16, 14
# f, cx, cy, k0..k5, p0, p1, s0..s3 (Fisheye624, single focal length).
ARIA_PARAMS = [6.0, 7.6, 6.4, 0.3, -0.1, 0.02, 0.0, 0.0, 0.0, 1e-4, -2e-4, 1e-4, 0.0, -1e-4, 0.0]
DEVICE_FROM_CAM = rigid(rot([0.3, -1.0, 0.2], 25.0), [0.004, -0.012, -0.005])


def aria_calibration(params=None, name="FisheyeRadTanThinPrism", quat=None) -> dict:
    q = rot_to_quat(DEVICE_FROM_CAM[:3, :3])
    return {
        "AlgorithmName": "test",
        "CalibrationSource": "Factory",
        "CameraCalibrations": [
            {
                "Calibrated": True,
                "Label": "camera-slam-left",
                "Projection": {"Name": "FisheyeRadTanThinPrism", "Params": [5.0, 8, 7] + [0] * 12},
                "SerialNumber": "0",
                "T_Device_Camera": {"Translation": [0, 0, 0], "UnitQuaternion": [1, [0, 0, 0]]},
            },
            {
                "Calibrated": True,
                "Label": "camera-rgb",
                "Projection": {
                    "Description": "see FisheyeRadTanThinPrism.h",
                    "Name": name,
                    "Params": params or ARIA_PARAMS,
                },
                "SerialNumber": "1",
                "T_Device_Camera": {
                    "Translation": DEVICE_FROM_CAM[:3, 3].tolist(),
                    "UnitQuaternion": quat or [float(q[0]), [float(x) for x in q[1:]]],
                },
            },
        ],
        "ImuCalibrations": [],
    }


TRAJ_HEADER = (
    "graph_uid,tracking_timestamp_us,utc_timestamp_ns,tx_world_device,ty_world_device,"
    "tz_world_device,qx_world_device,qy_world_device,qz_world_device,qw_world_device,"
    "device_linear_velocity_x_device,device_linear_velocity_y_device,"
    "device_linear_velocity_z_device,angular_velocity_x_device,angular_velocity_y_device,"
    "angular_velocity_z_device,gravity_x_world,gravity_y_world,gravity_z_world,quality_score"
)


def world_from_device(t_s: float) -> np.ndarray:
    """Constant-rate rotation about one axis and linear motion: exact under slerp + lerp."""
    return rigid(rot([0.0, 0.0, 1.0], 40.0 * t_s), [0.5 * t_s, 1.0, -0.2 * t_s])


def adt_fixture(seq: Path, frames_ns: list[int], depth_mm: int | None = 2000) -> None:
    seq.mkdir(parents=True)
    (seq / "calibration.json").write_text(json.dumps(aria_calibration(), indent=2))
    rows = [TRAJ_HEADER]
    for t_us in range(1_000_000, 1_100_001, 1000):
        T = world_from_device(t_us * 1e-6)
        w, x, y, z = (float(c) for c in rot_to_quat(T[:3, :3]))
        tx, ty, tz = (float(c) for c in T[:3, 3])
        rows.append(
            f"uid,{t_us},{t_us * 1000 + 7},{tx!r},{ty!r},{tz!r},"
            f"{x!r},{y!r},{z!r},{w!r},0,0,0,0,0,0,0,0,-9.81,1.0"
        )
    (seq / "aria_trajectory.csv").write_text("\n".join(rows) + "\n")
    for t in frames_ns:
        write_png(seq / "camera-rgb" / f"{t}.png", 90, size=(AH, AW))
        if depth_mm is not None:
            write_png(
                seq / "depth" / "camera-rgb" / f"{t}.png",
                depth_mm,
                dtype=np.uint16,
                channels=1,
                size=(AH, AW),
            )


def test_aria_calibration(tmp_path):
    p = tmp_path / "calibration.json"
    p.write_text(json.dumps(aria_calibration(), indent=2))
    cam, T = read_aria_calibration(p, "camera-rgb", AW, AH)
    assert isinstance(cam, cameras.Fisheye624) and (cam.width, cam.height) == (AW, AH)
    v = cam.values
    assert v["fx"] == v["fy"] == 6.0 and (v["cx"], v["cy"]) == (7.6, 6.4)
    assert v["k0"] == 0.3 and v["k5"] == 0.0 and v["p0"] == 1e-4 and v["p1"] == -2e-4
    assert v["s0"] == 1e-4 and v["s2"] == -1e-4
    np.testing.assert_allclose(T, DEVICE_FROM_CAM, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"name": "KannalaBrandtK3"},
            r"calibration.json:\d+: .*'KannalaBrandtK3' is not supported",
        ),
        ({"params": ARIA_PARAMS[:14]}, r"Projection.Params: expected a list of 15 numbers"),
        ({"quat": [0.9, [0.0, 0.0, 0.0]]}, r"UnitQuaternion is not unit length"),
        ({"quat": [1.0, 0.0, 0.0, 0.0]}, r"UnitQuaternion must be \[w, \[x, y, z\]\]"),
    ],
)
def test_aria_calibration_errors(tmp_path, kwargs, match):
    p = tmp_path / "calibration.json"
    p.write_text(json.dumps(aria_calibration(**kwargs), indent=2))
    with pytest.raises(DatasetError, match=match):
        read_aria_calibration(p, "camera-rgb", AW, AH)


def test_aria_calibration_missing(tmp_path):
    p = tmp_path / "calibration.json"
    p.write_text(json.dumps(aria_calibration(), indent=2))
    with pytest.raises(DatasetError, match="no CameraCalibrations entry with Label 'camera-et'"):
        read_aria_calibration(p, "camera-et", AW, AH)
    p.write_text('{"CameraCalibrations": [\n  {"Label": "camera-rgb",}\n]}')
    with pytest.raises(DatasetError, match=r"calibration.json:2: invalid JSON"):
        read_aria_calibration(p, "camera-rgb", AW, AH)


def test_adt_reader(tmp_path):
    seq_dir = tmp_path / "Apartment_release_clean_seq131_M1292"
    # 1.0203 s and 1.05 s are between trajectory samples; 2.0 s is past the end (dropped).
    frames = [1_020_300_000, 1_050_000_000, 2_000_000_000]
    adt_fixture(seq_dir, frames)
    seq = load_adt(seq_dir)
    assert len(seq) == 2 and seq.meta["n_dropped"] == 1
    assert (seq.width, seq.height) == (AW, AH)  # from the first image
    np.testing.assert_allclose(seq.timestamps, [1.0203, 1.05])
    for k, t in enumerate([1.0203, 1.05]):
        expect = invert_pose(world_from_device(t) @ DEVICE_FROM_CAM)
        np.testing.assert_allclose(seq.cam_from_world[k], expect, atol=1e-9)
    np.testing.assert_allclose(seq.meta["T_device_camera"], DEVICE_FROM_CAM, atol=1e-12)
    # Planar z = 2 m everywhere -> range: X = range * ray has z = 2 wherever the ray is valid,
    # range = 2 on the optical axis and grows off axis.
    assert seq.depth_kind == "range" and seq.depth.shape == (2, AH, AW)
    rays, valid = seq.camera.ray_table()
    rz = rays[..., 2].numpy()
    ok = valid.numpy() & (seq.depth[0] > 0)
    assert ok.sum() > 0.8 * AW * AH
    np.testing.assert_allclose((seq.depth[0] * rz)[ok], 2.0, rtol=1e-5)
    axis_ray = np.array([[0.0, 0.0, 1.0]])
    import torch

    uv, _ = seq.camera.project(torch.tensor(axis_ray))
    u, v = (int(round(x)) for x in uv[0].tolist())
    assert seq.depth[0, v, u] == pytest.approx(2.0 / rz[v, u], rel=1e-5)
    assert seq.depth[0, 0, 0] > 2.2
    assert detect_kind(seq_dir) == "adt" and len(load_sequence(seq_dir)) == 2
    assert load_adt(seq_dir, depth=False).depth is None


def test_adt_reader_errors(tmp_path):
    a = tmp_path / "a"
    adt_fixture(a, [1_050_000_000])
    traj = (a / "aria_trajectory.csv").read_text().splitlines()
    bad = traj[:3] + [traj[2]] + traj[3:]  # a repeated timestamp on line 4
    (a / "aria_trajectory.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(DatasetError, match=r"aria_trajectory.csv:4: tracking_timestamp_us"):
        load_adt(a)
    (a / "aria_trajectory.csv").write_text(
        "\n".join([traj[0].replace("qw_world_device", "qw")] + traj[1:]) + "\n"
    )
    with pytest.raises(DatasetError, match=r"aria_trajectory.csv:1: missing column.*qw_world"):
        load_adt(a)
    b = tmp_path / "b"
    adt_fixture(b, [1_050_000_000], depth_mm=None)
    write_png(b / "depth" / "camera-rgb" / "1050000000.png", 200, channels=1, size=(AH, AW))
    with pytest.raises(DatasetError, match=r"1050000000.png: ADT depth must be 1-channel uint16"):
        load_adt(b)
    c = tmp_path / "c"
    adt_fixture(c, [1_050_000_000], depth_mm=None)
    write_png(c / "camera-rgb" / "frame.png", 1, size=(AH, AW))
    with pytest.raises(DatasetError, match=r"frame.png: image file name is not an integer"):
        load_adt(c)
    with pytest.raises(DatasetError, match="image folder not found"):
        load_adt(c, label="camera-slam-right")


# ------------------------------------------------------------------------------------------
# ScanNet++ per-frame masks
# ------------------------------------------------------------------------------------------


def add_masks(path: Path, scene: Path, skip: int | None = None, bad_size: int | None = None):
    d = json.loads(path.read_text())
    rng = np.random.default_rng(3)
    masks = {}
    for key in ("frames", "test_frames"):
        for fr in d[key]:
            stem = fr["file_path"].rsplit(".", 1)[0]
            if skip is not None and stem == f"DSC{skip:05d}":
                continue
            fr["mask_path"] = f"{stem}.png"
            size = (H, W + 1) if bad_size is not None and stem == f"DSC{bad_size:05d}" else (H, W)
            m = np.where(rng.random(size) < 0.7, 255, 0).astype(np.uint8)
            out = scene / "dslr" / "resized_anon_masks" / f"{stem}.png"
            out.parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(out), m)
            masks[fr["file_path"]] = m == 255
    path.write_text(json.dumps(d, indent=2))
    return masks


def test_scannetpp_masks(tmp_path):
    scene = tmp_path / "0a5c013435"
    path = scannetpp_fixture(scene, poses(5, seed=6))
    masks = add_masks(path, scene)
    seq = load_scannetpp_transforms(path)
    assert seq.mask is not None and seq.mask.shape == (len(seq), H, W)
    for i, fp in enumerate(seq.meta["per_frame"]["file_path"]):
        np.testing.assert_array_equal(seq.frame_mask(i), masks[fp])
    sub = seq.subset([1, 3])
    np.testing.assert_array_equal(sub.frame_mask(1), masks[seq.meta["per_frame"]["file_path"][3]])
    # Without mask_path the sequence has no mask (as before).
    assert load_scannetpp_transforms(scannetpp_fixture(tmp_path / "x", poses(5))).mask is None


def test_scannetpp_mask_errors(tmp_path):
    s1 = tmp_path / "s1"
    path = scannetpp_fixture(s1, poses(5, seed=6))
    add_masks(path, s1, skip=3)
    with pytest.raises(DatasetError, match="'DSC00003.JPG' has no mask_path"):
        load_scannetpp_transforms(path)
    s2 = tmp_path / "s2"
    path = scannetpp_fixture(s2, poses(5, seed=6))
    add_masks(path, s2, bad_size=1)
    with pytest.raises(DatasetError, match=r"DSC00001.png: mask is 13x10 px, camera is 12x10"):
        load_scannetpp_transforms(path)
    (s2 / "dslr" / "resized_anon_masks" / "DSC00001.png").unlink()
    with pytest.raises(DatasetError, match=r"DSC00001.png: mask file not found"):
        load_scannetpp_transforms(path)
    d = json.loads(path.read_text())
    d["frames"][0]["mask_path"] = 5
    path.write_text(json.dumps(d, indent=2))
    with pytest.raises(DatasetError, match=r"frames\[0\].mask_path must be a non-empty string"):
        load_scannetpp_transforms(path)
