"""raytun3r: run frozen pinhole-trained 3D foundation models on fisheye cameras."""

from __future__ import annotations

from raytun3r_plugin._layout import check_installed_layout  # noqa: E402
from raytun3r_plugin._version import __version__
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

# Before anything can import the patch modules: a mixed install must fail here, not in a test.
check_installed_layout()

from raytun3r_plugin.adapter import Adapter  # noqa: E402
from raytun3r_plugin.patching import RaytunHandle, apply, handle_of, remove  # noqa: E402
from raytun3r_plugin.prediction import Prediction, predict  # noqa: E402
from raytun3r_plugin.weights import available_backbones, load_backbone  # noqa: E402

# Subpackages and modules reachable as ``rt.<name>`` without importing them here: they pull in
# cv2, the upstream backbones or the adaptation code, and ``import raytun3r_plugin`` stays cheap.
_LAZY_SUBMODULES = frozenset(
    {
        "adaptation",
        "apps",
        "cameras",
        "datasets",
        "geometry",
        "hooks",
        "images",
        "metrics",
        "patches",
        "patching",
        "prediction",
        "preprocess",
        "registry",
        "rope",
        "synthetic",
        "weights",
    }
)


def __getattr__(name: str):
    """Import ``raytun3r_plugin.<name>`` on first use (PEP 562), e.g. ``rt.cameras.load(...)``."""
    if name in _LAZY_SUBMODULES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | _LAZY_SUBMODULES)


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
