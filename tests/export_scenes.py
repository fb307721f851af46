"""Small rendered scenes for the export tests (a helper module, not fixtures)."""

from __future__ import annotations

import functools

import numpy as np

from raytun3r_plugin.exports import ExportScene


@functools.lru_cache(maxsize=8)
def rendered(camera_json: str, frames: int = 3, seed: int = 3):
    """A synthetic indoor sequence of the camera (JSON, so that the cache can key on it)."""
    from raytun3r_plugin import cameras, synthetic

    camera = cameras.from_dict(__import__("json").loads(camera_json))
    return synthetic.render_sequence("indoor", camera, n_frames=frames, seed=seed)


def scene_of(camera, frames: int = 3, confidence: bool = True) -> ExportScene:
    """An :class:`ExportScene` holding the ground truth of a rendered sequence: range depth,
    poses and frames, with a confidence that falls off with depth."""
    seq = rendered(camera.to_json(), frames)
    depth = np.asarray(seq.depth, dtype=np.float32)
    return ExportScene(
        camera=camera,
        images=np.asarray(seq.images, dtype=np.float32),
        depth=depth,
        cam_from_world=np.asarray(seq.cam_from_world, dtype=np.float64),
        names=[f"{k:04d}" for k in range(frames)],
        confidence=(1.0 / (1.0 + depth)).astype(np.float32) if confidence else None,
        depth_unit="m",
    )
