"""Center-PH geometry and the method runner / scorer used by the demo and the benchmark."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.apps.evaluation import (
    center_pinhole,
    center_pinhole_depth_to_fisheye,
    choose_pair_stride,
    fisheye_to_center_pinhole,
    frame_windows,
    headline,
    run_method,
    score,
)
from raytun3r_plugin.datasets import Sequence
from raytun3r_plugin.errors import InputError
from tests.helpers import fisheye

SIZE = 84


@pytest.fixture(scope="module")
def seq():
    return synthetic.render_sequence("indoor", fisheye(SIZE, SIZE, 190.0), n_frames=5, seed=3)


def test_frame_windows_cover_every_frame_once():
    assert frame_windows(list(range(7)), 3) == [[0, 1, 2], [3, 4, 5, 6]]
    assert frame_windows(list(range(6)), 3) == [[0, 1, 2], [3, 4, 5]]
    # Stride 2: two interleaved runs, pairs two frames apart, every frame once.
    assert frame_windows(list(range(8)), 3, 2) == [[0, 2, 4, 6], [1, 3, 5, 7]]
    assert frame_windows(list(range(12)), 3, 2) == [[0, 2, 4], [6, 8, 10], [1, 3, 5], [7, 9, 11]]
    with pytest.raises(InputError):
        frame_windows(list(range(6)), 3, 0)


def test_the_pair_stride_is_the_smallest_with_a_measurable_baseline():
    camera = fisheye(SIZE, SIZE, 190.0)
    positions = np.zeros((12, 3))
    positions[:, 0] = 0.004 * np.arange(12)  # 4 mm per frame
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, :3, 3] = -positions  # cam_from_world of an unrotated camera at `positions`
    seq = Sequence("line", camera, np.arange(12) / 30.0, poses)
    chosen = choose_pair_stride(seq)
    assert chosen["threshold"] == pytest.approx(0.05) and chosen["rule"] == "0.05 m"
    assert chosen["stride"] == 4  # capped at a third of the frames (13 needed for 5 cm)
    seq.depth = np.full((12, SIZE, SIZE), 0.5, np.float32)  # 3 % of 0.5 m = 15 mm: stride 4
    assert choose_pair_stride(seq)["stride"] == 4
    seq.depth = np.full((12, SIZE, SIZE), 0.2, np.float32)  # 6 mm: stride 2
    chosen = choose_pair_stride(seq)
    assert chosen["stride"] == 2 and chosen["median_baseline"] == pytest.approx(0.008)


def test_center_pinhole_has_the_stated_field_of_view(seq):
    pinhole = center_pinhole(seq.camera)
    rays, _ = pinhole.unproject(
        torch.tensor([[-0.5, (SIZE - 1) / 2], [SIZE - 0.5, (SIZE - 1) / 2]], dtype=torch.float64)
    )
    assert math.degrees(math.acos(float(rays[0] @ rays[1]))) == pytest.approx(110.0, abs=1e-6)


def test_center_ph_round_trip_reproduces_ground_truth_range(seq):
    """A pinhole render of the same view, mapped back, gives the fisheye's ground-truth range."""
    pinhole = center_pinhole(seq.camera)
    frame = synthetic.render_frame(synthetic.scene_of(seq), pinhole, seq.cam_from_world[0])
    z_depth = torch.from_numpy(np.asarray(frame.z_depth, dtype=np.float32))
    mapped, covered = center_pinhole_depth_to_fisheye(z_depth, seq.camera, pinhole)
    coverage = float(covered.sum() / seq.camera.valid_mask().sum())
    assert 0.2 < coverage < 0.6
    gt = torch.from_numpy(seq.depth[0])
    inner = covered & (gt > 0)
    relative = ((mapped - gt).abs() / gt)[inner]
    assert float(relative.median()) < 0.01
    # and the image resampling looks at the same content
    image = torch.from_numpy(seq.images[0]).permute(2, 0, 1)
    virtual = fisheye_to_center_pinhole(image, seq.camera, pinhole)
    rendered = torch.from_numpy(np.asarray(frame.rgb)).permute(2, 0, 1)
    assert float((virtual - rendered).abs().mean()) < 0.06


def test_methods_are_scored_on_the_same_pairs(seq):
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    model = build_tiny_network(seed=0)
    rows = {}
    for method in ("vanilla", "center-ph", "raytun3r"):
        summary = score(seq, run_method(model, seq, method))
        rows[method] = summary
        assert summary["n_pairs"] == 3  # windows [0,1,2] and [3,4]: pairs (0,1),(1,2),(3,4)
        values = headline(summary)
        assert all(
            math.isfinite(values[k])
            for k in ("rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25")
        )
    assert rows["center-ph"]["coverage"] < 0.6 and rows["vanilla"]["coverage"] == 1.0
    assert rows["vanilla"]["abs_rel"]["mean"] != rows["raytun3r"]["abs_rel"]["mean"]


def test_ground_truth_depth_scores_perfectly(seq):
    from raytun3r_plugin.apps.evaluation import MethodOutput

    windows = [([0, 1, 2], seq.cam_from_world[[0, 1, 2]]), ([3, 4], seq.cam_from_world[[3, 4]])]
    summary = score(seq, MethodOutput(depth=seq.depth.copy(), window_poses=windows))
    values = headline(summary)
    assert values["rot_deg"] < 1e-4 and values["trans_deg"] < 1e-3
    assert values["abs_rel"] < 1e-6 and values["delta_1.25"] == 1.0
    assert values["d_reproj_px"] < 0.05
