"""Reading frames and fitting them, with their camera, to a network input size."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from raytun3r_plugin.errors import InputError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_SUFFIXES = {".mp4", ".mov", ".avi", ".mkv", ".webm"}


def read_frames(source: str | os.PathLike, stride: int = 1, limit: int | None = None) -> tuple[np.ndarray, list[str]]:
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


def read_depth_maps(folder: str | os.PathLike, names: list[str], width: int, height: int, png_scale: float = 1000.0) -> np.ndarray:
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
    files = {path.stem: path for path in sorted(folder.iterdir()) if path.suffix.lower() in DEPTH_SUFFIXES}
    maps = []
    for name in names:
        path = files.get(name)
        if path is None:
            raise InputError(f"{folder}: no depth file for frame {name!r} (expected {name}.npy or {name}.png)")
        if path.suffix.lower() == ".npy":
            depth = np.load(path, allow_pickle=False).astype(np.float32)
        else:
            raw = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH)
            if raw is None:
                raise InputError(f"{path}: not a readable depth image")
            depth = raw.astype(np.float32) / (png_scale if raw.dtype in (np.uint16, np.uint8) else 1.0)
        if depth.shape != (height, width):
            raise InputError(f"{path}: depth map is {depth.shape[1] if depth.ndim > 1 else '?'}x{depth.shape[0]} px, the frames are {width}x{height}")
        maps.append(depth)
    return np.stack(maps)


def network_size(width: int, height: int, long_side: int, patch: int = 14) -> tuple[int, int, int, int]:
    """Resized size (w, h) keeping the aspect ratio and the centred crop (w', h') to patch multiples."""
    scale = long_side / max(width, height)
    resized_w, resized_h = max(patch, round(width * scale)), max(patch, round(height * scale))
    return resized_w, resized_h, resized_w - resized_w % patch, resized_h - resized_h % patch


def _network_box(width: int, height: int, long_side: int, patch: int) -> tuple[int, int, int, int, int, int]:
    """(resized w, h, crop x0, y0, crop w, h) of :func:`fit_to_network`: one place for its geometry."""
    resized_w, resized_h, crop_w, crop_h = network_size(width, height, long_side, patch)
    return resized_w, resized_h, (resized_w - crop_w) // 2, (resized_h - crop_h) // 2, crop_w, crop_h


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
        raise InputError(f"{path}: mask is {image.shape[1]}x{image.shape[0]} px, the frames are {width}x{height}")
    return image > 127


def fit_mask_to_network(mask: np.ndarray, long_side: int = 504, patch: int = 14) -> torch.Tensor:
    """Resize and crop an (H, W) mask exactly as :func:`fit_to_network` does the frames
    (nearest neighbour, so it stays binary); returns (h, w) bool."""
    import cv2

    height, width = mask.shape
    resized_w, resized_h, x0, y0, crop_w, crop_h = _network_box(width, height, long_side, patch)
    resized = cv2.resize(mask.astype(np.uint8), (resized_w, resized_h), interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(np.ascontiguousarray(resized[y0 : y0 + crop_h, x0 : x0 + crop_w] > 0))


def fit_to_network(images: np.ndarray, camera, long_side: int = 504, patch: int = 14) -> tuple[torch.Tensor, object]:
    """Resize (N, H, W, 3) images so the long side is ``long_side``, centre-crop to patch multiples.

    Returns (1, N, 3, h, w) float32 in [0, 1] and the camera of exactly that input (scaled, then
    cropped: the crop is stated, so the camera stays exact).
    """
    import cv2

    if images.ndim != 4 or images.shape[-1] != 3:
        raise InputError(f"images must be (N, H, W, 3), got {images.shape}")
    height, width = images.shape[1:3]
    if (camera.width, camera.height) != (width, height):
        raise InputError(f"frames are {width}x{height} px but the camera describes {camera.width}x{camera.height} px")
    resized_w, resized_h, x0, y0, crop_w, crop_h = _network_box(width, height, long_side, patch)
    interpolation = cv2.INTER_AREA if resized_w < width else cv2.INTER_CUBIC
    resized = np.stack([cv2.resize(image, (resized_w, resized_h), interpolation=interpolation) for image in images])
    cropped = np.clip(resized[:, y0 : y0 + crop_h, x0 : x0 + crop_w], 0.0, 1.0)
    camera = camera.resized(resized_w, resized_h)
    if (crop_w, crop_h) != (resized_w, resized_h):
        camera = camera.cropped(x0, y0, crop_w, crop_h)
    tensor = torch.from_numpy(np.ascontiguousarray(cropped)).permute(0, 3, 1, 2)[None].float()
    return tensor, camera
