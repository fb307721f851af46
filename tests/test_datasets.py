"""Dataset readers on tiny fixtures written in each format (well-formed and malformed)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from raytun3r_plugin import cameras
from raytun3r_plugin.datasets import (
    Sequence,
    detect_kind,
    load_colmap,
    load_kitti360,
    load_scannetpp_transforms,
    load_sequence,
    load_synthetic,
    load_tumvi,
    read_image,
    write_sequence,
)
from raytun3r_plugin.datasets._common import invert_pose, quat_to_rot, rot_to_quat, slerp
from raytun3r_plugin.errors import DatasetError, Raytun3rError
from tests.calibration_files import KITTI360_IMAGE_02

W, H = 12, 10


def rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack(
        [rigid(rot(rng.normal(size=3), rng.uniform(0, 170)), rng.normal(size=3)) for _ in range(n)]
    )


def write_png(path: Path, value: int, dtype=np.uint8, channels: int = 3, size=(H, W)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    shape = size if channels == 1 else (*size, channels)
    img = np.full(shape, value, dtype=dtype)
    if channels == 3:
        img[..., 0] = 0  # blue channel 0 in BGR -> last channel 0 in RGB
    assert cv2.imwrite(str(path), img)


def raises_at(exc_info, name: str, line: int | None = None) -> None:
    msg = str(exc_info.value)
    assert name in msg, msg
    if line is not None:
        assert f"{name}:{line}:" in msg, msg


# ------------------------------------------------------------------------------------------
# Sequence and helpers
# ------------------------------------------------------------------------------------------


def test_pose_helpers():
    rng = np.random.default_rng(2)
    for _ in range(50):
        R = rot(rng.normal(size=3), rng.uniform(0, 180))
        q = rot_to_quat(R)
        assert q[0] >= 0 and np.allclose(quat_to_rot(q), R, atol=1e-12)
    T = poses(3)
    assert np.allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)
    q0 = rot_to_quat(np.eye(3))[None]
    q1 = rot_to_quat(rot([0, 0, 1], 90.0))[None]
    mid = quat_to_rot(slerp(q0, q1, np.array([0.5])))[0]
    assert np.allclose(mid, rot([0, 0, 1], 45.0), atol=1e-12)


def test_read_image_formats(tmp_path):
    write_png(tmp_path / "a.png", 255)
    img = read_image(tmp_path / "a.png")
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    assert np.allclose(img[0, 0], [1.0, 1.0, 0.0])  # BGR on disk -> RGB in memory
    write_png(tmp_path / "g16.png", 65535 // 2, dtype=np.uint16, channels=1)
    g = read_image(tmp_path / "g16.png")
    assert g.shape == (H, W, 3) and np.allclose(g, (65535 // 2) / 65535.0)
    with pytest.raises(DatasetError, match="not found"):
        read_image(tmp_path / "none.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="cannot decode"):
        read_image(tmp_path / "bad.png")


def test_sequence_basics(tmp_path):
    cam = cameras.Pinhole(W, H, {"fx": 10.0, "fy": 10.0, "cx": 5.5, "cy": 4.5})
    imgs = np.random.default_rng(0).uniform(size=(4, H, W, 3)).astype(np.float32)
    seq = Sequence(
        "s",
        cam,
        np.arange(4) * 0.1,
        poses(4),
        images=imgs,
        depth=np.ones((4, H, W), np.float32),
        mask=np.ones((H, W), bool),
        meta={"per_frame": {"id": np.arange(4)}, "other": 1},
    )
    assert len(seq) == 4 and seq.height == H and seq.width == W
    assert np.array_equal(seq.image(-1), imgs[3])
    sub = seq.subset([3, 1])
    assert len(sub) == 2 and np.array_equal(sub.cam_from_world, seq.cam_from_world[[3, 1]])
    assert sub.meta["per_frame"]["id"].tolist() == [3, 1] and sub.meta["other"] == 1
    assert sub.mask.shape == (H, W) and np.array_equal(sub.images[0], imgs[3])
    assert (
        len(seq.subset(slice(0, 4, 2))) == 2
        and len(seq.subset(np.array([True, False, True, True]))) == 3
    )
    with pytest.raises(IndexError):
        seq.image(4)
    # an adaptation segment: the first frames, as a copy
    head = seq.first_images(3)
    assert head.shape == (3, H, W, 3) and np.array_equal(head, imgs[:3])
    head[0] = 0.0
    assert np.array_equal(seq.images, imgs) and not np.array_equal(head, imgs[:3])
    for count in (0, 5):
        with pytest.raises(IndexError, match=f"{count} frames"):
            seq.first_images(count)
    with pytest.raises(DatasetError):
        Sequence("bad", cam, np.arange(3), poses(2))
    with pytest.raises(DatasetError):
        Sequence("bad", cam, np.arange(2), None, depth_kind="disparity")
    # lazy images and the size check
    write_png(tmp_path / "ok.png", 10)
    write_png(tmp_path / "big.png", 10, size=(H + 1, W))
    lazy = Sequence(
        "lazy", cam, [0.0, 1.0], None, image_paths=[tmp_path / "ok.png", tmp_path / "big.png"]
    )
    assert lazy.image(0).shape == (H, W, 3) and lazy.first_images(1).shape == (1, H, W, 3)
    with pytest.raises(DatasetError, match="big.png"):
        lazy.image(1)
    # z-depth to range
    zseq = Sequence(
        "z", cam, [0.0], None, depth=np.full((1, H, W), 2.0, np.float32), depth_kind="z"
    )
    rays = cam.ray_table()[0].numpy()
    assert np.allclose(zseq.range_depth(0), 2.0 / rays[..., 2], rtol=1e-6)
    assert issubclass(DatasetError, Raytun3rError)


def test_synthetic_folder_malformed(tmp_path):
    cam = cameras.Pinhole(W, H, {"fx": 10.0, "fy": 10.0, "cx": 5.5, "cy": 4.5})
    seq = Sequence(
        "f",
        cam,
        [0.0, 0.5],
        poses(2),
        images=np.zeros((2, H, W, 3), np.float32),
        depth=np.ones((2, H, W), np.float32),
        mask=np.ones((2, H, W), bool),
    )
    folder = write_sequence(seq, tmp_path / "f")
    back = load_sequence(folder)
    assert np.array_equal(back.cam_from_world, seq.cam_from_world) and back.mask.shape == (2, H, W)
    text = (folder / "poses.txt").read_text().splitlines()
    text[2] = text[2].replace(text[2].split()[5], "abc")
    (folder / "poses.txt").write_text("\n".join(text) + "\n")
    with pytest.raises(DatasetError) as e:
        load_synthetic(folder)
    raises_at(e, "poses.txt", 3)
    (folder / "meta.json").write_text(
        '{"format": "raytun3r-sequence",\n "format_version": 1,\n "n_frames": 2 2}'
    )
    with pytest.raises(DatasetError) as e:
        load_synthetic(folder)
    raises_at(e, "meta.json", 3)
    with pytest.raises(DatasetError, match="meta.json"):
        load_synthetic(tmp_path / "nothing")


# ------------------------------------------------------------------------------------------
# COLMAP (ETH3D / ScanNet++ DSLR)
# ------------------------------------------------------------------------------------------


def colmap_fixture(root: Path, T: np.ndarray, names: list[str], cam_ids=None) -> None:
    root.mkdir(parents=True, exist_ok=True)
    (root / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 OPENCV_FISHEYE {W} {H} 9.5 9.75 6.0 5.0 0.01 -0.002 0.0003 0.0\n"
        f"2 PINHOLE {W} {H} 20 20 6 5\n"
    )
    cam_ids = cam_ids or [1] * len(names)
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
    ]
    for k, (Tk, nm) in enumerate(zip(T, names, strict=True)):
        q = rot_to_quat(Tk[:3, :3])
        vals = " ".join(repr(float(x)) for x in [*q, *Tk[:3, 3]])
        lines.append(f"{10 + k} {vals} {cam_ids[k]} {nm}")
        lines.append("1.5 2.5 -1 3.0 4.0 7" if k % 2 else "")
    (root / "images.txt").write_text("\n".join(lines) + "\n")


def test_colmap_reader(tmp_path):
    scene = tmp_path / "courtyard"
    T = poses(3, seed=4)
    names = ["dslr_images/DSC_0003.JPG", "dslr_images/DSC_0001.JPG", "dslr_images/DSC_0002.JPG"]
    colmap_fixture(scene / "dslr_calibration_jpg", T, names)
    for nm in names:
        write_png(scene / "images" / nm, 50)  # PNG bytes under a .JPG name decode fine
    seq = load_colmap(scene)
    assert seq.name == "courtyard" and len(seq) == 3
    order = [1, 2, 0]  # sorted by NAME
    np.testing.assert_allclose(seq.cam_from_world, T[order], atol=1e-12)
    assert [p.name for p in seq.image_paths] == ["DSC_0001.JPG", "DSC_0002.JPG", "DSC_0003.JPG"]
    assert seq.meta["per_frame"]["image_id"].tolist() == [11, 12, 10]
    v = seq.camera.values
    assert isinstance(seq.camera, cameras.KannalaBrandt4)
    assert v["cx"] == pytest.approx(5.5) and v["cy"] == pytest.approx(4.5) and v["fy"] == 9.75
    assert seq.image(0).shape == (H, W, 3)
    assert detect_kind(scene) == "colmap" and len(load_sequence(scene)) == 3


def test_colmap_reader_errors(tmp_path):
    T = poses(2, seed=5)
    root = tmp_path / "m"
    colmap_fixture(root, T, ["a.png", "b.png"], cam_ids=[1, 2])
    write_png(root / "images" / "a.png", 1)
    write_png(root / "images" / "b.png", 1)
    with pytest.raises(DatasetError, match="several cameras"):
        load_colmap(root)
    assert isinstance(load_colmap(root, camera_id=2).camera, cameras.Pinhole)
    lines = (root / "images.txt").read_text().splitlines()
    bad = lines.copy()
    bad[4] = bad[4].replace(bad[4].split()[3], "x1y", 1)  # second image line, a quaternion entry
    (root / "images.txt").write_text("\n".join(bad) + "\n")
    with pytest.raises(DatasetError) as e:
        load_colmap(root, camera_id=1)
    raises_at(e, "images.txt", 5)
    bad = lines.copy()
    bad[2] = "10 0 0 0 0 0 0 0 1 a.png"
    (root / "images.txt").write_text("\n".join(bad) + "\n")
    with pytest.raises(DatasetError) as e:
        load_colmap(root, camera_id=1)
    raises_at(e, "images.txt", 3)
    assert "zero" in str(e.value)
    bad = lines.copy()
    bad[5] = "1.0 2.0"  # POINTS2D line that is not triples
    (root / "images.txt").write_text("\n".join(bad) + "\n")
    with pytest.raises(DatasetError) as e:
        load_colmap(root, camera_id=2)
    raises_at(e, "images.txt", 6)
    (root / "images.txt").write_text("\n".join(lines) + "\n")
    (root / "cameras.txt").write_text(
        f"1 OPENCV_FISHEYE {W} {H} 9.5 9.75 6.0\n2 PINHOLE {W} {H} 20 20 6 5\n"
    )
    with pytest.raises(DatasetError) as e:
        load_colmap(root, camera_id=1)
    assert "cameras.txt" in str(e.value) and "line 1" in str(e.value)
    (root / "images").rename(root / "elsewhere")
    with pytest.raises(DatasetError, match="not found"):
        load_colmap(root, camera_id=2)
    assert len(load_colmap(root, camera_id=2, image_dir=root / "elsewhere")) == 1


# ------------------------------------------------------------------------------------------
# ScanNet++ nerfstudio transforms.json
# ------------------------------------------------------------------------------------------


def scannetpp_fixture(
    scene: Path, world_from_cam: np.ndarray, bad_index: int | None = None
) -> Path:
    ns = scene / "dslr" / "nerfstudio"
    ns.mkdir(parents=True, exist_ok=True)
    gl = world_from_cam @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [
        {"file_path": f"DSC{k:05d}.JPG", "transform_matrix": gl[k].tolist(), "is_bad": False}
        for k in range(len(gl))
    ]
    frames[2]["is_bad"] = True
    if bad_index is not None:
        frames[bad_index]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    d = {
        "camera_model": "OPENCV_FISHEYE",
        "fl_x": 9.0,
        "fl_y": 9.5,
        "cx": 6.25,
        "cy": 5.0,
        "w": W,
        "h": H,
        "k1": -0.03,
        "k2": -0.006,
        "k3": -0.002,
        "k4": 0.0001,
        "frames": frames[:3],
        "test_frames": frames[3:],
    }
    path = ns / "transforms.json"
    path.write_text(json.dumps(d, indent=2))
    for k in range(len(gl)):
        write_png(scene / "dslr" / "resized_images" / f"DSC{k:05d}.JPG", 30 + k)
    return path


def test_scannetpp_reader(tmp_path):
    wfc = poses(5, seed=6)
    path = scannetpp_fixture(tmp_path / "0a5c013435", wfc)
    seq = load_scannetpp_transforms(path)
    assert seq.name == "0a5c013435"
    keep = [0, 1, 3, 4]  # frame 2 is_bad
    assert len(seq) == 4 and seq.meta["per_frame"]["is_test"].tolist() == [False, False, True, True]
    np.testing.assert_allclose(seq.cam_from_world, np.linalg.inv(wfc[keep]), atol=1e-12)
    v = seq.camera.values
    assert isinstance(seq.camera, cameras.KannalaBrandt4)
    assert (v["fx"], v["fy"], v["cx"], v["cy"], v["k4"]) == (9.0, 9.5, 5.75, 4.5, 0.0001)
    assert seq.image(3)[0, 0, 1] == pytest.approx((30 + 4) / 255)
    assert len(load_scannetpp_transforms(path, split="train")) == 2
    assert len(load_scannetpp_transforms(path, split="test")) == 2
    assert len(load_scannetpp_transforms(path, skip_bad=False)) == 5
    assert detect_kind(tmp_path / "0a5c013435" / "dslr") == "scannetpp"
    assert len(load_sequence(tmp_path / "0a5c013435" / "dslr")) == 4


def test_scannetpp_reader_errors(tmp_path):
    path = scannetpp_fixture(tmp_path / "s", poses(5, seed=7), bad_index=3)
    with pytest.raises(DatasetError) as e:
        load_scannetpp_transforms(path)
    text = path.read_text().splitlines()
    line = next(i for i, ln in enumerate(text, 1) if '"DSC00003.JPG"' in ln)
    raises_at(e, "transforms.json", line)
    assert "test_frames[0].transform_matrix" in str(e.value)
    path.write_text(path.read_text().replace('"fl_y": 9.5', '"fl_y": "x"'))
    with pytest.raises(DatasetError, match="fl_y"):
        load_scannetpp_transforms(path)
    path.write_text('{\n "w": 12,\n "h": 10,,\n}')
    with pytest.raises(DatasetError) as e:
        load_scannetpp_transforms(path)
    raises_at(e, "transforms.json", 3)


# ------------------------------------------------------------------------------------------
# TUM-VI (ASL / EuRoC layout)
# ------------------------------------------------------------------------------------------

T_CAM_IMU = rigid(rot([0.2, 1.0, -0.3], 100.0), [0.05, -0.01, 0.02])
W_RATE = np.array([0.3, -0.5, 0.8])  # rad/s, constant (slerp is exact for it)
V = np.array([0.4, 0.1, -0.2])  # m/s, constant (linear interpolation is exact)
T0 = 1_520_530_308_000_000_000


def world_from_imu(t_ns: int) -> np.ndarray:
    s = (t_ns - T0) * 1e-9
    ang = np.linalg.norm(W_RATE) * s
    return rigid(
        rot(W_RATE, math.degrees(ang)) @ rot([1, 0, 0], 30.0), np.array([1.0, 2.0, 0.5]) + V * s
    )


def tumvi_fixture(root: Path, bad_line: str | None = None) -> list[int]:
    mav = root / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    (mav / "mocap0").mkdir(parents=True)
    cc = {
        "cam0": {
            "T_cam_imu": T_CAM_IMU.tolist(),
            "cam_overlaps": [1],
            "camera_model": "pinhole",
            "distortion_coeffs": [0.0035, 0.0007, -0.002, 0.0002],
            "distortion_model": "equidistant",
            "intrinsics": [4.5, 4.5, 5.9, 4.8],
            "resolution": [W, H],
            "rostopic": "/cam0/image_raw",
        }
    }
    import yaml

    (root / "camchain.yaml").write_text(yaml.safe_dump(cc, sort_keys=False))
    mocap = [T0 + k * 10_000_000 for k in range(40)]  # 100 Hz over 0.4 s
    mocap = [t for t in mocap if not (200_000_000 <= t - T0 <= 330_000_000)]  # a gap
    rows = [
        "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    ]
    for t in mocap:
        Twi = world_from_imu(t)
        q = rot_to_quat(Twi[:3, :3])
        rows.append(f"{t}," + ",".join(repr(float(x)) for x in [*Twi[:3, 3], *q]))
    if bad_line is not None:
        rows[3] = bad_line
    (mav / "mocap0" / "data.csv").write_text("\n".join(rows) + "\n")
    images = [T0 + 3_000_000 + k * 50_000_000 for k in range(8)]  # 20 Hz, offset 3 ms
    rows = ["#timestamp [ns],filename"] + [f"{t},{t}.png" for t in images]
    (mav / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    for t in images:
        write_png(mav / "cam0" / "data" / f"{t}.png", 40000, dtype=np.uint16, channels=1)
    return images


def test_tumvi_reader(tmp_path):
    root = tmp_path / "dataset-room1_512_16"
    images = tumvi_fixture(root)
    seq = load_tumvi(root)
    # images at 0.203, 0.253, 0.303 s have no mocap within 10 ms (gap 0.2..0.33 s)
    kept = [t for t in images if not (0.2e9 < t - T0 < 0.31e9)]
    assert seq.meta["per_frame"]["timestamp_ns"].tolist() == kept and seq.meta["n_dropped"] == len(
        images
    ) - len(kept)
    np.testing.assert_allclose(seq.timestamps, np.array(kept) * 1e-9)
    expect = np.stack([T_CAM_IMU @ np.linalg.inv(world_from_imu(t)) for t in kept])
    np.testing.assert_allclose(seq.cam_from_world, expect, atol=1e-9)
    assert isinstance(seq.camera, cameras.KannalaBrandt4) and seq.camera.values["cx"] == 5.9
    img = seq.image(0)
    assert img.shape == (H, W, 3) and np.allclose(img, 40000 / 65535)
    assert detect_kind(root) == "tumvi" and len(load_sequence(root)) == len(kept)


def test_tumvi_reader_errors(tmp_path):
    root = tmp_path / "t"
    tumvi_fixture(root, bad_line="1520530308020000000,1.0,2.0,zz,1,0,0,0")
    with pytest.raises(DatasetError) as e:
        load_tumvi(root)
    raises_at(e, "data.csv", 4)
    assert "mocap0" in str(e.value)
    root2 = tmp_path / "t2"
    tumvi_fixture(root2, bad_line="1520530308020000000,1.0,2.0")
    with pytest.raises(DatasetError) as e:
        load_tumvi(root2)
    raises_at(e, "data.csv", 4)
    with pytest.raises(DatasetError, match="cam7"):
        load_tumvi(root2, cam="cam7")
    with pytest.raises(DatasetError, match="camchain"):
        load_tumvi(tmp_path)


# ------------------------------------------------------------------------------------------
# KITTI-360
# ------------------------------------------------------------------------------------------


def mei_yaml(size: int = 28) -> str:
    """KITTI-360's image_02 calibration (tests/calibration_files.py) for ``size`` x ``size``
    frames: the image size and the projection parameters scaled from its 1400 px."""
    factor = size / 1400
    text = KITTI360_IMAGE_02.replace("1400\n", f"{size}\n")
    for key in ("gamma1", "gamma2", "u0", "v0"):
        text = re.sub(
            rf"({key}: )(\S+)", lambda m: f"{m.group(1)}{float(m.group(2)) * factor!r}", text
        )
    return text


SEQ = "2013_05_28_drive_0007_sync"


def kitti_fixture(
    root: Path, pose_rows: dict[int, np.ndarray], c2p: np.ndarray, n_images: int = 6
) -> None:
    (root / "calibration").mkdir(parents=True)
    (root / "calibration" / "image_02.yaml").write_text(mei_yaml())
    lines = []
    for k in range(4):
        T = c2p if k == 2 else rigid(rot([0, 0, 1], 10.0 * k), [k, 0, 0])
        lines.append(f"image_0{k}: " + " ".join(repr(float(x)) for x in T[:3].reshape(-1)))
    (root / "calibration" / "calib_cam_to_pose.txt").write_text("\n".join(lines) + "\n")
    (root / "data_poses" / SEQ).mkdir(parents=True)
    rows = [
        f"{f} " + " ".join(repr(float(x)) for x in T[:3].reshape(-1))
        for f, T in sorted(pose_rows.items())
    ]
    (root / "data_poses" / SEQ / "poses.txt").write_text("\n".join(rows) + "\n")
    cam_dir = root / "data_2d_raw" / SEQ / "image_02"
    for f in range(n_images):
        write_png(cam_dir / "data_rgb" / f"{f:010d}.png", 20 + f, size=(28, 28))
    stamps = [
        f"2013-05-28 08:46:02.{100000000 * f + 879058484 % 100000000:09d}" for f in range(n_images)
    ]
    (cam_dir / "timestamps.txt").write_text("\n".join(stamps) + "\n")


def test_kitti360_reader(tmp_path):
    root = tmp_path / "KITTI-360"
    P = poses(8, seed=9)
    pose_rows = {1: P[1], 2: P[2], 4: P[4], 7: P[7]}  # frame 7 has no image
    c2p = rigid(rot([0, 1, 0], 90.0), [0.8, 0.3, -0.1])
    kitti_fixture(root, pose_rows, c2p)
    seq = load_kitti360(root, SEQ)
    assert seq.meta["per_frame"]["frame"].tolist() == [1, 2, 4]
    expect = np.stack([np.linalg.inv(P[f] @ c2p) for f in (1, 2, 4)])
    np.testing.assert_allclose(seq.cam_from_world, expect, atol=1e-12)
    assert isinstance(seq.camera, cameras.MEI) and seq.camera.width == 28
    np.testing.assert_allclose(np.diff(seq.timestamps), [0.1, 0.2], atol=1e-6)
    assert seq.image(2)[0, 0, 1] == pytest.approx(24 / 255)
    assert seq.name == f"{SEQ}/image_02"
    assert len(load_kitti360(root, 7)) == 3  # sequence by number
    assert detect_kind(root) == "kitti360" and len(load_sequence(root)) == 3


def test_kitti360_reader_errors(tmp_path):
    root = tmp_path / "K"
    P = poses(3, seed=10)
    kitti_fixture(root, {0: P[0], 1: P[1], 2: P[2]}, np.eye(4))
    ppath = root / "data_poses" / SEQ / "poses.txt"
    lines = ppath.read_text().splitlines()
    lines[1] = lines[1].rsplit(" ", 1)[0]  # 12 fields instead of 13
    ppath.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as e:
        load_kitti360(root, SEQ)
    raises_at(e, "poses.txt", 2)
    lines[1] = "1 " + " ".join(["2.0"] * 12)  # not a rotation
    ppath.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as e:
        load_kitti360(root, SEQ)
    raises_at(e, "poses.txt", 2)
    ppath.write_text("\n".join([lines[0]]) + "\n")
    with pytest.raises(DatasetError, match="image_03"):
        load_kitti360(root, SEQ, camera="image_03")
    c2p = root / "calibration" / "calib_cam_to_pose.txt"
    good = c2p.read_text()
    c2p.write_text(good.replace("image_01:", "image_01 "))
    with pytest.raises(DatasetError) as e:
        load_kitti360(root, SEQ)
    raises_at(e, "calib_cam_to_pose.txt", 2)
    c2p.write_text(good)
    with pytest.raises(DatasetError, match="poses.txt"):
        load_kitti360(root, "2013_05_28_drive_0099_sync")


def test_detect_kind_unknown(tmp_path):
    with pytest.raises(DatasetError, match="cannot tell"):
        detect_kind(tmp_path)
    with pytest.raises(ValueError):
        load_sequence(tmp_path, kind="nope")
