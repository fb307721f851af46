"""Write a frozen model as an ONNX graph and run one with ONNX Runtime (the ``deploy`` extra).

The graph has one input, ``images`` (batch, views, 3, H, W) float32 in [0, 1], and three
outputs, ``depth`` (batch, views, H, W), ``confidence`` (same shape) and ``cam_from_world``
(batch, views, 4, 4), all of the shape it was frozen for. It needs neither raytun3r nor
PyTorch to run.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

import torch

from raytun3r_plugin.atomic_files import atomic_path
from raytun3r_plugin.deploy.freeze import FrozenModel
from raytun3r_plugin.errors import UnsupportedUpstreamError, require_module

INPUT_NAME = "images"
OUTPUT_NAMES = ("depth", "confidence", "cam_from_world")
#: Families whose frozen model has no ONNX graph, and why (checked before anything is written).
#: None today: Pi3's SVD and nested DA3's masked quantiles have export equivalents
#: (``freeze.EXPORT_EQUIVALENTS``); Pi3X and VGGT-Omega are refused by ``freeze`` already.
ONNX_BLOCKERS: dict[str, str] = {}


def _require(module: str):
    return require_module(module, "deploy", "exporting to ONNX")


def export_onnx(frozen: FrozenModel, path: str | os.PathLike, opset: int = 18) -> Path:
    """Write ``frozen`` as an ONNX file at ``path`` (atomically); returns the path.

    Uses ``torch.onnx.export(dynamo=True)`` (torch.export, then onnxscript), with the shapes
    ``frozen`` was frozen for; the weights are stored in the one file.
    """
    family = frozen.info.get("family")
    if family in ONNX_BLOCKERS:
        raise UnsupportedUpstreamError(
            f"{family} cannot be exported to ONNX: {ONNX_BLOCKERS[family]}"
        )
    for module in ("onnx", "onnxscript"):
        _require(module)
    example = torch.zeros(frozen.shape, device=next(frozen.parameters()).device)
    with (
        atomic_path(path) as temporary,
        warnings.catch_warnings(),
        contextlib.redirect_stdout(io.StringIO()),
    ):  # the exporter prints its progress and warns about deprecations of its own
        warnings.simplefilter("ignore")
        try:
            program = torch.onnx.export(
                frozen,
                (example,),
                dynamo=True,
                input_names=[INPUT_NAME],
                output_names=list(OUTPUT_NAMES),
                opset_version=opset,
                verbose=False,
            )
        except Exception as error:  # the exporter's own errors carry pages of context
            summary = str(error).strip().splitlines()
            raise UnsupportedUpstreamError(
                f"{family}: torch.onnx.export failed ({type(error).__name__}: {summary[0] if summary else ''}); "
                "the frozen model still runs in PyTorch"
            ) from error
        program.save(str(temporary), external_data=False)
    return Path(path)


def run_onnx(
    path: str | os.PathLike, images: torch.Tensor, threads: int = 1
) -> dict[str, torch.Tensor]:
    """Run the ONNX graph at ``path`` with ONNX Runtime on the CPU: outputs by name.

    images: (batch, views, 3, H, W) in [0, 1], the shape the graph was frozen for.
    """
    session = onnx_session(path, threads)
    outputs = session.run(None, {INPUT_NAME: images.detach().cpu().float().numpy()})
    names = [output.name for output in session.get_outputs()]
    return {name: torch.from_numpy(value) for name, value in zip(names, outputs, strict=True)}


def onnx_session(path: str | os.PathLike, threads: int = 1):
    """An ONNX Runtime CPU session of the graph at ``path`` with ``threads`` intra-op threads."""
    ort = _require("onnxruntime")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
