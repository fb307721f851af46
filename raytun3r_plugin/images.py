"""Reading frames, scene masks and ground-truth depth maps at their native size.

Fitting them to the network input is :class:`raytun3r_plugin.preprocess.InputLayout`'s job (the
one preparation shared by adapt, infer and eval).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from raytun3r_plugin.errors import InputError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm"}


def read_frames(
    source: str | os.PathLike, stride: int = 1, limit: int | None = None
) -> tuple[np.ndarray, list[str]]:
    """Frames from an image folder (sorted by name) or a video file.

    Returns (N, H, W, 3) float32 RGB in [0, 1] and a name per frame.
    """
    import cv2

    source = Path(source)
    frames, names = [], []
    if source.is_dir():
        paths = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)[::stride]
        if limit is not None:
            paths = paths[:limit]
        if not paths:
            raise InputError(f"{source}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        for path in paths:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise InputError(f"{path}: not a readable image")
            frames.append(image)
            names.append(path.stem)
    elif source.suffix.lower() in VIDEO_SUFFIXES and source.is_file():
        capture = cv2.VideoCapture(str(source))
        index = 0
        while limit is None or len(frames) < limit:
            ok, image = capture.read()
            if not ok:
                break
            if index % stride == 0:
                frames.append(image)
                names.append(f"{index:06d}")
            index += 1
        capture.release()
        if not frames:
            raise InputError(f"{source}: no frames could be decoded")
    else:
        raise InputError(f"{source}: neither an image folder nor a video file")
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise InputError(f"{source}: frames have different sizes {sorted(shapes)}")
    rgb = np.stack([f[..., ::-1] for f in frames]).astype(np.float32) / 255.0
    return rgb, names


DEPTH_SUFFIXES = (".npy", ".png", ".tif", ".tiff", ".exr")


def read_depth_maps(
    folder: str | os.PathLike, names: list[str], width: int, height: int, png_scale: float = 1000.0
) -> np.ndarray:
    """Ground-truth depth for the frames ``names`` from a folder with one file per frame.

    The file of a frame has the frame's name (its stem) and one of :data:`DEPTH_SUFFIXES`:
    ``.npy`` float depth, or a 16-bit PNG / TIFF divided by ``png_scale`` (1000: millimetres,
    the convention of depth sensors and of KITTI-style projected LiDAR maps, which store 0
    where no point fell). 0, negative and NaN mean "no value", so sparse maps work as they are.

    Returns:
        (N, H, W) float32, one map per name, in the order of ``names``.

    Raises:
        InputError: a frame without a depth file, an unreadable file, or a map of another size.
    """
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of depth maps")
    files = {
        path.stem: path
        for path in sorted(folder.iterdir())
        if path.suffix.lower() in DEPTH_SUFFIXES
    }
    maps = []
    for name in names:
        path = files.get(name)
        if path is None:
            raise InputError(
                f"{folder}: no depth file for frame {name!r} (expected {name}.npy or {name}.png)"
            )
        if path.suffix.lower() == ".npy":
            depth = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            raw = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
            if raw is None:
                raise InputError(f"{path}: not a readable depth image")
            depth = raw.astype(np.float32) / (
                png_scale if raw.dtype in (np.uint16, np.uint8) else 1.0
            )
        if depth.shape != (height, width):
            raise InputError(
                f"{path}: depth map is {depth.shape[1] if depth.ndim > 1 else '?'}x{depth.shape[0]} px, the frames are {width}x{height}"
            )
        maps.append(depth)
    return np.stack(maps)


def read_mask(path: str | os.PathLike, width: int, height: int) -> np.ndarray:
    """A scene mask image: (H, W) bool, True where the pixel value is above 127 (255 = the scene
    is seen, 0 = excluded, e.g. the vehicle's body); the first channel of a colour image.

    Raises:
        InputError: unreadable file, or a size other than ``width`` x ``height``.
    """
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: mask file missing or unreadable")
    if image.ndim == 3:
        image = image[..., 0]
    if image.shape != (height, width):
        raise InputError(
            f"{path}: mask is {image.shape[1]}x{image.shape[0]} px, the frames are {width}x{height}"
        )
    return image > 127
