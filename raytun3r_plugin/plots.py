"""Small pictures drawn with OpenCV (always installed): the fallback for the loss curves, the PE
picture and the Jacobian chart where matplotlib (the ``viz`` extra,
:mod:`raytun3r_plugin.figures`) is not installed.

``line_chart`` draws loss curves; ``heatmap`` draws a scalar field (e.g. the size of the PE
correction over the image) with a labelled colour bar. Both return BGR uint8 images for
``cv2.imwrite``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["heatmap", "line_chart"]

_COLOURS = [
    (180, 119, 31),
    (14, 127, 255),
    (44, 160, 44),
    (40, 39, 214),
    (189, 103, 148),
    (75, 86, 140),
    (194, 119, 227),
]


def line_chart(
    series: Mapping[str, Sequence[float]],
    title: str,
    *,
    log_y: bool = True,
    size: tuple[int, int] = (720, 420),
    x: Sequence[float] | None = None,
    x_label: str = "step",
) -> np.ndarray:
    """Curves of ``series`` (name -> values per step) on one chart, legend at the top right.

    ``x`` gives the abscissa of every value (default: the step index 0, 1, ...). Non-finite
    values (and non-positive ones with ``log_y``) are left out of each curve.
    """
    import cv2

    width, height = size
    left, right, top, bottom = 64, 16, 34, 36
    image = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(image, title, (left, 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    curves = {}
    for name, values in series.items():
        y = np.asarray(values, dtype=np.float64)
        xs = np.arange(y.size, dtype=np.float64) if x is None else np.asarray(x, np.float64)
        keep = np.isfinite(y) & ((y > 0) if log_y else True)
        if keep.any():
            curves[name] = (xs[keep], np.log10(y[keep]) if log_y else y[keep])
    cv2.rectangle(image, (left, top), (width - right, height - bottom), (0, 0, 0), 1)
    if not curves:
        cv2.putText(
            image,
            "no finite values",
            (left + 10, height // 2),
            font,
            0.5,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
        return image
    x_max = max(float(x.max()) for x, _ in curves.values()) or 1.0
    y_lo = min(float(y.min()) for _, y in curves.values())
    y_hi = max(float(y.max()) for _, y in curves.values())
    if y_hi - y_lo < 1e-9:
        y_lo, y_hi = y_lo - 0.5, y_hi + 0.5

    def to_px(xs: np.ndarray, y: np.ndarray) -> np.ndarray:
        u = left + (xs / x_max) * (width - left - right)
        v = height - bottom - (y - y_lo) / (y_hi - y_lo) * (height - top - bottom)
        return np.stack([u, v], axis=1).round().astype(np.int32)

    for k in range(5):
        value = y_lo + (y_hi - y_lo) * k / 4
        v = int(round(height - bottom - k / 4 * (height - top - bottom)))
        cv2.line(image, (left - 4, v), (left, v), (0, 0, 0), 1)
        label = f"{10**value:.3g}" if log_y else f"{value:.3g}"
        cv2.putText(image, label, (4, v + 4), font, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
    for k in range(5):
        step = x_max * k / 4
        u = int(round(left + k / 4 * (width - left - right)))
        cv2.line(image, (u, height - bottom), (u, height - bottom + 4), (0, 0, 0), 1)
        cv2.putText(
            image,
            f"{step:.0f}" if x is None else f"{step:.2g}",
            (u - 10, height - bottom + 18),
            font,
            0.38,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    cv2.putText(image, x_label, (width // 2 - 14, height - 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for index, (name, (xs, y)) in enumerate(curves.items()):
        colour = _COLOURS[index % len(_COLOURS)]
        cv2.polylines(image, [to_px(xs, y).reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
        v = top + 16 + 16 * index
        cv2.line(image, (width - right - 120, v - 4), (width - right - 100, v - 4), colour, 2)
        cv2.putText(image, name, (width - right - 94, v), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return image


def heatmap(
    values: np.ndarray,
    title: str,
    unit: str,
    *,
    valid: np.ndarray | None = None,
    min_size: int = 320,
    limits: tuple[float, float] | None = None,
) -> np.ndarray:
    """A scalar field (H, W) coloured with the turbo map (0 = the smallest value, black outside
    ``valid``), enlarged to at least ``min_size`` px, with a colour bar labelled in ``unit``.
    ``limits``: the values at the two ends of the colour bar (default: the field's own minimum
    and maximum), so several pictures can share one scale."""
    import cv2

    values = np.asarray(values, dtype=np.float64)
    valid = np.isfinite(values) if valid is None else np.asarray(valid, bool) & np.isfinite(values)
    low = float(values[valid].min()) if valid.any() else 0.0
    high = float(values[valid].max()) if valid.any() else 1.0
    if limits is not None:
        low, high = float(limits[0]), float(limits[1])
    high = high if high > low else low + 1e-12
    scaled = np.clip((np.where(valid, values, low) - low) / (high - low), 0, 1)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[~valid] = 0
    scale = max(1, math.ceil(min_size / max(values.shape)))
    image = cv2.resize(
        image, (values.shape[1] * scale, values.shape[0] * scale), interpolation=cv2.INTER_NEAREST
    )
    height = image.shape[0]
    top, bottom, bar_w, text_w = 34, 10, 18, 96
    bar = np.full((height, bar_w + text_w, 3), 255, np.uint8)
    strip = np.linspace(1.0, 0.0, height - top - bottom, dtype=np.float32)[:, None]
    bar[top : height - bottom, 4:bar_w] = cv2.applyColorMap(
        (strip * 255).astype(np.uint8), cv2.COLORMAP_TURBO
    )
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(bar, unit, (4, 24), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for k in range(5):
        fraction = k / 4
        v = int(round(top + (1 - fraction) * (height - top - bottom - 1)))
        cv2.line(bar, (bar_w, v), (bar_w + 4, v), (0, 0, 0), 1)
        cv2.putText(
            bar,
            f"{low + fraction * (high - low):.3g}",
            (bar_w + 7, v + 4),
            font,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    out = np.concatenate([image, bar], axis=1)
    banner = np.full((26, out.shape[1], 3), 255, np.uint8)
    cv2.putText(banner, title, (6, 18), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([banner, out], axis=0)
