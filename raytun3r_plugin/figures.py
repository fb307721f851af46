"""Pictures drawn with matplotlib (the optional ``viz`` extra), returned as PNG bytes.

* :func:`loss_figure`: one small chart per loss term, each on its own scale, the smoothed trend
  drawn over the faint per-step values, so a reader sees whether each term settled;
* :func:`depth_figure`: an input frame beside depth maps on one colour scale, with colour bars;
* :func:`field_figure`: a scalar field over the image (the PE correction) with a colour bar;
* :func:`metric_bars`: a metric per method and cell (benchmark tables);
* :func:`curves_figure`: curves over a common abscissa, one chart per panel (analyses).

Figures are built with ``matplotlib.figure.Figure`` on the Agg canvas, never through pyplot's
global state, so they are safe in worker threads and leave no window behind. Without
matplotlib every function raises :class:`~raytun3r_plugin.errors.MissingDependencyError`; the
OpenCV charts of :mod:`raytun3r_plugin.plots` are the fallback where a picture must be written
anyway (the loss curve of every fit).
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np

from raytun3r_plugin.errors import MissingDependencyError

__all__ = [
    "curves_figure",
    "depth_figure",
    "field_figure",
    "loss_figure",
    "metric_bars",
    "smoothed",
    "trend_change",
]


def _figure(
    width_in: float, height_in: float, layout: Literal["constrained"] | None = "constrained"
):
    try:
        from matplotlib.figure import Figure
    except ImportError as error:
        raise MissingDependencyError(
            "matplotlib is needed for this picture: pip install 'raytun3r[viz]'"
        ) from error
    return Figure(figsize=(width_in, height_in), dpi=100, layout=layout)


def _png(figure) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    return buffer.getvalue()


def smoothed(values: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """Centred moving mean of ``values`` over ``window`` steps (shorter at the ends), non-finite
    values left out; NaN where a window holds none. A fit cycles through its windows one per
    step, so a window of one pass over them averages out which window a step happened to see."""
    y = np.asarray(values, dtype=np.float64)
    window = max(1, int(window))
    finite = np.isfinite(y)
    sums = np.concatenate([[0.0], np.cumsum(np.where(finite, y, 0.0))])
    counts = np.concatenate([[0], np.cumsum(finite)])
    index = np.arange(y.size)
    low = np.clip(index - (window - 1) // 2, 0, y.size)
    high = np.clip(index + window // 2 + 1, 0, y.size)
    count = counts[high] - counts[low]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (sums[high] - sums[low]) / np.maximum(count, 1), np.nan)


def trend_change(values: Sequence[float] | np.ndarray, window: int) -> float | None:
    """Relative change of the mean over the last ``window`` steps against the ``window`` steps
    before them (``-0.02``: 2 % lower), or None with fewer than two windows of finite values or a
    zero mean before. Small values say the term has settled."""
    y = np.asarray(values, dtype=np.float64)
    y = y[np.isfinite(y)]
    window = max(1, int(window))
    if y.size < 2 * window:
        return None
    before, last = float(y[-2 * window : -window].mean()), float(y[-window:].mean())
    return None if before == 0 else (last - before) / abs(before)


def loss_figure(
    series: Mapping[str, Sequence[float]],
    window: int,
    *,
    title: str = "",
    columns: int = 3,
) -> bytes:
    """Small multiples of loss terms: one chart per entry of ``series`` (name -> value per step),
    each with its own linear y scale; faint raw values, the :func:`smoothed` trend over
    ``window`` steps in bold, and in each chart's title the change of its last ``window`` steps
    against the ``window`` before (:func:`trend_change`). Terms without a finite value are left
    out. Returns PNG bytes."""
    names = [name for name, v in series.items() if np.isfinite(np.asarray(v, float)).any()]
    columns = max(1, min(columns, len(names) or 1))
    rows = max(1, math.ceil(len(names) / columns))
    title_in = 0.3 if title else 0.0
    width, height = 3.6 * columns, 2.4 * rows + title_in
    # Fixed margins in inches, not the constrained layout: every chart of the grid has the same
    # furniture, and the layout's extra draw pass was half of the time each fit spent on its PNG.
    figure = _figure(width, height, layout=None)
    figure.subplots_adjust(
        left=0.55 / width,
        right=1 - 0.15 / width,
        bottom=0.45 / height,
        top=1 - (0.35 + title_in) / height,
        wspace=0.28,
        hspace=0.54,
    )
    if title:
        figure.suptitle(title, fontsize=11)
    if not names:
        axis = figure.add_subplot(1, 1, 1)
        axis.text(0.5, 0.5, "no finite loss values", ha="center", va="center")
        axis.set_axis_off()
        return _png(figure)
    for k, name in enumerate(names):
        axis = figure.add_subplot(rows, columns, k + 1)
        y = np.asarray(series[name], dtype=np.float64)
        steps = np.arange(y.size)
        axis.plot(steps, y, color="0.75", linewidth=0.8, label="per step")
        axis.plot(steps, smoothed(y, window), color="C0", linewidth=2.0, label="trend")
        change = trend_change(y, window)
        note = "" if change is None else f" (last {window} steps {100 * change:+.1f} %)"
        axis.set_title(f"{name}{note}", fontsize=9)
        axis.tick_params(labelsize=8)
        axis.grid(True, linewidth=0.4, alpha=0.5)
        if k >= len(names) - columns:
            axis.set_xlabel("step", fontsize=8)
    return _png(figure)


def _masked(values: np.ndarray, valid: np.ndarray | None) -> np.ma.MaskedArray:
    values = np.asarray(values, dtype=np.float64)
    keep = np.isfinite(values) if valid is None else np.asarray(valid, bool) & np.isfinite(values)
    return np.ma.masked_array(values, mask=~keep)


def field_figure(
    values: np.ndarray,
    title: str,
    unit: str,
    *,
    valid: np.ndarray | None = None,
    cmap: str = "viridis",
) -> bytes:
    """A scalar field (H, W) with a colour bar labelled ``unit``; pixels outside ``valid`` (or
    not finite) are drawn dark grey. Returns PNG bytes."""
    field = _masked(values, valid)
    figure = _figure(4.6, 3.9)
    axis = figure.add_subplot(1, 1, 1)
    colours = _colour_map(cmap)
    image = axis.imshow(field, cmap=colours, interpolation="nearest")
    axis.set_title(title, fontsize=9)
    axis.set_axis_off()
    figure.colorbar(image, ax=axis, shrink=0.85).set_label(unit, fontsize=8)
    return _png(figure)


def _colour_map(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="0.25")


def depth_figure(
    frame: np.ndarray,
    depths: Mapping[str, np.ndarray],
    *,
    valid: np.ndarray | None = None,
    unit: str = "depth units",
    frame_title: str = "input",
) -> bytes:
    """The input ``frame`` (H, W, 3) RGB in [0, 1] beside each depth map of ``depths`` (title ->
    (H, W)), all depth panels on one colour scale (2nd to 98th percentile of their valid pixels
    together) with a colour bar each, pixels outside ``valid`` grey. Returns PNG bytes."""
    panels = {title: _masked(depth, valid) for title, depth in depths.items()}
    pooled = np.concatenate([p.compressed() for p in panels.values()] + [np.zeros(0)])
    pooled = pooled if pooled.size else np.array([0.0, 1.0])
    low, high = (float(v) for v in np.percentile(pooled, [2, 98]))
    high = high if high > low else low + 1e-6
    figure = _figure(3.3 * (1 + len(panels)), 3.3)
    axis = figure.add_subplot(1, 1 + len(panels), 1)
    axis.imshow(np.clip(np.asarray(frame, dtype=np.float64), 0, 1), interpolation="nearest")
    axis.set_title(frame_title, fontsize=9)
    axis.set_axis_off()
    colours = _colour_map("turbo")
    for k, (title, depth) in enumerate(panels.items()):
        axis = figure.add_subplot(1, 1 + len(panels), k + 2)
        image = axis.imshow(depth, cmap=colours, vmin=low, vmax=high, interpolation="nearest")
        axis.set_title(title, fontsize=9)
        axis.set_axis_off()
        figure.colorbar(image, ax=axis, shrink=0.8).set_label(unit, fontsize=8)
    return _png(figure)


def metric_bars(
    values: Mapping[str, Mapping[str, float]],
    metric: str,
    *,
    lower_is_better: bool = True,
) -> bytes:
    """Grouped bars: ``values[group][method]`` (e.g. cell -> method -> mean AbsRel), one group
    per cell, one colour per method, the y axis labelled ``metric``. Returns PNG bytes."""
    groups = list(values)
    methods = list(dict.fromkeys(m for g in groups for m in values[g]))
    figure = _figure(max(5.0, 1.1 * len(groups) * max(1, len(methods)) / 3 + 2.5), 3.4)
    axis = figure.add_subplot(1, 1, 1)
    width = 0.8 / max(1, len(methods))
    for k, method in enumerate(methods):
        heights = [values[g].get(method, np.nan) for g in groups]
        positions = np.arange(len(groups)) + (k - (len(methods) - 1) / 2) * width
        axis.bar(positions, heights, width=width, label=method, color=f"C{k % 10}")
    axis.set_xticks(np.arange(len(groups)), groups, fontsize=8, rotation=15)
    axis.set_ylabel(metric + (" (lower is better)" if lower_is_better else ""), fontsize=8)
    axis.tick_params(labelsize=8)
    axis.grid(True, axis="y", linewidth=0.4, alpha=0.5)
    axis.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _png(figure)


def curves_figure(
    panels: Sequence[tuple[str, Mapping[str, Sequence[float]]]],
    x: Sequence[float],
    *,
    x_label: str,
    log_y: bool = True,
    size_px: tuple[int, int] = (1280, 400),
) -> bytes:
    """One chart per ``(title, {name: values})`` panel, side by side, every curve over the
    abscissa ``x`` (log y scale with ``log_y``; non-finite and, on a log scale, non-positive
    values left out), legend in each chart. The PNG is ``size_px`` (width, height) pixels."""
    figure = _figure(size_px[0] / 100, size_px[1] / 100)
    abscissa = np.asarray(x, dtype=np.float64)
    for k, (title, series) in enumerate(panels):
        axis = figure.add_subplot(1, max(1, len(panels)), k + 1)
        for name, values in series.items():
            y = np.asarray(values, dtype=np.float64)
            keep = np.isfinite(y) & ((y > 0) if log_y else True)
            axis.plot(abscissa[keep], y[keep], marker=".", linewidth=1.2, label=name)
        if log_y:
            axis.set_yscale("log")
        axis.set_title(title, fontsize=9)
        axis.set_xlabel(x_label, fontsize=8)
        axis.tick_params(labelsize=8)
        axis.grid(True, linewidth=0.4, alpha=0.5)
        axis.legend(fontsize=7)
    return _png(figure)
