"""Writing a prediction for the tools that come next: COLMAP, nerfstudio / gsplat, GLB, Rerun.

Every writer reads one :class:`ExportScene` (frames, range depth, confidence, poses and the
camera, at the frames' resolution by default) and states its depth convention. A format is
*planned* first (:func:`plan_exports`: options checked, the lens decided or fitted, optional
packages imported), and only when every plan stands is anything written, so a refused export
leaves the output folder as it was. See docs/exports.md.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from raytun3r_plugin.errors import InputError, require_module
from raytun3r_plugin.exports.lens import COLMAP_LENS_CHOICES, DEFAULT_MAX_FIT_ERROR_PX
from raytun3r_plugin.exports.scene import (
    DEPTH_CONVENTIONS,
    ExportScene,
    PointSample,
    check_depth_convention,
)

__all__ = [
    "DEPTH_CONVENTIONS",
    "FORMATS",
    "ExportOptions",
    "ExportPlan",
    "ExportScene",
    "PointSample",
    "check_formats",
    "plan_exports",
    "require",
]

#: ``--export`` names and the module that writes each.
FORMATS = {
    "colmap": "raytun3r_plugin.exports.colmap",
    "nerfstudio": "raytun3r_plugin.exports.nerfstudio",
    "glb": "raytun3r_plugin.exports.glb",
    "rerun": "raytun3r_plugin.exports.rrd",
}


@dataclass(frozen=True)
class ExportOptions:
    """Settings shared by the exports.

    Attributes:
        depth_convention: ``range`` or ``z`` for every depth image written.
        max_points: at most this many 3-D points (COLMAP points3D, GLB, Rerun per frame).
        confidence_quantile: per frame, drop pixels below this confidence quantile.
        max_fit_error_px: a lens the format has no model for is fitted as OPENCV_FISHEYE and
            refused when its worst reprojection error over the valid image exceeds this.
        colmap_lens: ``native`` (COLMAP's own model where it has one) or ``opencv-fisheye``
            (only PINHOLE, OPENCV, OPENCV_FISHEYE; the rest fitted), see
            :data:`~raytun3r_plugin.exports.lens.COLMAP_LENS_CHOICES`.
    """

    depth_convention: str = "range"
    max_points: int = 50_000
    confidence_quantile: float = 0.2
    max_fit_error_px: float = DEFAULT_MAX_FIT_ERROR_PX
    colmap_lens: str = "native"

    def __post_init__(self) -> None:
        check_depth_convention(self.depth_convention)
        if self.max_points < 1:
            raise InputError(f"max_points must be at least 1, got {self.max_points}")
        if not 0.0 <= self.confidence_quantile < 1.0:
            raise InputError(
                f"confidence quantile must be in [0, 1), got {self.confidence_quantile}"
            )
        if not self.max_fit_error_px > 0:
            raise InputError(f"max fit error must be > 0 px, got {self.max_fit_error_px}")
        if self.colmap_lens not in COLMAP_LENS_CHOICES:
            raise InputError(
                f"COLMAP lens must be one of {list(COLMAP_LENS_CHOICES)}, got {self.colmap_lens!r}"
            )


@dataclass
class ExportPlan:
    """One export, decided and ready: ``write(out_dir)`` writes it and returns its record.

    ``notes`` are lines for the user (a fitted lens and its error, rays COLMAP cannot take).
    """

    name: str
    write: Callable[[Path], dict]
    notes: list[str] = field(default_factory=list)


def require(module: str):
    """Import an export's optional package (the ``viz`` extra)."""
    return require_module(module, "viz", "this export")


def check_formats(formats: Iterable[str]) -> list[str]:
    """The formats, each once, after checking each is known and its optional package installed
    (so a command can refuse before it runs the network).

    Raises:
        InputError: an unknown format.
        MissingDependencyError: a format's optional package is missing.
    """
    names = list(dict.fromkeys(formats))
    unknown = [name for name in names if name not in FORMATS]
    if unknown:
        raise InputError(f"unknown export {unknown}; choose from {sorted(FORMATS)}")
    for name in names:
        for package in getattr(importlib.import_module(FORMATS[name]), "REQUIRES", ()):
            require(package)
    return names


def plan_exports(
    scene: ExportScene, formats: Iterable[str], options: ExportOptions
) -> dict[str, ExportPlan]:
    """Check and decide every export in ``formats`` (each once, in order) without writing.

    Raises:
        InputError: an unknown format, or a lens the format cannot take within the options.
        MissingDependencyError: a format's optional package is missing.
    """
    names = check_formats(formats)
    plans = {}
    for name in names:
        module = importlib.import_module(FORMATS[name])
        plans[name] = module.plan(scene, options)
    return plans
