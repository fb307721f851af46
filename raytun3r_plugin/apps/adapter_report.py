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


def _training_lines(training: Mapping[str, Any]) -> list[str]:
    """A few lines about the fitting; the full record is ``raytun3r inspect --json``."""
    if not training:
        return ["training:        none (not fitted: made by Adapter.for_model or by hand)"]
    indent = " " * 17
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
    lines = [f"training:        {training.get('method', 'unknown method')}: {head}"]
    from raytun3r_plugin.apps.fits import recipe_text, setting_text

    recipe = training.get("recipe")
    if isinstance(recipe, Mapping) and recipe.get("name"):
        text = recipe_text(recipe, with_old=True)
        lines.extend(f"{indent}{part}" for part in _wrap(text, 100 - len(indent)))
    elif training:
        lines.append(f"{indent}recipe: not recorded (fitted before recipes existed)")
    gate = training.get("pose_gate")
    if isinstance(gate, Mapping) and "pose_term" in gate:
        verdict = "kept" if gate["pose_term"] else "dropped: the head does not turn"
        lines.append(
            f"{indent}pose gate: responsiveness {setting_text(gate.get('responsiveness'))} against "
            f"{setting_text(gate.get('threshold'))}, pose term {verdict}"
        )
    losses = training.get("final_losses") or {}
    if losses:
        over = training.get("final_losses_over_steps")
        text = ", ".join(f"{name} {float(value):.3g}" for name, value in losses.items())
        lines.append(f"{indent}final losses{f' (mean of the last {over} steps)' if over else ''}:")
        lines.extend(f"{indent}  {part}" for part in _wrap(text, 100 - len(indent)))
    segment = training.get("segment") or {}
    if segment:
        parts = [
            f"{key} {_short(value)}"
            for key, value in segment.items()
            if key not in ("windows", "segments") and value is not None
        ]
        if "segments" in segment:  # a fit on several segments: their count, not their records
            parts.insert(0, f"{len(segment['segments'])} segments")
        if "windows" in segment:
            parts.insert(0, f"{len(segment['windows'])} windows")
        lines.append(f"{indent}segment:")
        lines.extend(f"{indent}  {part}" for part in _wrap(", ".join(parts), 100 - len(indent)))
    layout = training.get("input") or {}
    if layout:
        crop = layout.get("crop")
        rule = (
            f" (long side {layout['long_side']}, input rule v{layout.get('rule_version')})"
            if layout.get("long_side")
            else ""
        )
        lines.append(
            f"{indent}input: {layout.get('width')}x{layout.get('height')} px, "
            + (f"crop {crop}" if crop else "no crop")
            + rule
        )
    check = training.get("check")
    if isinstance(check, Mapping) and check.get("adapted_px") is not None:
        lines.append(
            f"{indent}check on {check.get('frames')} held-out frames: reprojection "
            f"{float(check['zero_adapter_px']):.3f} px without the adapter -> "
            f"{float(check['adapted_px']):.3f} px with it"
        )
    verdict = training.get("verdict")
    if isinstance(verdict, Mapping) and verdict.get("summary"):
        lines.append(f"{indent}verdict:")
        lines.extend(
            f"{indent}  {part}" for part in _wrap(str(verdict["summary"]), 100 - len(indent))
        )
    teacher = training.get("teacher")
    if isinstance(teacher, Mapping) and "used" in teacher:
        lines.append(
            f"{indent}pinhole-view teacher: {'used' if teacher['used'] else 'left out'} (its "
            f"largest view covers {float(teacher.get('coverage', 0.0)):.0%} of the lens, at most "
            f"{float(teacher.get('max_coverage', 0.0)):.0%} for it to be used)"
        )
    extra = [
        key
        for key in training
        if key
        not in (
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
    ]
    if extra:
        lines.append(
            f"{indent}also recorded: {', '.join(extra)} (raytun3r inspect --json shows everything)"
        )
    else:
        lines.append(f"{indent}(raytun3r inspect --json shows the full record)")
    return lines


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
    if trained.get("long_side"):
        # The fit's own layout: the rule applied again to the uncropped camera and long side.
        layout = input_layout(
            fitted_source_camera(adapter), int(trained["long_side"]), adapter.patch_size
        )
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
