"""The FIORD reader on fixtures written here in the layout Wid3R's loader reads
(``jdk9405/Wid3R@29eb5f9``: ``<scene>/images_180/cam1/*.png``, ``<scene>/colmap/model/images.bin``)."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from raytun3r_plugin import cameras
from raytun3r_plugin.datasets import detect_kind, load_fiord, load_sequence, read_images_bin
from raytun3r_plugin.errors import DatasetError
from raytun3r_plugin.poses import rotation_to_quaternion
from tests.helpers import fisheye

WIDTH, HEIGHT = 64, 48


def _random_poses(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    for pose in poses:
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        pose[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
        pose[:3, 3] = rng.normal(size=3)
    return poses


def _pack_images_bin(records: list[tuple[int, np.ndarray, int, str, int]]) -> bytes:
    """COLMAP's images.bin for (image_id, cam_from_world, camera_id, name, points) records."""
    out = struct.pack("<Q", len(records))
    for image_id, pose, camera_id, name, points in records:
        q = rotation_to_quaternion(pose[:3, :3])
        out += struct.pack("<i7di", image_id, *q, *pose[:3, 3], camera_id)
        out += name.encode() + b"\0" + struct.pack("<Q", points)
        out += b"".join(struct.pack("<ddq", 1.5 * k, 2.5, k) for k in range(points))
    return out


def _scene(root, name: str, poses: np.ndarray, *, camera_ids=None, lens="cam1"):
    """A FIORD scene: frames (written in shuffled id order) and the COLMAP model's images.bin."""
    folder = root / name
    (folder / "images_180" / lens).mkdir(parents=True)
    (folder / "colmap" / "model").mkdir(parents=True)
    names = [
        f"{lens}/IMG_20241120_000613_00_{700 + 7 * k:03d}_fisheye1.png" for k in range(len(poses))
    ]
    for k, image_name in enumerate(names):
        image = np.full((HEIGHT, WIDTH, 3), 20 * k, np.uint8)
        cv2.imwrite(str(folder / "images_180" / image_name), image)
    order = np.random.default_rng(1).permutation(len(poses))  # ids not in name order
    records = [
        (int(10 + j), poses[k], (camera_ids or [1] * len(poses))[k], names[k], k % 3)
        for j, k in enumerate(order)
    ]
    (folder / "colmap" / "model" / "images.bin").write_bytes(_pack_images_bin(records))
    return folder, names


@pytest.fixture
def fiord(tmp_path):
    camera = fisheye(WIDTH, HEIGHT, 200.0)
    cameras.save(camera, tmp_path / "camera.json")
    poses = _random_poses(5, seed=0)
    folder, names = _scene(tmp_path / "FIORD", "meetingroom", poses)
    return {
        "root": tmp_path / "FIORD",
        "scene": folder,
        "names": names,
        "poses": poses,
        "camera_file": tmp_path / "camera.json",
        "camera": camera,
    }


def test_scene_reads_frames_in_name_order_with_wid3r_turned_poses(fiord):
    seq = load_fiord(fiord["root"], "meetingroom", camera=fiord["camera_file"])
    assert [
        p.relative_to(fiord["scene"] / "images_180").as_posix() for p in seq.image_paths
    ] == fiord["names"]
    # Wid3R: pose = inv(inv(cam_from_world) @ diag(-1, -1, 1, 1)), computed here literally.
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    expected = np.stack([np.linalg.inv(np.linalg.inv(p) @ flip) for p in fiord["poses"]])
    np.testing.assert_allclose(seq.cam_from_world, expected, atol=1e-12)
    assert seq.camera.to_json() == fiord["camera"].to_json() and len(seq) == 5
    np.testing.assert_array_equal(seq.timestamps, np.arange(5.0))
    assert seq.meta["turn_180"] and seq.meta["format"] == "fiord"
    assert float(seq.image(3)[0, 0, 0]) == pytest.approx(60 / 255)
    stored = load_fiord(fiord["scene"], camera=fiord["camera"], turn_180=False)
    np.testing.assert_allclose(stored.cam_from_world, fiord["poses"], atol=1e-12)
    # Registered with the other readers.
    assert detect_kind(fiord["scene"]) == "fiord"
    again = load_sequence(fiord["scene"], camera=fiord["camera_file"])
    np.testing.assert_allclose(again.cam_from_world, expected, atol=1e-12)


def test_what_cannot_be_verified_or_is_broken_is_refused(fiord, tmp_path):
    with pytest.raises(DatasetError, match="camera="):
        load_fiord(fiord["scene"])  # no verified calibration source
    with pytest.raises(DatasetError, match=r"lens 'cam2'.*\['cam1'\]"):
        load_fiord(fiord["scene"], camera=fiord["camera"], lens="cam2")
    with pytest.raises(DatasetError, match="describes 80x48"):
        load_fiord(fiord["scene"], camera=fisheye(80, HEIGHT, 200.0))
    _scene(fiord["root"], "Kitchen_In", _random_poses(3, seed=2))
    with pytest.raises(DatasetError, match=r"2 FIORD scenes \['Kitchen_In', 'meetingroom'\]"):
        load_fiord(fiord["root"], camera=fiord["camera"])
    mixed, _ = _scene(tmp_path, "parakennus", _random_poses(3, seed=3), camera_ids=[1, 2, 1])
    with pytest.raises(DatasetError, match="several COLMAP cameras"):
        load_fiord(mixed, camera=fiord["camera"])
    missing = fiord["scene"] / "images_180" / fiord["names"][2]
    missing.unlink()
    with pytest.raises(DatasetError, match="not found"):
        load_fiord(fiord["scene"], camera=fiord["camera"])
    model = fiord["scene"] / "colmap" / "model" / "images.bin"
    model.write_bytes(model.read_bytes()[:-5])
    with pytest.raises(DatasetError, match="truncated"):
        read_images_bin(model)
    with pytest.raises(DatasetError, match="not a FIORD scene"):
        load_fiord(tmp_path / "nowhere", camera=fiord["camera"])


def test_images_bin_reads_what_pycolmap_writes(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="OPENCV_FISHEYE",
        width=WIDTH,
        height=HEIGHT,
        params=[20, 20, 32, 24, 0, 0, 0, 0],
        camera_id=1,
    )
    reconstruction.add_camera(camera)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(camera.sensor_id)
    reconstruction.add_rig(rig)
    poses = _random_poses(4, seed=4)
    for k, pose in enumerate(poses):
        frame = pycolmap.Frame()
        frame.frame_id, frame.rig_id = k + 1, 1
        w, x, y, z = rotation_to_quaternion(pose[:3, :3])
        frame.rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([x, y, z, w])), pose[:3, 3]
        )
        image = pycolmap.Image(name=f"cam1/{k:03d}.png", camera_id=1, image_id=k + 1)
        frame.add_data_id(image.data_id)
        reconstruction.add_frame(frame)
        image.frame_id = k + 1
        reconstruction.add_image(image)
    reconstruction.write_binary(str(tmp_path))
    records = read_images_bin(tmp_path / "images.bin")
    assert [r["name"] for r in records] == [f"cam1/{k:03d}.png" for k in range(4)]
    for record in records:
        written = reconstruction.images[record["image_id"]].cam_from_world().matrix()
        np.testing.assert_allclose(record["cam_from_world"][:3], written, atol=1e-12)
