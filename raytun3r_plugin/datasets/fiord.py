"""FIORD scenes (Gunes et al. 2025, arXiv 2504.01732: 200-degree fisheye stills with SfM poses),
in the layout Wid3R's evaluation reads them.

The evidence is Wid3R's FIORD loader (``jdk9405/Wid3R`` at commit
29eb5f9293864038accce3a7b2b3c54c39fda4ff: ``evaluation/datasets/fiord_eval.py``,
``evaluation/configs/data/relpose-angular.yaml``,
``evaluation/datasets/seq-id-maps/fiord_relpose_seq-id-map.json``). What it shows::

    <FIORD>/<scene>/images_180/cam1/IMG_..._fisheye1.jpg    (or .png; scenes Kitchen_In,
                                                             meetingroom, parakennus)
    <FIORD>/<scene>/colmap/model/images.bin                 (COLMAP model; .txt also read)

the model's image NAMEs are relative to ``images_180`` (``cam1/<file>``), and its poses are
COLMAP's ``cam_from_world``, which Wid3R turns by 180 degrees about the optical axis
(``diag(-1, -1, 1)`` on the camera side) before pairing them with the ``images_180`` frames.
This reader does the same by default (``turn_180=True``) and records it in ``meta``.

What the evidence leaves open is refused rather than guessed: Wid3R evaluates FIORD without
intrinsics (its Fisheye624 parameters are all zero), so no calibration file or format is
verified: ``camera=`` must be given (a file :func:`raytun3r_plugin.cameras.load` reads, e.g. the
model's own ``cameras.txt`` if the user has checked it describes these frames, or a Camera). The
LiDAR ground truth is not read (no layout seen), nor any lens but the one named (default
``cam1``, the only one Wid3R uses).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from raytun3r_plugin.datasets._common import fail, load_camera
from raytun3r_plugin.datasets.colmap import read_images_bin, read_images_txt
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import DatasetError

__all__ = ["FIORD_SCENES_SEEN", "TURN_180", "is_fiord_scene", "load_fiord"]

#: The scenes Wid3R's FIORD pose evaluation lists (other FIORD scenes may exist; any folder in
#: the same layout is read).
FIORD_SCENES_SEEN = ("Kitchen_In", "meetingroom", "parakennus")
#: Wid3R's turn of the camera frame: 180 degrees about the optical axis.
TURN_180 = np.diag([-1.0, -1.0, 1.0, 1.0])
IMAGES = "images_180"
MODEL = Path("colmap") / "model"


def is_fiord_scene(folder: str | Path) -> bool:
    """True when ``folder`` has ``images_180/`` and ``colmap/model/images.bin`` (or ``.txt``)."""
    p = Path(folder)
    return (p / IMAGES).is_dir() and any(
        (p / MODEL / f"images.{ext}").is_file() for ext in ("bin", "txt")
    )


def _scene_folder(root: Path, scene: str | None) -> Path:
    if scene is not None:
        folder = root / scene
        if not is_fiord_scene(folder):
            raise fail(folder, None, f"not a FIORD scene (no {IMAGES}/ and {MODEL}/images.bin)")
        return folder
    if is_fiord_scene(root):
        return root
    scenes = (
        sorted(d.name for d in root.iterdir() if d.is_dir() and is_fiord_scene(d))
        if root.is_dir()
        else []
    )
    if len(scenes) == 1:
        return root / scenes[0]
    if scenes:
        raise fail(root, None, f"{len(scenes)} FIORD scenes {scenes}; pass scene=")
    raise fail(root, None, f"not a FIORD scene or root (no {IMAGES}/ and {MODEL}/images.bin)")


def load_fiord(
    root: str | Path,
    scene: str | None = None,
    *,
    camera: Any = None,
    lens: str = "cam1",
    turn_180: bool = True,
    name: str | None = None,
) -> Sequence:
    """Read one FIORD scene as a :class:`Sequence` (poses, images; no depth).

    Args:
        root: a scene folder (``images_180/`` + ``colmap/model/``) or the FIORD root holding
            scene folders (then ``scene=`` picks one, unless there is only one).
        scene: scene folder name under ``root`` (e.g. ``"meetingroom"``).
        camera: the calibration of the ``images_180`` frames: a camera file path (raytun3r JSON,
            COLMAP ``cameras.txt``, ...) or a Camera. Required: no FIORD calibration source
            could be verified (see the module docstring).
        lens: the sub-folder of ``images_180`` whose frames are read (the model NAME prefix).
        turn_180: turn each camera frame by 180 degrees about its optical axis, as Wid3R does
            with these poses and frames; False keeps the model's poses as stored.
        name: sequence name (default ``FIORD/<scene>/<lens>``).

    Frames are ordered by image NAME; timestamps are frame indices (COLMAP has no time).
    ``meta["per_frame"]`` holds ``image_id`` and ``name``.

    Raises:
        DatasetError: not this layout, no ``camera``, no frame of ``lens``, images of several
            COLMAP cameras, a listed image missing, frames of another size than the camera.
    """
    folder = _scene_folder(Path(root), scene)
    model = folder / MODEL
    binary = model / "images.bin"
    images = read_images_bin(binary) if binary.is_file() else read_images_txt(model / "images.txt")
    source = binary if binary.is_file() else model / "images.txt"
    if camera is None:
        raise DatasetError(
            f"{folder}: FIORD's calibration is not read (no file layout for it was verified; "
            "Wid3R evaluates FIORD without intrinsics); pass camera= a camera file of the "
            f"{IMAGES} frames (e.g. {model / 'cameras.txt'} once you have checked it) or a Camera"
        )
    if isinstance(camera, (str, Path)):
        camera = load_camera(camera)
    prefix = f"{lens}/"
    chosen = sorted(
        (im for im in images if im["name"].startswith(prefix)), key=lambda im: im["name"]
    )
    if not chosen:
        found = sorted({im["name"].split("/")[0] for im in images if "/" in im["name"]})
        raise fail(source, None, f"no image of lens {lens!r} (NAME prefixes found: {found})")
    cameras = sorted({im["camera_id"] for im in chosen})
    if len(cameras) > 1:
        raise fail(source, None, f"the {lens} images use several COLMAP cameras {cameras}")
    paths = [folder / IMAGES / im["name"] for im in chosen]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise fail(
            missing[0], None, f"image listed in {source.name} not found ({len(missing)} missing)"
        )
    _check_frame_size(paths[0], camera)
    poses = np.stack([im["cam_from_world"] for im in chosen])
    if turn_180:
        poses = TURN_180 @ poses
    return Sequence(
        name=name or f"FIORD/{folder.name}/{lens}",
        camera=camera,
        timestamps=np.arange(len(chosen), dtype=np.float64),
        cam_from_world=poses,
        image_paths=paths,
        meta={
            "source": str(source),
            "format": "fiord",
            "layout_evidence": "jdk9405/Wid3R@29eb5f9 evaluation/datasets/fiord_eval.py",
            "turn_180": bool(turn_180),
            "colmap_camera_id": cameras[0],
            "per_frame": {
                "image_id": np.array([im["image_id"] for im in chosen], dtype=np.int64),
                "name": np.array([im["name"] for im in chosen]),
            },
        },
    )


def _check_frame_size(path: Path, camera: Any) -> None:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise fail(path, None, "cannot decode image")
    height, width = image.shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise fail(
            path,
            None,
            f"frame is {width}x{height} px but the camera describes {camera.width}x{camera.height}",
        )
