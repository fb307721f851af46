"""A Rerun recording of a prediction (``--export rerun``, rerun-sdk): ``recording.rrd``.

Entities, each frame logged at ``frame = k`` (sequence) and ``time`` (the frame's timestamp, s):

* ``frames/image``: the input frame (RGB); ``frames/depth``: its depth image in the chosen
  convention, in the scene's unit (``meter`` = 1: one depth unit is one world unit), 0 = unknown;
* ``world/points``: that frame's back-projected points (confidence-filtered, subsampled,
  coloured); ``world/camera``: the camera pose (``world_from_cam``, translation + 3x3);
  ``world/trajectory``: the camera centres so far;
* ``world`` is declared RDF (x right, y down, z forward: OpenCV axes); ``description`` (static)
  says the depth convention and why no camera model is logged.

No ``Pinhole`` is logged: Rerun cannot project through a fisheye lens (rerun-io/rerun #2315),
and a pinhole standing in for one would draw the frames and depth in the wrong place. The depth
images are shown as 2-D images and the geometry comes as 3-D points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from raytun3r_plugin.atomic_files import atomic_path
from raytun3r_plugin.exports import ExportOptions, ExportPlan, require
from raytun3r_plugin.exports.scene import ExportScene, depth_convention_text

__all__ = ["APPLICATION_ID", "ENTITIES", "REQUIRES", "plan", "write_rrd"]

#: Optional packages this export imports (``pip install 'raytun3r[viz]'``).
REQUIRES = ("rerun",)

#: The recording's application id (what the viewer groups recordings by).
APPLICATION_ID = "raytun3r"

#: Entity paths every recording holds.
ENTITIES = (
    "description",
    "frames/image",
    "frames/depth",
    "world",
    "world/points",
    "world/camera",
    "world/trajectory",
)

_NO_PINHOLE = (
    "No camera model is logged: Rerun cannot project through a fisheye lens "
    "(rerun-io/rerun issue 2315), so a Pinhole would place the images and depth wrongly. "
    "The geometry is logged as 3-D points in the world frame."
)


def write_rrd(path: str | Path, scene: ExportScene, options: ExportOptions) -> dict:
    """Write ``path`` (an .rrd recording); returns a record of what it holds."""
    rr = require("rerun")
    sample = scene.sample_points(
        options.max_points * len(scene), options.confidence_quantile, seed=0
    )
    depth = scene.depth_as(options.depth_convention)
    convention = depth_convention_text(options.depth_convention)
    stamps = np.arange(len(scene), dtype=float) if scene.timestamps is None else scene.timestamps
    centres = np.stack([scene.world_from_cam(k)[:3, 3] for k in range(len(scene))])
    recording = rr.RecordingStream(APPLICATION_ID)
    with atomic_path(path) as temporary:
        recording.save(str(temporary))
        text = (
            f"raytun3r prediction, {len(scene)} frames, camera {scene.camera.model} "
            f"{scene.camera.width}x{scene.camera.height} px.\n\nDepth images: {convention} "
            f"(unit: {scene.depth_unit}; 0 = unknown).\n\nWorld axes: OpenCV (x right, y down, "
            f"z forward) of the backbone's first frame.\n\n{_NO_PINHOLE}"
        )
        recording.log("description", rr.TextDocument(text), static=True)
        recording.log("world", rr.ViewCoordinates.RDF, static=True)
        for k in range(len(scene)):
            recording.set_time("frame", sequence=k)
            recording.set_time("time", duration=float(stamps[k]))
            image = (np.clip(scene.images[k], 0, 1) * 255 + 0.5).astype(np.uint8)
            recording.log("frames/image", rr.Image(image))
            recording.log("frames/depth", rr.DepthImage(depth[k], meter=1.0))
            here = sample.frame == k
            colours = (np.clip(sample.rgb[here], 0, 1) * 255 + 0.5).astype(np.uint8)
            recording.log("world/points", rr.Points3D(sample.xyz[here], colors=colours))
            pose = scene.world_from_cam(k)
            recording.log(
                "world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3])
            )
            recording.log("world/trajectory", rr.LineStrips3D([centres[: k + 1]]))
        recording.flush()
        recording.disconnect()
    return {
        "file": str(path),
        "entities": list(ENTITIES),
        "frames": len(scene),
        "points": int(len(sample)),
        "depth_convention": options.depth_convention,
        "pinhole": "none: Rerun cannot project through a fisheye lens (rerun-io/rerun #2315)",
    }


def plan(scene: ExportScene, options: ExportOptions) -> ExportPlan:
    """Check rerun-sdk is installed; write later."""
    require("rerun")
    return ExportPlan(
        "rerun",
        lambda out: write_rrd(Path(out) / "recording.rrd", scene, options),
        [
            "rerun: no Pinhole logged (Rerun cannot project a fisheye); depth as 2-D images, geometry as 3-D points"
        ],
    )
