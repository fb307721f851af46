"""Image sequences with ground truth: one :class:`Sequence` type and readers for raytun3r's own
folder format (synthetic data), COLMAP text models (ETH3D, ScanNet++ DSLR), nerfstudio
``transforms.json`` (ScanNet++), TUM-VI (ASL/EuRoC layout), KITTI-360 fisheye cameras, ETH3D
multi-camera-rig scenes, Aria Digital Twin (Project Aria calibration JSON) and FIORD scenes (in
the layout Wid3R's evaluation reads).

Every reader returns a :class:`Sequence` and raises :class:`~raytun3r_plugin.errors.DatasetError`
naming the file (and the line) on missing or malformed input. See
``docs/synthetic_and_datasets.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from raytun3r_plugin.datasets.aria import load_adt, read_aria_calibration, read_aria_trajectory
from raytun3r_plugin.datasets.colmap import load_colmap, read_images_bin, read_images_txt
from raytun3r_plugin.datasets.eth3d import eth3d_rig_cameras, load_eth3d_rig, load_eth3d_rig_all
from raytun3r_plugin.datasets.fiord import is_fiord_scene, load_fiord
from raytun3r_plugin.datasets.folder import load_synthetic, write_sequence
from raytun3r_plugin.datasets.kitti360 import load_kitti360
from raytun3r_plugin.datasets.rig import Rig, load_eth3d_rig_set, load_tumvi_rig, rig_from_sequences
from raytun3r_plugin.datasets.scannetpp import load_scannetpp_transforms
from raytun3r_plugin.datasets.sequence import Sequence, read_image
from raytun3r_plugin.datasets.tumvi import load_tumvi
from raytun3r_plugin.errors import DatasetError

__all__ = [
    "KINDS",
    "Rig",
    "Sequence",
    "detect_kind",
    "eth3d_rig_cameras",
    "load_adt",
    "load_colmap",
    "load_eth3d_rig",
    "load_eth3d_rig_all",
    "load_eth3d_rig_set",
    "load_fiord",
    "load_kitti360",
    "load_scannetpp_transforms",
    "load_sequence",
    "load_synthetic",
    "load_tumvi",
    "load_tumvi_rig",
    "read_aria_calibration",
    "rig_from_sequences",
    "read_aria_trajectory",
    "read_image",
    "read_images_bin",
    "read_images_txt",
    "write_sequence",
]

KINDS = ("synthetic", "colmap", "scannetpp", "tumvi", "kitti360", "eth3d_rig", "adt", "fiord")


def detect_kind(path: str | Path) -> str:
    """Guess the dataset kind of ``path`` from the files it holds (see :func:`load_sequence`)."""
    p = Path(path)
    if p.is_file():
        if p.name.endswith(".json") and p.name != "meta.json":
            return "scannetpp"
        if p.name == "meta.json":
            return "synthetic"
        raise DatasetError(f"{p}: cannot tell the dataset kind of this file")
    if (p / "meta.json").is_file():
        return "synthetic"
    if (p / "transforms.json").is_file() or (p / "nerfstudio" / "transforms.json").is_file():
        return "scannetpp"
    if (p / "mav0").is_dir():
        return "tumvi"
    if (p / "calibration").is_dir() and (p / "data_poses").is_dir():
        return "kitti360"
    if (p / "rig_calibration" / "images.txt").is_file() or (
        p / "rig_calibration_undistorted" / "images.txt"
    ).is_file():
        return "eth3d_rig"
    if (p / "aria_trajectory.csv").is_file():
        return "adt"
    if is_fiord_scene(p):
        return "fiord"
    for sub in (p, p / "sparse" / "0", p / "sparse", p / "colmap", p / "dslr_calibration_jpg"):
        if (sub / "images.txt").is_file() and (sub / "cameras.txt").is_file():
            return "colmap"
    raise DatasetError(
        f"{p}: cannot tell the dataset kind (no meta.json, transforms.json, mav0/, "
        "calibration/ + data_poses/, rig_calibration/, aria_trajectory.csv, images_180/ + "
        "colmap/model/ (FIORD), or cameras.txt + images.txt)"
    )


def load_sequence(path: str | Path, kind: str | None = None, **kw: Any) -> Sequence:
    """Load a sequence of any supported kind.

    Args:
        path: the dataset folder (or file, for ``meta.json`` / ``transforms.json``).
        kind: one of :data:`KINDS`; detected from the content when None.
        **kw: passed to the reader (``load_kitti360`` needs ``sequence=`` unless ``data_poses``
            holds a single sequence; ``load_eth3d_rig`` needs ``camera=`` when the rig has
            several cameras, and reads ``rig_calibration_undistorted`` with ``undistorted=True``
            or when only that one exists; ``load_fiord`` needs ``camera=``).
    """
    p = Path(path)
    kind = kind or detect_kind(p)
    if kind == "synthetic":
        return load_synthetic(p.parent if p.is_file() else p, **kw)
    if kind == "colmap":
        return load_colmap(p, **kw)
    if kind == "scannetpp":
        if p.is_dir() and not (p / "transforms.json").is_file():
            p = p / "nerfstudio"
        return load_scannetpp_transforms(p, **kw)
    if kind == "tumvi":
        return load_tumvi(p, **kw)
    if kind == "kitti360":
        if "sequence" not in kw:
            seqs = sorted(d.name for d in (p / "data_poses").iterdir() if d.is_dir())
            if len(seqs) != 1:
                raise DatasetError(
                    f"{p / 'data_poses'}: {len(seqs)} sequences {seqs[:5]}; pass sequence="
                )
            kw["sequence"] = seqs[0]
        return load_kitti360(p, **kw)
    if kind == "eth3d_rig":
        if "undistorted" not in kw and not (p / "rig_calibration" / "images.txt").is_file():
            kw["undistorted"] = True
        return load_eth3d_rig(p, **kw)
    if kind == "adt":
        return load_adt(p, **kw)
    if kind == "fiord":
        return load_fiord(p, **kw)
    raise DatasetError(f"unknown dataset kind {kind!r}; expected one of {KINDS}")
