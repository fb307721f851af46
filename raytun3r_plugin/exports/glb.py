"""A GLB scene of a prediction: the coloured point cloud and one frustum per frame
(``--export glb``, trimesh).

Writes ``scene.glb`` with a node ``points`` (a point cloud: back-projected predicted depth,
confidence-filtered and subsampled, the frames' colours) and a node ``camera_<name>`` per frame
(a pyramid mesh: apex at the camera centre, base a square one :data:`FRUSTUM_SCALE` of the
scene's size ahead, spanning up to 45 degrees off the axis; a fisheye's real field of view
does not fit a frustum). glTF is y-up: every coordinate is the backbone's world frame with y and
z negated (OpenCV -> glTF axes, :data:`GLTF_FROM_WORLD`), so the scene stands upright in
viewers when the first camera was upright. A GLB holds no depth maps; the depth convention
does not apply, and the points are the same under either convention.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from raytun3r_plugin.atomic_files import atomic_write_bytes
from raytun3r_plugin.exports import ExportOptions, ExportPlan, require
from raytun3r_plugin.exports.scene import ExportScene

__all__ = ["FRUSTUM_SCALE", "GLTF_FROM_WORLD", "REQUIRES", "frustum_vertices", "plan", "write_glb"]

#: Optional packages this export imports (``pip install 'raytun3r[viz]'``).
REQUIRES = ("trimesh",)

#: World (OpenCV axes: x right, y down, z forward) -> glTF (x right, y up, z toward the viewer).
GLTF_FROM_WORLD = np.diag([1.0, -1.0, -1.0])

#: Frustum depth as a fraction of the point cloud's bounding-box diagonal.
FRUSTUM_SCALE = 0.05

_FRUSTUM_FACES = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
_FRUSTUM_COLOUR = (255, 96, 0, 255)


def frustum_vertices(world_from_cam: np.ndarray, depth: float, half_angle_deg: float) -> np.ndarray:
    """(5, 3) world vertices of a frustum: the camera centre, then the base corners at camera
    coordinates (+-d tan a, +-d tan a, d), in the order (+,+), (+,-), (-,-), (-,+)."""
    side = depth * math.tan(math.radians(half_angle_deg))
    corners = np.array(
        [
            [0, 0, 0],
            [side, side, depth],
            [side, -side, depth],
            [-side, -side, depth],
            [-side, side, depth],
        ],
        dtype=np.float64,
    )
    return corners @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def write_glb(path: str | Path, scene: ExportScene, options: ExportOptions) -> dict:
    """Write ``path`` (a .glb); returns a record of what it holds."""
    trimesh = require("trimesh")
    sample = scene.sample_points(options.max_points, options.confidence_quantile)
    points = sample.xyz @ GLTF_FROM_WORLD.T
    colours = np.concatenate(
        [
            (np.clip(sample.rgb, 0, 1) * 255 + 0.5).astype(np.uint8),
            np.full((len(sample), 1), 255, np.uint8),
        ],
        axis=1,
    )
    glb = trimesh.Scene()
    glb.add_geometry(
        trimesh.PointCloud(points, colors=colours), geom_name="points", node_name="points"
    )
    span = float(np.linalg.norm(np.ptp(sample.xyz, axis=0))) if len(sample) > 1 else 1.0
    half_angle = min(45.0, scene.camera.fov_deg / 2)
    for k, name in enumerate(scene.names):
        vertices = frustum_vertices(scene.world_from_cam(k), FRUSTUM_SCALE * span, half_angle)
        mesh = trimesh.Trimesh(
            vertices=vertices @ GLTF_FROM_WORLD.T,
            faces=_FRUSTUM_FACES,
            vertex_colors=np.tile(_FRUSTUM_COLOUR, (5, 1)).astype(np.uint8),
            process=False,
        )
        glb.add_geometry(mesh, geom_name=f"camera_{name}", node_name=f"camera_{name}")
    atomic_write_bytes(path, glb.export(file_type="glb"))
    return {
        "file": str(path),
        "points": len(sample),
        "cameras": len(scene),
        "axes": "glTF: world x, -y, -z (OpenCV world turned y-up)",
        "depth_convention": "none (points only)",
    }


def plan(scene: ExportScene, options: ExportOptions) -> ExportPlan:
    """Check trimesh is installed; write later."""
    require("trimesh")
    return ExportPlan("glb", lambda out: write_glb(Path(out) / "scene.glb", scene, options))
