"""Files of an adaptation run: artefact paths, the loss log and its CSV/picture, and the
resumable checkpoint (safetensors + string metadata, never pickle).

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports the public names here).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from raytun3r_plugin.adaptation.config import TERMS
from raytun3r_plugin.atomic_files import atomic_save_safetensors
from raytun3r_plugin.errors import AdapterError

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "artifact_paths",
    "load_checkpoint",
    "read_loss_log",
    "trend_window",
    "write_loss_artifacts",
]

CHECKPOINT_FORMAT = "raytun3r-adapt-checkpoint"
CHECKPOINT_VERSION = "1"


def artifact_paths(out_path: str | os.PathLike) -> dict[str, Path]:
    """``{"adapter", "log", "checkpoint", "csv", "curve"}`` paths for an adapter file ``out_path``."""
    out = Path(out_path)
    stem = out.name[: -len(".safetensors")] if out.name.endswith(".safetensors") else out.name
    return {
        "adapter": out,
        "log": out.with_name(f"{stem}.log.jsonl"),
        "checkpoint": out.with_name(f"{stem}.ckpt.safetensors"),
        "csv": out.with_name(f"{stem}.losses.csv"),
        "curve": out.with_name(f"{stem}.losses.png"),
    }


def write_loss_artifacts(
    paths: Mapping[str, Path],
    records: list[dict[str, Any]],
    terms: list[str] | None = None,
    title: str | None = None,
    plotted: list[str] | None = None,
) -> None:
    """The per-step losses as CSV (``paths["csv"]``) and as a loss-curve picture (``paths["curve"]``).

    Columns: ``step``, ``loss``, every term the run had (``terms``: these columns instead, e.g.
    a rig fit's per-camera ones), ``grad_norm``, ``skipped``, ``time_s``. The picture shows the
    total and each term (``plotted``: these columns instead) over the steps: with matplotlib (the
    ``viz`` extra) one chart per term on its own scale, its trend smoothed over one pass through
    the fit's windows (:func:`raytun3r_plugin.figures.loss_figure`); without it, the raw values
    on one log axis (OpenCV, :func:`raytun3r_plugin.plots.line_chart`).
    """
    import csv

    from raytun3r_plugin.errors import MissingDependencyError
    from raytun3r_plugin.figures import loss_figure

    if terms is None:
        terms = [name for name in TERMS if records and name in records[0]]
    columns = ["step", "loss", *terms, "grad_norm", "skipped", "time_s"]
    with open(paths["csv"], "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for record in records:
            writer.writerow([record.get(name, "") for name in columns])
    series = {
        name: [float(r[name]) for r in records]
        for name in ("loss", *(terms if plotted is None else plotted))
        if all(name in r for r in records) and any(float(r[name]) > 0 for r in records)
    }
    title = title or f"adaptation losses ({len(records)} steps)"
    try:
        Path(paths["curve"]).write_bytes(loss_figure(series, trend_window(records), title=title))
    except MissingDependencyError:
        import cv2

        from raytun3r_plugin.plots import line_chart

        cv2.imwrite(str(paths["curve"]), line_chart(series, title))


def trend_window(records: list[dict[str, Any]]) -> int:
    """Steps in one pass through a fit's windows (the distinct ``window`` indices of its log;
    at least 1): the span over which a loss trend is smoothed, so every window counts once."""
    windows = {r.get("window") for r in records if r.get("window") is not None}
    return max(1, len(windows)) if windows else max(1, len(records) // 10)


def read_loss_log(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The per-step records of a loss log (``*.log.jsonl``), or of the log next to an adapter."""
    path = Path(path)
    if not path.name.endswith(".jsonl"):
        path = artifact_paths(path)["log"]
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]


def _save_checkpoint(
    path: Path,
    adapter: nn.Module,
    optimizer: torch.optim.Optimizer,
    step: int,
    identity: dict[str, str],
) -> None:
    """Write the tables of ``adapter`` (an :class:`Adapter`, or a rig's ``ModuleList`` of
    them), the Adam moments and ``identity`` as metadata, atomically."""
    names = [name for name, _ in adapter.named_parameters()]
    tensors = {
        f"adapter.{name}": value.detach().to("cpu", torch.float32).contiguous().clone()
        for name, value in adapter.state_dict().items()
    }
    state = optimizer.state_dict()["state"]
    for index, name in enumerate(names):
        for key, value in state.get(index, {}).items():
            tensors[f"adam.{name}.{key}"] = (
                torch.as_tensor(value).detach().to("cpu", torch.float32).reshape(-1).clone()
            )
    metadata = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "step": str(step),
        **identity,
    }
    atomic_save_safetensors(path, tensors, metadata)


def load_checkpoint(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of an adaptation checkpoint (safetensors; nothing is unpickled)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata() or {})
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}  # noqa: SIM118
    if metadata.get("format") != CHECKPOINT_FORMAT:
        raise AdapterError(
            f"{path}: not a raytun3r adaptation checkpoint (format {metadata.get('format')!r})"
        )
    return tensors, metadata


def _restore_checkpoint(
    path: Path, adapter: nn.Module, optimizer: torch.optim.Optimizer, identity: dict[str, str]
) -> int:
    tensors, metadata = load_checkpoint(path)
    for key, expected in identity.items():
        if metadata.get(key) != expected:
            raise AdapterError(
                f"{path}: checkpoint was written for another run ({key} {metadata.get(key)!r}, this run {expected!r}); "
                "pass resume=False (raytun3r adapt: --restart) to start over"
            )
    with torch.no_grad():
        for name, parameter in adapter.named_parameters():
            stored = tensors.get(f"adapter.{name}")
            if stored is None or stored.shape != parameter.shape:
                raise AdapterError(
                    f"{path}: checkpoint has no table {name!r} of shape {tuple(parameter.shape)}"
                )
            parameter.copy_(stored)
    state: dict[int, dict[str, torch.Tensor]] = {}
    for index, (name, parameter) in enumerate(adapter.named_parameters()):
        entry = {}
        for key in ("step", "exp_avg", "exp_avg_sq"):
            stored = tensors.get(f"adam.{name}.{key}")
            if stored is not None:
                entry[key] = (
                    stored.reshape(()) if key == "step" else stored.reshape(parameter.shape).clone()
                )
        if entry:
            state[index] = entry
    optimizer.load_state_dict(
        {"state": state, "param_groups": optimizer.state_dict()["param_groups"]}
    )
    return int(metadata["step"])


def _rewrite_log(path: Path, keep_before: int) -> None:
    """Drop records of steps >= ``keep_before`` (they are redone after a resume)."""
    if not path.is_file():
        return
    kept = [
        line
        for line in path.read_text(encoding="utf-8").splitlines()
        if line.strip() and json.loads(line)["step"] < keep_before
    ]
    path.write_text("".join(line + "\n" for line in kept), encoding="utf-8")
