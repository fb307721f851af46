"""``--export rerun``: an .rrd recording read back with the Rerun SDK's own reader."""

from __future__ import annotations

import numpy as np
import pytest

from raytun3r_plugin.exports import ExportOptions, plan_exports
from raytun3r_plugin.exports.rrd import ENTITIES
from tests.export_scenes import scene_of
from tests.helpers import fisheye

rerun_chunk = pytest.importorskip("rerun.chunk")


def _rows(path) -> dict[str, list]:
    """Per entity path, its chunks' record batches (the SDK's RrdReader)."""
    found: dict[str, list] = {}
    for chunk in rerun_chunk.RrdReader(path).stream():
        found.setdefault(chunk.entity_path.lstrip("/"), []).append(chunk.to_record_batch())
    return found


def test_recording_holds_frames_depth_points_and_trajectory_but_no_pinhole(tmp_path):
    scene = scene_of(fisheye(96, 80, 190.0), frames=3)
    options = ExportOptions(max_points=500, depth_convention="z")
    plan = plan_exports(scene, ["rerun"], options)["rerun"]
    assert any("no Pinhole" in note for note in plan.notes)
    record = plan.write(tmp_path)
    path = tmp_path / "recording.rrd"
    assert path.is_file() and record["depth_convention"] == "z"
    rows = _rows(path)
    assert set(ENTITIES) <= set(rows)
    columns = {
        name for batches in rows.values() for batch in batches for name in batch.schema.names
    }
    assert not any("Pinhole" in name for name in columns)  # a pinhole would be a wrong lens

    def per_frame(entity: str, column: str) -> dict[int, object]:
        values = {}
        for batch in rows[entity]:
            for frame, value in zip(
                batch.column("frame").to_pylist(), batch.column(column), strict=True
            ):
                values[frame] = value
        return values

    expected = scene.sample_points(500 * 3, options.confidence_quantile, seed=0)
    depth = scene.depth_as("z")
    points = per_frame("world/points", "Points3D:positions")
    buffers = per_frame("frames/depth", "DepthImage:buffer")
    images = per_frame("frames/image", "Image:buffer")
    strips = per_frame("world/trajectory", "LineStrips3D:strips")
    assert sorted(points) == sorted(buffers) == sorted(images) == [0, 1, 2]
    for k in range(3):
        xyz = np.asarray(points[k].values.flatten()).reshape(-1, 3)
        assert np.allclose(xyz, expected.xyz[expected.frame == k], atol=1e-5)
        logged = np.frombuffer(
            np.asarray(buffers[k].values.flatten(), np.uint8).tobytes(), np.float32
        )
        assert np.array_equal(logged.reshape(depth[k].shape), depth[k])
        assert np.asarray(images[k].values.flatten()).size == 96 * 80 * 3
        centres = np.asarray(strips[k].values[0].values.flatten()).reshape(-1, 3)
        assert len(centres) == k + 1
        assert np.allclose(centres[-1], scene.world_from_cam(k)[:3, 3], atol=1e-5)
    (text,) = rows["description"][0].column("TextDocument:text")[0].as_py()
    assert "z: distance along the optical axis" in text and "2315" in text
