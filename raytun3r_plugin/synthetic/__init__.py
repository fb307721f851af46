"""Synthetic fisheye data with exact ground truth: procedural indoor/outdoor scenes, smooth
camera trajectories, analytic ray-cast rendering through any raytun3r camera model (fields of
view beyond 180 degrees included), and ground-truth correspondences with visibility.

Typical use::

    from raytun3r_plugin import cameras, synthetic
    cam = cameras.KannalaBrandt4(256, 256, {...})
    seq = synthetic.render_sequence("indoor", cam, n_frames=10, seed=0)
    uv_i, uv_j, visible = synthetic.correspondences(seq, 0, 1)
    synthetic.write_sequence(seq, "out/indoor")          # datasets.load_synthetic reads it back

See ``docs/synthetic_and_datasets.md``.
"""

from __future__ import annotations

from raytun3r_plugin.datasets.folder import write_sequence
from raytun3r_plugin.synthetic.correspondence import (
    bilinear_sample,
    correspondences,
    dense_flow,
    relative_pose,
)
from raytun3r_plugin.synthetic.generate import (
    FLOW_PX,
    camera_centres,
    make_trajectory,
    median_flow,
    render_rig,
    render_sequence,
    scene_of,
    stereo_extrinsics,
)
from raytun3r_plugin.synthetic.raycast import Hit, intersect
from raytun3r_plugin.synthetic.render import RenderedFrame, Renderer, render_frame
from raytun3r_plugin.synthetic.scene import (
    Scene,
    make_indoor_scene,
    make_outdoor_scene,
    make_scene,
)
from raytun3r_plugin.synthetic.trajectory import driving_trajectory, handheld_trajectory

__all__ = [
    "FLOW_PX",
    "Hit",
    "RenderedFrame",
    "Renderer",
    "Scene",
    "bilinear_sample",
    "camera_centres",
    "correspondences",
    "dense_flow",
    "driving_trajectory",
    "handheld_trajectory",
    "intersect",
    "make_indoor_scene",
    "make_outdoor_scene",
    "make_scene",
    "make_trajectory",
    "median_flow",
    "relative_pose",
    "render_frame",
    "render_rig",
    "render_sequence",
    "scene_of",
    "stereo_extrinsics",
    "write_sequence",
]
