"""Multi-camera rigs: time-aligned sequences of several cameras with their fixed extrinsics.

A :class:`Rig` holds one :class:`~raytun3r_plugin.datasets.sequence.Sequence` per camera, frame
``k`` of every one taken at one instant, and ``cam_from_rig[name]`` (4, 4), the transform from
the rig frame (the reference camera's, whose own transform is the identity) to each camera.
:meth:`Rig.views` lays the frames out for a rig forward (``apply(model, rig.cameras, ...)``):
instant-major, camera-minor, so view ``s`` belongs to camera ``s % V`` (docs/rigs.md).

Builders: :func:`rig_from_sequences` (align by timestamp, extrinsics given or measured from the
ground-truth poses), :func:`load_tumvi_rig` (cam0 + cam1, extrinsics from the Kalibr camchain)
and :func:`load_eth3d_rig_set` (every camera of an ETH3D rig scene).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from raytun3r_plugin.datasets._common import invert_pose
from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import DatasetError
from raytun3r_plugin.poses import rotation_angle

__all__ = ["Rig", "load_eth3d_rig_set", "load_tumvi_rig", "rig_from_sequences"]

#: Largest spread (metres, degrees) of the per-instant camera-from-reference transforms that
#: :func:`rig_from_sequences` accepts as one rigid rig.
RIGID_TOLERANCE_M = 1e-3
RIGID_TOLERANCE_DEG = 0.1


@dataclass
class Rig:
    """Time-aligned sequences of the cameras of one rig.

    Attributes:
        name: human-readable name.
        sequences: camera name -> :class:`Sequence`; all the same length, frame ``k`` of each
            taken at instant ``k``. The first entry is the reference camera.
        cam_from_rig: camera name -> (4, 4) float64 transform from the rig (reference camera)
            frame to that camera; the reference's is the identity.
        meta: free-form information (sources, alignment residuals).
    """

    name: str
    sequences: dict[str, Sequence]
    cam_from_rig: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.sequences:
            raise DatasetError(f"rig {self.name!r}: no camera")
        lengths = {name: len(seq) for name, seq in self.sequences.items()}
        if len(set(lengths.values())) != 1:
            raise DatasetError(f"rig {self.name!r}: cameras have different frame counts {lengths}")
        if set(self.cam_from_rig) != set(self.sequences):
            raise DatasetError(
                f"rig {self.name!r}: extrinsics for {sorted(self.cam_from_rig)}, cameras "
                f"{sorted(self.sequences)}"
            )
        self.cam_from_rig = {
            name: np.asarray(self.cam_from_rig[name], dtype=np.float64) for name in self.sequences
        }
        for name, transform in self.cam_from_rig.items():
            if transform.shape != (4, 4) or not np.isfinite(transform).all():
                raise DatasetError(f"rig {self.name!r}: cam_from_rig[{name!r}] is not a finite 4x4")

    @property
    def names(self) -> list[str]:
        """Camera names, reference first (the order of :meth:`views` and :attr:`cameras`)."""
        return list(self.sequences)

    @property
    def cameras(self) -> list:
        """One camera per rig camera, in :attr:`names` order: ``apply(model, rig.cameras, ...)``."""
        return [seq.camera for seq in self.sequences.values()]

    def __len__(self) -> int:
        return len(next(iter(self.sequences.values())))

    def views(self, instants: Any) -> np.ndarray:
        """(T V, H, W, 3) float32 frames of ``instants`` for a rig forward: instant-major.

        View ``t V + c`` is camera ``c`` (in :attr:`names` order) at instant ``instants[t]``,
        which is the order ``apply(model, rig.cameras, ...)`` expects.
        """
        instants = [int(i) for i in np.atleast_1d(instants)]
        frames = [seq.image(i) for i in instants for seq in self.sequences.values()]
        shapes = {frame.shape for frame in frames}
        if len(shapes) != 1:
            raise DatasetError(
                f"rig {self.name!r}: the cameras' frames differ in size {sorted(shapes)}; a rig "
                "forward needs one size (resize or crop them to a common one first)"
            )
        return np.stack(frames).astype(np.float32)

    def inputs(
        self, instants: Any, long_side: int | None = None, patch: int = 14
    ) -> tuple[torch.Tensor, list]:
        """Network input of ``instants`` and the camera list to ``apply`` with it.

        Each camera's frames are prepared by its own
        :class:`~raytun3r_plugin.preprocess.InputLayout` (the rule ``adapt`` and ``infer`` use:
        resize, a centred crop only for another aspect ratio), so they match what
        :func:`~raytun3r_plugin.adaptation.rig.adapt_rig` fitted on.

        Returns:
            ``(images, cameras)``: (1, T V, 3, h, w) float32 in [0, 1], instant-major like
            :meth:`views`, and one (cropped) native camera per rig camera.

        Raises:
            DatasetError: the cameras' layouts give different input sizes.
        """
        from raytun3r_plugin.preprocess import DEFAULT_LONG_SIDE, InputLayout

        instants = [int(i) for i in np.atleast_1d(instants)]
        layouts = [
            InputLayout.for_camera(seq.camera, long_side or DEFAULT_LONG_SIDE, patch)
            for seq in self.sequences.values()
        ]
        sizes = {(layout.width, layout.height) for layout in layouts}
        if len(sizes) != 1:
            raise DatasetError(
                f"rig {self.name!r}: the cameras give network inputs of {sorted(sizes)} px; a rig "
                "forward needs one size"
            )
        per_camera = [
            layout.frames(np.stack([seq.image(i) for i in instants]))
            for layout, seq in zip(layouts, self.sequences.values(), strict=True)
        ]
        views = torch.stack(per_camera, dim=1).flatten(0, 1)  # (T, V, ...) -> instant-major
        return views[None], [layout.native_camera for layout in layouts]

    def subset(self, instants: Any) -> Rig:
        """The rig restricted to ``instants`` (every camera's frames sliced alike)."""
        return Rig(
            self.name,
            {name: seq.subset(instants) for name, seq in self.sequences.items()},
            dict(self.cam_from_rig),
            dict(self.meta),
        )


def rig_from_sequences(
    sequences: Mapping[str, Sequence],
    cam_from_rig: Mapping[str, np.ndarray] | None = None,
    *,
    max_dt: float = 0.005,
    name: str | None = None,
) -> Rig:
    """A :class:`Rig` from per-camera sequences: frames matched by timestamp, extrinsics checked.

    Args:
        sequences: camera name -> sequence; the first is the reference camera.
        cam_from_rig: the extrinsics (reference -> camera); None measures them from the
            ground-truth poses (the median over the shared instants, refused when they spread
            by more than :data:`RIGID_TOLERANCE_M` / :data:`RIGID_TOLERANCE_DEG`).
        max_dt: seconds: a reference frame is kept only when every camera has a frame this close.
        name: the rig's name (default: the reference sequence's, without its camera part).

    Raises:
        DatasetError: no shared instant, no poses to measure the extrinsics from, or poses that
            do not form a rigid rig.
    """
    if not sequences:
        raise DatasetError("a rig needs at least one camera sequence")
    names = list(sequences)
    reference = sequences[names[0]]
    picks: dict[str, list[int]] = {camera: [] for camera in names}
    for index, time in enumerate(reference.timestamps):
        matched = {}
        for camera in names:
            stamps = sequences[camera].timestamps
            nearest = int(np.argmin(np.abs(stamps - time))) if stamps.size else -1
            if nearest < 0 or abs(stamps[nearest] - time) > max_dt:
                break
            matched[camera] = nearest
        else:
            for camera in names:
                picks[camera].append(matched[camera] if camera != names[0] else index)
    if not picks[names[0]]:
        raise DatasetError(
            f"rig {names}: no instant where every camera has a frame within {max_dt * 1e3:g} ms"
        )
    aligned = {camera: sequences[camera].subset(picks[camera]) for camera in names}
    meta: dict[str, Any] = {"max_dt": max_dt, "instants": len(picks[names[0]])}
    if cam_from_rig is None:
        cam_from_rig, meta["extrinsics"] = _measured_extrinsics(aligned)
    label = name or reference.name.rsplit("/", 1)[0]
    return Rig(label, aligned, dict(cam_from_rig), meta)


def _measured_extrinsics(aligned: dict[str, Sequence]) -> tuple[dict[str, np.ndarray], dict]:
    names = list(aligned)
    reference = aligned[names[0]].cam_from_world
    if reference is None or any(aligned[c].cam_from_world is None for c in names):
        raise DatasetError(
            "the rig's extrinsics are needed: give cam_from_rig, or sequences with poses"
        )
    extrinsics, spread = {}, {}
    for camera in names:
        relative = aligned[camera].cam_from_world @ invert_pose(reference)
        centre = np.median(relative, axis=0)
        u, _s, vt = np.linalg.svd(centre[:3, :3])
        rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        transform = np.eye(4)
        transform[:3, :3], transform[:3, 3] = rotation, centre[:3, 3]
        metres = float(np.abs(relative[:, :3, 3] - transform[:3, 3]).max())
        degrees = float(np.degrees(rotation_angle(relative[:, :3, :3], rotation).max()))
        if metres > RIGID_TOLERANCE_M or degrees > RIGID_TOLERANCE_DEG:
            raise DatasetError(
                f"camera {camera!r} moves against {names[0]!r} by up to {metres * 1e3:.3g} mm / "
                f"{degrees:.3g} deg over the sequence (tolerance {RIGID_TOLERANCE_M * 1e3:g} mm / "
                f"{RIGID_TOLERANCE_DEG:g} deg): the poses do not form a rigid rig"
            )
        extrinsics[camera] = transform
        spread[camera] = {"max_dev_m": metres, "max_dev_deg": degrees}
    return extrinsics, {"measured_from": "ground-truth poses", "spread": spread}


def load_tumvi_rig(
    folder: str | Path, cams: tuple[str, ...] = ("cam0", "cam1"), **kwargs: Any
) -> Rig:
    """The stereo fisheye pair of a TUM-VI sequence as a :class:`Rig` (reference ``cams[0]``).

    The extrinsics come from the camchain's ``T_cam_imu`` of each camera (``T_cam_imu(c) @
    T_cam_imu(cams[0])^-1``), not from the mocap; ``kwargs`` go to
    :func:`~raytun3r_plugin.datasets.tumvi.load_tumvi`.
    """
    from raytun3r_plugin.datasets.tumvi import _find_camchain, _t_cam_imu, load_tumvi

    root = Path(folder)
    camchain = _find_camchain(root, kwargs.pop("camchain", None))
    sequences = {cam: load_tumvi(root, cam=cam, camchain=camchain, **kwargs) for cam in cams}
    reference = _t_cam_imu(camchain, cams[0])
    extrinsics = {cam: _t_cam_imu(camchain, cam) @ invert_pose(reference) for cam in cams}
    rig = rig_from_sequences(sequences, extrinsics, name=root.name)
    rig.meta.update({"source": str(root), "format": "tumvi", "extrinsics": "camchain T_cam_imu"})
    return rig


def load_eth3d_rig_set(scene: str | Path, undistorted: bool = False, **kwargs: Any) -> Rig:
    """Every camera of an ETH3D rig scene as a :class:`Rig` (reference: the reader's).

    The extrinsics are the reader's ``meta["rig"]["cam_from_ref"]`` (measured from the
    per-image ground-truth poses); frames are matched by their shared timestamps.
    """
    from raytun3r_plugin.datasets.eth3d import load_eth3d_rig_all

    sequences = load_eth3d_rig_all(scene, undistorted=undistorted, **kwargs)
    references = {seq.meta["rig"]["ref_camera"] for seq in sequences.values()}
    reference = next(iter(references)) if len(references) == 1 else None
    if reference is None or reference not in sequences:
        raise DatasetError(f"{scene}: the rig's reference camera is not among {sorted(sequences)}")
    ordered = {reference: sequences[reference]}
    ordered.update({name: seq for name, seq in sequences.items() if name != reference})
    extrinsics = {}
    for name, seq in ordered.items():
        transform = seq.meta["rig"]["cam_from_ref"]
        if transform is None:
            raise DatasetError(f"{scene}: camera {name!r} shares no timestamp with {reference!r}")
        extrinsics[name] = transform
    rig = rig_from_sequences(ordered, extrinsics, max_dt=1e-6, name=Path(scene).name)
    rig.meta.update({"source": str(scene), "format": "eth3d_rig"})
    return rig
