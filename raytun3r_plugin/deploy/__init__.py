"""Deployment of an adapted model for one fixed camera and input size (docs/deployment.md).

:func:`freeze` turns a patched model into a plain module whose camera- and size-only values are
constant buffers; :func:`export_onnx` writes it as an ONNX graph (the ``deploy`` extra).
"""

from raytun3r_plugin.deploy.freeze import SUPPORTED, FrozenModel, freeze
from raytun3r_plugin.deploy.onnx import export_onnx, run_onnx

__all__ = ["SUPPORTED", "FrozenModel", "export_onnx", "freeze", "run_onnx"]
