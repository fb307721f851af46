"""What ``raytun3r inspect`` shows of an adapter file: a summary in words (:func:`describe_file`),
the whole record as JSON (:func:`describe_record`) and a picture of the PE correction over the
image (:func:`write_pe_picture`). The file format itself is :mod:`raytun3r_plugin.adapter`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from typing import Any

import torch

from raytun3r_plugin.adapter import FORMAT, FORMAT_VERSION, Adapter
from raytun3r_plugin.apps.fits import recipe_text, setting_text
from raytun3r_plugin.errors import AdapterError

__all__ = ["describe_file", "describe_record", "pe_correction_field", "write_pe_picture"]


def describe_record(path: str | os.PathLike) -> dict[str, Any]:
    """An adapter file's metadata as one JSON-ready dict (what ``raytun3r inspect --json`` prints).

    The string metadata of the file are decoded (camera, components and the training record
    as objects, sizes as integers) and the parameter counts are added.
    """
    adapter = Adapter.load(path)
    metadata = adapter.metadata()
    record: dict[str, Any] = {
        key: value
        for key, value in metadata.items()
        if key not in ("camera", "components", "training")
    }
    for key in ("embed_dim", "patch_size", "n_r", "n_theta", "n_r_rope"):
        record[key] = int(metadata[key])
    record["camera"] = json.loads(metadata["camera"]) if metadata["camera"] else None
    record["components"] = dict(adapter.components)
    record["training"] = dict(adapter.training_info)
    record["parameters"] = adapter.num_parameters()
    return record


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple)):
        return f"{len(value)} items"
    if isinstance(value, dict):
        return f"{len(value)} keys"
    return str(value)


#: The indent of every line under ``training:``.
_INDENT = " " * 17
_WIDTH = 100 - len(_INDENT)
#: training_info keys the lines below show; any other is named under "also recorded".
_SHOWN = (
    "verdict",
    "teacher",
    "recipe",
    "check",
    "method",
    "steps",
    "requested_steps",
    "resumed_from",
    "interrupted",
    "wall_time_s",
    "final_losses",
    "final_losses_over_steps",
    "segment",
    "input",
)


def _training_lines(training: Mapping[str, Any]) -> list[str]:
    """A few lines about the fitting; the full record is ``raytun3r inspect --json``."""
    if not training:
        return ["training:        none (not fitted: made by Adapter.for_model or by hand)"]
    lines = [f"training:        {training.get('method', 'unknown method')}: {_head(training)}"]
    for section in (
        _recipe_lines,
        _pose_gate_lines,
        _loss_lines,
        _segment_lines,
        _input_lines,
        _check_lines,
        _verdict_lines,
        _teacher_lines,
        _extra_lines,
    ):
        lines.extend(f"{_INDENT}{line}" for line in section(training))
    return lines


def _head(training: Mapping[str, Any]) -> str:
    steps = training.get("steps")
    head = (
        f"{steps} of {training['requested_steps']} steps"
        if "requested_steps" in training
        else f"{steps} steps"
    )
    if training.get("resumed_from"):
        head += f", resumed at step {training['resumed_from']}"
    if training.get("interrupted"):
        head += ", interrupted"
    if "wall_time_s" in training:
        head += f", {float(training['wall_time_s']):.1f} s"
    return head


def _recipe_lines(training: Mapping[str, Any]) -> list[str]:
    recipe = training.get("recipe")
    if isinstance(recipe, Mapping) and recipe.get("name"):
        return _wrap(recipe_text(recipe, with_old=True), _WIDTH)
    return ["recipe: not recorded (fitted before recipes existed)"]


def _pose_gate_lines(training: Mapping[str, Any]) -> list[str]:
    gate = training.get("pose_gate")
    if not (isinstance(gate, Mapping) and "pose_term" in gate):
        return []
    verdict = "kept" if gate["pose_term"] else "dropped: the head does not turn"
    return [
        f"pose gate: responsiveness {setting_text(gate.get('responsiveness'))} against "
        f"{setting_text(gate.get('threshold'))}, pose term {verdict}"
    ]


def _loss_lines(training: Mapping[str, Any]) -> list[str]:
    losses = training.get("final_losses") or {}
    if not losses:
        return []
    over = training.get("final_losses_over_steps")
    text = ", ".join(f"{name} {float(value):.3g}" for name, value in losses.items())
    return [
        f"final losses{f' (mean of the last {over} steps)' if over else ''}:",
        *(f"  {part}" for part in _wrap(text, _WIDTH)),
    ]


def _segment_lines(training: Mapping[str, Any]) -> list[str]:
    segment = training.get("segment") or {}
    if not segment:
        return []
    parts = [
        f"{key} {_short(value)}"
        for key, value in segment.items()
        if key not in ("windows", "segments") and value is not None
    ]
    if "segments" in segment:  # a fit on several segments: their count, not their records
        parts.insert(0, f"{len(segment['segments'])} segments")
    if "windows" in segment:
        parts.insert(0, f"{len(segment['windows'])} windows")
    return ["segment:", *(f"  {part}" for part in _wrap(", ".join(parts), _WIDTH))]


def _input_lines(training: Mapping[str, Any]) -> list[str]:
    layout = training.get("input") or {}
    if not layout:
        return []
    crop = layout.get("crop")
    rule = (
        f" (long side {layout['long_side']}, input rule v{layout.get('rule_version')})"
        if layout.get("long_side")
        else ""
    )
    return [
        f"input: {layout.get('width')}x{layout.get('height')} px, "
        + (f"crop {crop}" if crop else "no crop")
        + rule
    ]


def _check_lines(training: Mapping[str, Any]) -> list[str]:
    check = training.get("check")
    if not (isinstance(check, Mapping) and check.get("adapted_px") is not None):
        return []
    return [
        f"check on {check.get('frames')} held-out frames: reprojection "
        f"{float(check['zero_adapter_px']):.3f} px without the adapter -> "
        f"{float(check['adapted_px']):.3f} px with it"
    ]


def _verdict_lines(training: Mapping[str, Any]) -> list[str]:
    verdict = training.get("verdict")
    if not (isinstance(verdict, Mapping) and verdict.get("summary")):
        return []
    return ["verdict:", *(f"  {part}" for part in _wrap(str(verdict["summary"]), _WIDTH))]


def _teacher_lines(training: Mapping[str, Any]) -> list[str]:
    teacher = training.get("teacher")
    if not (isinstance(teacher, Mapping) and "used" in teacher):
        return []
    return [
        f"pinhole-view teacher: {'used' if teacher['used'] else 'left out'} (its "
        f"largest view covers {float(teacher.get('coverage', 0.0)):.0%} of the lens, at most "
        f"{float(teacher.get('max_coverage', 0.0)):.0%} for it to be used)"
    ]


def _extra_lines(training: Mapping[str, Any]) -> list[str]:
    extra = [key for key in training if key not in _SHOWN]
    if extra:
        return [f"also recorded: {', '.join(extra)} (raytun3r inspect --json shows everything)"]
    return ["(raytun3r inspect --json shows the full record)"]


def _wrap(text: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width) or [""]


def describe_file(path: str | os.PathLike) -> str:
    """Human-readable summary of an adapter file (what ``raytun3r inspect`` prints)."""
    adapter = Adapter.load(path)
    counts = adapter.num_parameters()
    metadata = adapter.metadata()
    lines = [
        f"file:            {path}",
        f"format:          {FORMAT} v{FORMAT_VERSION} (written by raytun3r {metadata['raytun3r_version']})",
        f"backbone:        {adapter.backbone} (embed_dim {adapter.embed_dim}, patch {adapter.patch_size})",
        f"tables:          pe.radial {adapter.n_r}x{adapter.embed_dim}, pe.angular {adapter.n_theta}x{adapter.embed_dim}"
        + (f", rope.radial {adapter.n_r_rope}" if adapter.n_r_rope else ""),
        f"parameters:      {counts['total']:,} ({counts['pe']:,} PE + {counts['rope']:,} RoPE)",
        f"camera:          {adapter.camera!r}",
        f"field of view:   {adapter.camera.fov_deg:.1f} deg"
        if adapter.camera is not None
        else "field of view:   -",
        f"components:      {', '.join(k for k, v in adapter.components.items() if v) or 'none'}",
        f"pe_fingerprint:  {adapter.pe_fingerprint or '-'}",
        *_training_lines(adapter.training_info),
    ]
    magnitude = max(float(p.detach().abs().max()) for p in adapter.parameters())
    lines.append(
        f"max |table|:     {magnitude:.3g}"
        + (" (identity adapter)" if magnitude == 0 or math.isclose(magnitude, 0.0) else "")
    )
    return "\n".join(lines)


def pe_correction_field(adapter: Adapter, long_side: int = 504):
    """The adapter's PE correction size ``||t_r(rho) + rho d_theta(theta)||`` (PE units) per
    pixel of the network input it was fitted at (or ``long_side`` px), each token's value over its
    patch: ``(values (H, W) float64, lens (H, W) bool, title)``. A fresh adapter is flat zero; a
    fitted one shows where the correction acts (typically growing towards the rim).

    Raises:
        AdapterError: the adapter carries no camera.
    """
    import numpy as np

    from raytun3r_plugin.adaptation.losses import pe_correction_grid
    from raytun3r_plugin.preprocess import fitted_source_camera, input_layout
    from raytun3r_plugin.size_geometry import GeometryCache

    if adapter.camera is None:
        raise AdapterError(
            "the adapter carries no camera, so the PE correction has no image to be drawn on"
        )
    trained = (adapter.training_info or {}).get("input") or {}
    source = fitted_source_camera(adapter)  # not None: the adapter carries a camera
    if trained.get("long_side") and source is not None:
        # The fit's own layout: the rule applied again to the uncropped camera and long side.
        layout = input_layout(source, int(trained["long_side"]), adapter.patch_size)
    else:
        # Files from before the rule was recorded: the input's long side on the adapter's camera.
        layout = input_layout(
            adapter.camera,
            int(max(trained.get("width", 0), trained.get("height", 0)) or long_side),
            adapter.patch_size,
        )
    geometry = GeometryCache(layout.native_camera, adapter.patch_size).at(
        layout.height, layout.width
    )
    with torch.no_grad():
        size = pe_correction_grid(adapter, geometry).norm(dim=-1).cpu().numpy()
    pixels = np.kron(size, np.ones((adapter.patch_size, adapter.patch_size)))
    lens = layout.camera.valid_mask().cpu().numpy().astype(bool)
    title = f"PE correction per token ({layout.width}x{layout.height} px input)"
    return pixels, lens, title


def write_pe_picture(adapter: Adapter, path: str | os.PathLike, long_side: int = 504) -> None:
    """Write a PNG of the adapter's PE correction (:func:`pe_correction_field`) with a colour
    bar in PE units: drawn with matplotlib (the ``viz`` extra), or with OpenCV's
    :func:`~raytun3r_plugin.plots.heatmap` where matplotlib is not installed.

    Raises:
        AdapterError: the adapter carries no camera.
    """
    from pathlib import Path

    from raytun3r_plugin.errors import MissingDependencyError
    from raytun3r_plugin.figures import field_figure

    pixels, lens, title = pe_correction_field(adapter, long_side)
    try:
        Path(path).write_bytes(field_figure(pixels, title, "PE units", valid=lens))
    except MissingDependencyError:
        import cv2

        from raytun3r_plugin.plots import heatmap

        cv2.imwrite(str(path), heatmap(pixels, title, "PE units", valid=lens))
