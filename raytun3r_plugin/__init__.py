"""raytun3r: run frozen pinhole-trained 3D foundation models on fisheye cameras."""

from __future__ import annotations

from raytun3r_plugin.errors import (
    AdapterError,
    AlreadyAppliedError,
    CameraError,
    DatasetError,
    InputError,
    MissingDependencyError,
    NotAppliedError,
    PatchedCopyError,
    Raytun3rError,
    SplitInstallError,
    UnsupportedUpstreamError,
    WeightsError,
)

__version__ = "0.1.0"

from raytun3r_plugin._layout import check_installed_layout  # noqa: E402

# Before anything can import the patch modules: a mixed install must fail here, not in a test.
check_installed_layout()

from raytun3r_plugin.adapter import Adapter  # noqa: E402
from raytun3r_plugin.patching import RaytunHandle, apply, handle_of, remove  # noqa: E402
from raytun3r_plugin.prediction import Prediction, predict  # noqa: E402
from raytun3r_plugin.weights import available_backbones, load_backbone  # noqa: E402

__all__ = [
    "Adapter",
    "Prediction",
    "RaytunHandle",
    "apply",
    "available_backbones",
    "handle_of",
    "load_backbone",
    "predict",
    "remove",
    "AdapterError",
    "AlreadyAppliedError",
    "CameraError",
    "DatasetError",
    "InputError",
    "MissingDependencyError",
    "NotAppliedError",
    "PatchedCopyError",
    "Raytun3rError",
    "SplitInstallError",
    "UnsupportedUpstreamError",
    "WeightsError",
    "__version__",
]
