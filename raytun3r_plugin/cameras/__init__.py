"""Camera models and calibration readers.

Every model is an immutable :class:`Camera` with batched, differentiable torch ``project`` /
``unproject`` (unit rays, valid masks), whole-image helpers (``ray_table``, ``valid_mask``,
``fov_deg``), resize/crop and an exact JSON form. ``load`` reads Kalibr, basalt, COLMAP,
KITTI-360 (OpenCV YAML) and raytun3r's own JSON calibration files; ``fisheye`` builds the
equidistant-like synthetic lens of a given size and field of view. Every camera is validated
when it is built (bounds, domain, a float64 project/unproject round trip); ``validate`` re-runs
the checks and returns the round-trip error. See ``docs/cameras.md``.
"""

from __future__ import annotations

from raytun3r_plugin.cameras.base import Camera, pixel_grid, validate
from raytun3r_plugin.cameras.builders import fisheye, perturbed
from raytun3r_plugin.cameras.checks import (
    DISTORTION_BOUND,
    FOCAL_RANGE_PX,
    MAX_IMAGE_SIDE,
    PRINCIPAL_MARGIN,
    ROUND_TRIP_TOL_PX,
)
from raytun3r_plugin.cameras.fisheye624 import Fisheye624
from raytun3r_plugin.cameras.formats import load, save, to_colmap_line
from raytun3r_plugin.cameras.fov import FOV
from raytun3r_plugin.cameras.kb import KannalaBrandt4, ThinPrismFisheye
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan, Pinhole
from raytun3r_plugin.cameras.serialisation import CAMERA_MODELS, from_dict
from raytun3r_plugin.cameras.unified import EUCM, MEI, UCM, DoubleSphere

__all__ = [
    "CAMERA_MODELS",
    "DISTORTION_BOUND",
    "EUCM",
    "FOCAL_RANGE_PX",
    "MAX_IMAGE_SIDE",
    "PRINCIPAL_MARGIN",
    "ROUND_TRIP_TOL_PX",
    "FOV",
    "Fisheye624",
    "MEI",
    "UCM",
    "Camera",
    "DoubleSphere",
    "KannalaBrandt4",
    "OpenCVRadTan",
    "Pinhole",
    "ThinPrismFisheye",
    "fisheye",
    "perturbed",
    "from_dict",
    "load",
    "pixel_grid",
    "save",
    "to_colmap_line",
    "validate",
]
