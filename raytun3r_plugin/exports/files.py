"""Plain files of a prediction: depth pictures (input | depth | colour bar), TUM trajectories and
coloured PLY point clouds."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from raytun3r_plugin.atomic_files import atomic_write_bytes, atomic_write_text
from raytun3r_plugin.poses import invert_rigid, rotation_to_quaternion


def colourise_depth(
    depth: np.ndarray,
    valid: np.ndarray | None = None,
    inverse_range: tuple[float, float] | None = None,
) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) uint8 BGR (OpenCV turbo map on inverse depth, 2-98% range of
    the valid pixels unless ``inverse_range`` = (low, high) inverse depth is given)."""
    import cv2

    valid = (
        np.isfinite(depth) & (depth > 0)
        if valid is None
        else valid & np.isfinite(depth) & (depth > 0)
    )
    inverse = np.zeros_like(depth, dtype=np.float32)
    inverse[valid] = 1.0 / depth[valid]
    if valid.any():
        low, high = inverse_range or _inverse_range(depth, valid)
        inverse = np.clip((inverse - low) / (high - low), 0, 1)
    image = cv2.applyColorMap((inverse * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[~valid] = 0
    return image


def _inverse_range(depth: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """The 2-98% range of inverse depth that :func:`colourise_depth` maps to the colour map."""
    if not valid.any():
        return 0.0, 1.0
    low, high = np.percentile(1.0 / depth[valid], [2, 98])
    return float(low), float(max(high, low + 1e-12))


def _nice_ticks(near: float, far: float, count: int = 5) -> list[float]:
    """About ``count`` round depth values between ``near`` and ``far`` (both ends included)."""
    if not np.isfinite(far) or far <= near:
        return [near]
    raw = (far - near) / max(count - 1, 1)
    magnitude = 10 ** np.floor(np.log10(raw))
    step = min((m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw), default=raw)
    inner = np.arange(np.ceil(near / step) * step, far, step)
    ticks = [near, *[float(t) for t in inner if near + 0.3 * step < t < far - 0.3 * step], far]
    return ticks


def _label(value: float) -> str:
    return f"{value:.3g}" if value < 1000 else f"{value:.0f}"


def depth_panel(
    image: np.ndarray,
    depth: np.ndarray,
    valid: np.ndarray | None = None,
    unit: str = "units",
    min_height: int = 240,
    label: str = "depth",
    scale_region: np.ndarray | None = None,
) -> np.ndarray:
    """One picture of a prediction: input frame | colourised depth | colour bar with its scale.

    Args:
        image: (H, W, 3) RGB input frame in [0, 1] (float) or 0..255 (uint8).
        depth: (H, W) depth; invalid (non-finite, <= 0 or outside ``valid``) pixels are black.
        valid: optional (H, W) bool mask, e.g. the camera's image circle.
        unit: the depth unit written on the bar ("m" for a metric model).
        label: the bar's title before the unit: ``"range"`` or ``"z"`` says the convention.
        scale_region: optional (H, W) bool: the colour scale spans the 2-98% range of these
            pixels only (every usable pixel is still drawn, clipped to the scale): z-depth falls
            to 0 towards 90 degrees off-axis, and a fisheye's rim would otherwise take the scale.
        min_height: small inputs are enlarged (nearest neighbour) to at least this height so
            that the labels stay readable.

    Returns:
        (H', W', 3) uint8 BGR image, ready for ``cv2.imwrite``. The bar is linear in inverse
        depth, as the colours are, and its labels are depths in ``unit``.
    """
    import cv2

    depth = np.asarray(depth, dtype=np.float32)
    height, width = depth.shape
    usable = np.isfinite(depth) & (depth > 0)
    if valid is not None:
        usable &= np.asarray(valid, dtype=bool)
    scaled = usable if scale_region is None else usable & np.asarray(scale_region, dtype=bool)
    low, high = _inverse_range(depth, scaled if scaled.any() else usable)
    coloured = colourise_depth(depth, usable, (low, high))
    frame = np.asarray(image)
    if frame.dtype != np.uint8:
        frame = (np.clip(frame, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    frame = cv2.cvtColor(np.ascontiguousarray(frame[..., :3]), cv2.COLOR_RGB2BGR)

    scale = max(1, int(np.ceil(min_height / height)))
    size = (width * scale, height * scale)
    frame = cv2.resize(frame, size, interpolation=cv2.INTER_NEAREST)
    coloured = cv2.resize(coloured, size, interpolation=cv2.INTER_NEAREST)
    panel_h = size[1]

    # Colour bar: top = near (high inverse depth), bottom = far, the same map as the panel.
    top, bottom, bar_w, text_w = 28, 10, 18, 90  # top: room for the title above the bar
    strip = np.linspace(1.0, 0.0, panel_h - top - bottom, dtype=np.float32)[:, None]
    bar_colours = cv2.applyColorMap((strip * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bar = np.full((panel_h, bar_w + text_w, 3), 255, np.uint8)
    bar[top : panel_h - bottom, 4:bar_w] = bar_colours
    font, font_scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1
    cv2.putText(bar, f"{label} [{unit}]", (4, 14), font, font_scale, (0, 0, 0), thick, cv2.LINE_AA)
    if usable.any():
        near, far = 1.0 / high, 1.0 / max(low, 1e-12)
        for tick in _nice_ticks(near, far):
            fraction = (1.0 / tick - low) / (high - low)  # 1 at the top
            y = int(round(top + (1.0 - np.clip(fraction, 0.0, 1.0)) * (panel_h - top - bottom - 1)))
            cv2.line(bar, (bar_w, y), (bar_w + 4, y), (0, 0, 0), 1)
            cv2.putText(
                bar,
                _label(tick),
                (bar_w + 7, y + 4),
                font,
                font_scale,
                (0, 0, 0),
                thick,
                cv2.LINE_AA,
            )
    else:
        cv2.putText(
            bar,
            "no valid",
            (bar_w + 2, panel_h // 2),
            font,
            font_scale,
            (0, 0, 0),
            thick,
            cv2.LINE_AA,
        )
    return np.concatenate([frame, coloured, bar], axis=1)


def write_tum(path: str | os.PathLike, timestamps: np.ndarray, cam_from_world: np.ndarray) -> None:
    """TUM trajectory: one line ``t tx ty tz qx qy qz qw`` per frame, camera-to-world poses."""
    lines = ["# timestamp tx ty tz qx qy qz qw (world_from_cam)"]
    for stamp, pose in zip(timestamps, cam_from_world, strict=True):
        world_from_cam = invert_rigid(pose)
        t = world_from_cam[:3, 3]
        w, *xyz = rotation_to_quaternion(world_from_cam[:3, :3])  # TUM stores (x, y, z, w)
        q = (*xyz, w)
        lines.append(" ".join(f"{v:.9g}" for v in (stamp, *t, *q)))
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_ply(path: str | os.PathLike, points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY with float32 xyz and uint8 rgb; points (N, 3), colours (N, 3) in [0, 1]."""
    points = np.asarray(points, dtype="<f4")
    colours = (np.clip(np.asarray(colours), 0, 1) * 255 + 0.5).astype(np.uint8)
    record = np.empty(
        len(points),
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
        ],
    )
    record["x"], record["y"], record["z"] = points.T
    record["red"], record["green"], record["blue"] = colours.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    atomic_write_bytes(path, header.encode("ascii") + record.tobytes())


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read back what :func:`write_ply` writes: (N, 3) float32 points and (N, 3) uint8 colours."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(
        next(
            line for line in data[:end].decode().splitlines() if line.startswith("element vertex")
        ).split()[-1]
    )
    record = np.frombuffer(
        data[end:],
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
        ],
        count=count,
    )
    return np.stack([record["x"], record["y"], record["z"]], -1), np.stack(
        [record["red"], record["green"], record["blue"]], -1
    )


def write_frames(folder: str | os.PathLike, names: list[str], images: np.ndarray) -> list[str]:
    """Write (S, H, W, 3) RGB frames in [0, 1] as 8-bit ``<name>.png``; returns the file names."""
    import cv2

    Path(folder).mkdir(parents=True, exist_ok=True)
    files = []
    for name, image in zip(names, images, strict=True):
        pixels = (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)[..., ::-1]
        ok, png = cv2.imencode(".png", np.ascontiguousarray(pixels))
        if not ok:
            raise OSError(f"could not encode frame {name!r} as PNG")
        atomic_write_bytes(Path(folder) / f"{name}.png", png.tobytes())
        files.append(f"{name}.png")
    return files
