"""``raytun3r infer``'s output options: resolution, depth convention and the exports
(COLMAP, nerfstudio, GLB, Rerun; :mod:`raytun3r_plugin.exports`)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from raytun3r_plugin.exports import DEPTH_CONVENTIONS, FORMATS, ExportOptions, check_formats
from raytun3r_plugin.exports.lens import COLMAP_LENS_CHOICES, DEFAULT_MAX_FIT_ERROR_PX

if TYPE_CHECKING:
    import numpy as np
    import torch

    from raytun3r_plugin.prediction import Prediction
    from raytun3r_plugin.preprocess import InputLayout

__all__ = ["add_output_arguments", "export_names", "export_options", "write_infer_outputs"]


def add_output_arguments(parser: argparse.ArgumentParser) -> None:
    """Register ``--export``, ``--depth-convention``, ``--depth-resolution`` and the export
    settings on ``infer``'s sub-parser."""
    parser.add_argument(
        "--export",
        action="append",
        default=[],
        metavar="FORMAT",
        help=f"also write this format (repeat or comma-separate): {', '.join(FORMATS)} "
        "(docs/exports.md)",
    )
    parser.add_argument(
        "--depth-convention",
        choices=DEPTH_CONVENTIONS,
        default="range",
        help="range: distance along each pixel's ray (exists for every ray of a fisheye); "
        "z: distance along the optical axis (0 beyond 90 degrees); default range",
    )
    parser.add_argument(
        "--depth-resolution",
        choices=("frames", "network"),
        default="frames",
        help="write depth at the frames' resolution (resampled inside the camera's valid "
        "region; default) or at the network input's",
    )
    parser.add_argument(
        "--max-points",
        type=int,
        default=ExportOptions.max_points,
        help="3-D points in the COLMAP, GLB and Rerun exports (default %(default)s)",
    )
    parser.add_argument(
        "--confidence-quantile",
        type=float,
        default=ExportOptions.confidence_quantile,
        help="drop each frame's pixels below this confidence quantile from the exported "
        "points (default %(default)s)",
    )
    parser.add_argument(
        "--max-fit-error-px",
        type=float,
        default=DEFAULT_MAX_FIT_ERROR_PX,
        help="a lens a format has no model for is fitted as OPENCV_FISHEYE; refuse when the "
        "fit misses by more than this many pixels (default %(default)s)",
    )
    parser.add_argument(
        "--colmap-lens",
        choices=COLMAP_LENS_CHOICES,
        default="native",
        help="native: COLMAP's own model where it has one (EUCM and RAD_TAN_THIN_PRISM_FISHEYE "
        "need COLMAP 4.1+); opencv-fisheye: only PINHOLE, OPENCV, OPENCV_FISHEYE, other lenses "
        "fitted (gsplat's COLMAP loader, older COLMAP)",
    )


def export_names(args: argparse.Namespace) -> list[str]:
    """The formats of every ``--export`` (repeated or comma-separated), each once, checked
    (known, optional package installed: :func:`~raytun3r_plugin.exports.check_formats`)."""
    names = [part.strip() for value in args.export for part in value.split(",") if part.strip()]
    return check_formats(names)


def export_options(args: argparse.Namespace) -> ExportOptions:
    """The :class:`~raytun3r_plugin.exports.ExportOptions` of the command line (checked, with
    the ``--export`` names)."""
    export_names(args)
    return ExportOptions(
        depth_convention=args.depth_convention,
        max_points=args.max_points,
        confidence_quantile=args.confidence_quantile,
        max_fit_error_px=args.max_fit_error_px,
        colmap_lens=args.colmap_lens,
    )


def write_infer_outputs(
    args: argparse.Namespace,
    options: ExportOptions,
    prediction: Prediction,
    images: torch.Tensor,
    layout: InputLayout,
    frames: np.ndarray,
    names: list[str],
    raw_mask: np.ndarray | None = None,
) -> dict:
    """Write ``infer``'s files at the resolution ``--depth-resolution`` asks for, and say what
    was written (the lens notes of each export first)."""
    from raytun3r_plugin.apps.inference import write_outputs

    at_frames = args.depth_resolution == "frames"
    x0, y0, width, height = layout.crop or (0, 0, frames.shape[2], frames.shape[1])
    if raw_mask is None:
        mask = None
    else:
        mask = layout.native_mask(raw_mask) if at_frames else layout.mask(raw_mask)
    summary = write_outputs(
        args.out,
        prediction,
        images,
        layout.camera,
        names,
        frames=frames[:, y0 : y0 + height, x0 : x0 + width] if at_frames else None,
        frames_camera=layout.native_camera if at_frames else None,
        mask=mask,
        depth_convention=options.depth_convention,
        exports=export_names(args),
        export_options=options,
    )
    for note in summary["notes"]:
        print(note)
    depth = summary["depth"]
    where = "the frames'" if depth["resolution"] == "frames" else "the network's"
    print(
        f"wrote {depth['convention']} depth at {where} resolution ({depth['width']}x{depth['height']} px) "
        f"for {summary['frames']} frames, trajectory.txt and points.ply ({summary['points']:,} points) "
        f"to {args.out}"
    )
    for name, record in summary["exports"].items():
        print(f"{name}: {record.get('folder') or record.get('file')}")
    return summary
