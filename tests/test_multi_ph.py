"""Multi-PH: view geometry, the tilt rule, depth and pose fusion, and the method in run_method."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin import synthetic
from raytun3r_plugin.baselines import (
    chain_relative_poses,
    choose_tilt,
    chordal_mean,
    fuse_depth,
    fuse_relative_poses,
    multi_pinhole_views,
    predict_multi_ph,
    resample_to_view,
    view_coverage,
    view_depth_to_fisheye,
    view_lookup,
    view_rotation,
)
from raytun3r_plugin.cameras import KannalaBrandt4
from raytun3r_plugin.cameras import fisheye as build_fisheye
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.poses import relative_pose, rotation_angle, translation_angle
from tests.helpers import fisheye

SIZE = 84


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def _rotation(axis, angle_deg: float) -> torch.Tensor:
    """Rodrigues' formula, float64."""
    k = torch.tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    a = math.radians(angle_deg)
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx


def _rigid(rotation: torch.Tensor, translation) -> torch.Tensor:
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rotation
    out[:3, 3] = torch.as_tensor(translation, dtype=torch.float64)
    return out


# --------------------------------------------------------------------------------------------
# Views and the tilt rule
# --------------------------------------------------------------------------------------------


def test_views_point_where_the_rule_says():
    camera = fisheye(SIZE, SIZE, 190.0)
    views = multi_pinhole_views(camera, tilt_deg=45.0)
    assert [v.name for v in views] == ["centre", "right", "left", "down", "up"]
    assert torch.equal(views[0].rotation, torch.eye(3, dtype=torch.float64))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    expected = {"right": (0, 1.0), "left": (0, -1.0), "down": (1, 1.0), "up": (1, -1.0)}
    for view in views:
        r = view.rotation
        assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
        assert float(torch.linalg.det(r)) == pytest.approx(1.0)
        # rotation maps fisheye to view coordinates: the view's axis, seen from the fisheye
        assert torch.allclose(r @ view.axis, z, atol=1e-12)
        if view.name == "centre":
            continue
        assert _angle_deg(view.axis, z) == pytest.approx(45.0, abs=1e-9)
        index, sign = expected[view.name]
        assert math.copysign(1.0, float(view.axis[index])) == sign
        assert abs(float(view.axis[1 - index])) < 1e-12
    # every view is the Center-PH pinhole: 110 degrees across its width, pixel edge to edge
    for view in views:
        edges = torch.tensor(
            [[-0.5, (SIZE - 1) / 2], [SIZE - 0.5, (SIZE - 1) / 2]], dtype=torch.float64
        )
        rays, _ = view.camera.unproject(edges)
        assert _angle_deg(rays[0], rays[1]) == pytest.approx(110.0, abs=1e-6)


def test_view_rotation_turns_the_axis_right_then_down():
    axis = view_rotation(30.0, 20.0)[2]
    y, p = math.radians(30.0), math.radians(20.0)
    expected = torch.tensor(
        [math.cos(p) * math.sin(y), math.sin(p), math.cos(p) * math.cos(y)], dtype=torch.float64
    )
    assert torch.allclose(axis, expected, atol=1e-12)
    # the view's x axis stays horizontal (no roll)
    assert abs(float(view_rotation(30.0, 20.0)[0, 1])) < 1e-12


@pytest.mark.parametrize(
    ("fov", "centre_only", "tilt"),
    # docs/baselines.md: union coverage of an ideal equidistant circle, Center-PH alone and
    # the tilt the rule picks
    [(185.0, 0.392, 45.0), (195.0, 0.353, 50.0), (200.0, 0.336, 50.0)],
)
def test_the_tilt_rule_reproduces_the_coverage_table(fov, centre_only, tilt):
    camera = build_fisheye(256, fov, "kb4", k=(0.0, 0.0, 0.0, 0.0))
    views = multi_pinhole_views(camera, tilt_deg=tilt)
    assert view_coverage(camera, views[:1]) == pytest.approx(centre_only, abs=0.005)
    assert choose_tilt(camera) == tilt
    assert view_coverage(camera, views) >= 0.995
    smaller = multi_pinhole_views(camera, tilt_deg=tilt - 5.0)
    assert view_coverage(camera, smaller) < 0.995


def test_a_narrow_lens_gets_the_smallest_tilt_and_bad_tilts_are_refused():
    w, h, f = 378, 252, 3411 / 16  # ETH3D-DSLR-like, corner at about 61 degrees
    params = {"fx": f, "fy": f, "cx": (w - 1) / 2, "cy": (h - 1) / 2}
    camera = KannalaBrandt4(w, h, {**params, "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0})
    assert choose_tilt(camera) == 5.0
    with pytest.raises(InputError):
        multi_pinhole_views(camera, tilt_deg=90.0)


# --------------------------------------------------------------------------------------------
# Depth: back to the fisheye, scale alignment, ownership
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def seq():
    return synthetic.render_sequence("indoor", fisheye(SIZE, SIZE, 190.0), n_frames=3, seed=80011)


def _view_pose(view, cam_from_world: np.ndarray) -> np.ndarray:
    """cam_from_world of a virtual view of the fisheye camera (same centre)."""
    rotation = np.eye(4)
    rotation[:3, :3] = view.rotation.numpy()
    return rotation @ cam_from_world


def test_exact_view_depths_fuse_back_to_the_fisheye_range(seq):
    """Pinhole renders of the five views, each at its own unknown scale, fuse to the ground
    truth range: the scales are recovered and each pixel belongs to the nearest view axis."""
    camera = seq.camera
    views = multi_pinhole_views(camera)
    scene = synthetic.scene_of(seq)
    true_scale = [1.0, 0.5, 2.0, 1.7, 0.8]  # what each stream's depth is off by
    ranges, inside, cosines, errors = [], [], [], []
    for view, scale in zip(views, true_scale, strict=True):
        frame = synthetic.render_frame(scene, view.camera, _view_pose(view, seq.cam_from_world[0]))
        z_depth = torch.from_numpy(np.asarray(frame.z_depth, dtype=np.float32)) / scale
        range_v, inside_v = view_depth_to_fisheye(z_depth, camera, view.camera, view.rotation)
        ranges.append(range_v[None])
        inside.append(inside_v)
        cosines.append(view_lookup(camera, view.camera, view.rotation)[1])
        # the resampled image shows what the view renders
        image = torch.from_numpy(seq.images[0]).permute(2, 0, 1)
        virtual = resample_to_view(image, camera, view.camera, view.rotation)
        rendered = torch.from_numpy(np.asarray(frame.rgb)).permute(2, 0, 1)
        seen = torch.from_numpy(np.asarray(frame.valid)) & (virtual.sum(0) > 0)
        errors.append(float((virtual - rendered).abs().mean(0)[seen].mean()))
    assert max(errors) < 0.06, errors
    fused, owner, scales, flagged = fuse_depth(
        torch.stack(ranges), torch.stack(inside), torch.stack(cosines), valid=camera.valid_mask()
    )
    assert not bool(flagged.any())
    assert scales[0].tolist() == pytest.approx(true_scale, rel=0.01)
    valid = camera.valid_mask()
    covered = owner >= 0
    assert float((covered & valid).sum() / valid.sum()) > 0.995
    gt = torch.from_numpy(seq.depth[0])
    scored = covered & (gt > 0)
    relative = ((fused[0] - gt).abs() / gt)[scored]
    assert float(relative.median()) < 0.01 and float((relative < 0.05).double().mean()) > 0.9
    # ownership: the covering view with the largest cosine to its axis
    cos = torch.stack(cosines).masked_fill(~torch.stack(inside), -2.0)
    assert torch.equal(owner[covered], cos.argmax(0)[covered])
    assert set(owner[covered].unique().tolist()) == {0, 1, 2, 3, 4}


def test_scale_alignment_recovers_known_scales_exactly_and_flags_missing_overlap():
    g = torch.Generator().manual_seed(0)
    h, w = 12, 16
    truth = 1.0 + torch.rand(2, h, w, generator=g, dtype=torch.float64)
    inside = torch.zeros(3, h, w, dtype=torch.bool)
    inside[0, :, :10] = True
    inside[1, :, 6:] = True  # overlaps view 0 on columns 6..9
    inside[2, :, 14:] = True  # no overlap with view 0
    scales = torch.tensor([1.0, 3.0, 0.25], dtype=torch.float64)
    ranges = truth[None] / scales[:, None, None, None]
    cosines = torch.zeros(3, h, w, dtype=torch.float64)
    cosines[1, :, 8:] = 0.5  # view 1 owns columns 8.. where it is nearer its axis
    fused, owner, found, flagged = fuse_depth(ranges, inside, cosines)
    assert found[:, 1].tolist() == pytest.approx([3.0, 3.0], rel=1e-12)
    assert flagged[:, 2].all() and not flagged[:, :2].any() and found[:, 2].tolist() == [1.0, 1.0]
    assert (owner[:, :8] == 0).all() and (owner[:, 8:] == 1).all()
    assert torch.allclose(fused, truth, rtol=1e-12)
    with pytest.raises(InputError):
        fuse_depth(ranges[0], inside, cosines)


# --------------------------------------------------------------------------------------------
# Pose fusion
# --------------------------------------------------------------------------------------------


def test_chordal_mean_of_known_rotations():
    a, b = _rotation([0, 0, 1], 30.0), _rotation([0, 0, 1], -10.0)
    # about one axis the chordal mean is the rotation by atan2 of the weighted sin / cos sums
    expected = math.degrees(
        math.atan2(
            2 * math.sin(math.radians(30)) + math.sin(math.radians(-10)),
            2 * math.cos(math.radians(30)) + math.cos(math.radians(-10)),
        )
    )
    mean = chordal_mean(torch.stack([a, b]), torch.tensor([2.0, 1.0]))
    assert torch.allclose(mean, _rotation([0, 0, 1], expected), atol=1e-12)
    # symmetric pair about an axis: the identity; the result is a rotation (det +1)
    x = chordal_mean(torch.stack([_rotation([1, 0, 0], 170.0), _rotation([1, 0, 0], -170.0)]))
    assert float(torch.linalg.det(x)) == pytest.approx(1.0)
    assert float(rotation_angle(x, _rotation([1, 0, 0], 180.0))) < 1e-9
    with pytest.raises(InputError):
        chordal_mean(torch.stack([a, b]), torch.tensor([0.0, 0.0]))


def test_exact_stream_poses_fuse_to_the_exact_relative_pose():
    views = multi_pinhole_views(fisheye(SIZE, SIZE, 190.0), tilt_deg=50.0)
    truth = _rigid(_rotation([0.3, -1.0, 0.2], 7.0), [0.2, -0.05, 0.4])
    rotations = torch.stack([view.rotation for view in views])
    streams = []
    for k, view in enumerate(views):
        r4 = _rigid(view.rotation, [0.0, 0.0, 0.0])
        seen = r4 @ truth @ r4.T  # the same motion in view coordinates
        seen[:3, 3] *= 0.5 + k  # each stream at its own scale
        streams.append(seen)
    fused = fuse_relative_poses(torch.stack(streams), rotations, torch.tensor([1, 0.3, 2, 1, 0.5]))
    assert float(rotation_angle(fused[:3, :3], truth[:3, :3])) < 1e-10
    assert float(translation_angle(fused[:3, 3], truth[:3, 3])) < 1e-10
    assert float(fused[:3, 3].norm()) == pytest.approx(0.5 * float(truth[:3, 3].norm()))
    # a stream seen in the wrong frame (no conjugation) would not agree
    wrong = fuse_relative_poses(torch.stack(streams), torch.eye(3).expand(5, 3, 3), torch.ones(5))
    assert math.degrees(float(translation_angle(wrong[:3, 3], truth[:3, 3]))) > 1.0
    # weights [v = 0] give the centre stream's pose
    alone = fuse_relative_poses(torch.stack(streams), rotations, torch.tensor([1.0, 0, 0, 0, 0]))
    assert torch.allclose(alone, streams[0], atol=1e-12)


def test_chained_poses_have_the_given_consecutive_relative_poses():
    steps = torch.stack(
        [
            _rigid(_rotation([0, 1, 0], 5.0), [0.1, 0, 0]),
            _rigid(_rotation([1, 1, 0], 3.0), [0, 0.2, 0.1]),
        ]
    )
    chain = chain_relative_poses(steps)
    assert torch.equal(chain[0], torch.eye(4, dtype=torch.float64))
    for k in range(2):
        assert torch.allclose(relative_pose(chain, k, k + 1), steps[k], atol=1e-12)


# --------------------------------------------------------------------------------------------
# The method on the built-in network
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def network():
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.apps.demo import default_network

    return default_network()[0]


@pytest.fixture(scope="module")
def demo_seq():
    from raytun3r_plugin.apps.demo import demo_camera

    return synthetic.render_sequence("indoor", demo_camera(112), n_frames=5, seed=80012)


def test_predict_multi_ph_runs_the_unpatched_model_five_times_and_leaves_it_unchanged(
    network, demo_seq
):
    from raytun3r_plugin import apply

    camera = demo_seq.camera
    images = torch.from_numpy(demo_seq.images[:3]).permute(0, 3, 1, 2).float()
    before = {k: v.clone() for k, v in network.state_dict().items()}
    calls = []
    hook = network.register_forward_pre_hook(lambda module, args: calls.append(1))
    try:
        with torch.no_grad():
            fused = predict_multi_ph(network, images, camera)
    finally:
        hook.remove()
    assert len(calls) == 5 and fused.forward_images == 15
    after = network.state_dict()
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert fused.depth.shape == (3, 112, 112) and fused.cam_from_world.shape == (3, 4, 4)
    assert fused.coverage > 0.99 and fused.tilt_deg == 50.0
    assert bool((fused.depth[:, fused.covered] > 0).all())
    assert bool((fused.depth[:, ~fused.covered] == 0).all())
    assert fused.scales.shape == (3, 5) and bool((fused.scales[:, 0] == 1).all())
    # V0 alone is Center-PH: the same depth, and its own relative poses
    from raytun3r_plugin.apps.evaluation import run_method

    with torch.no_grad():
        centre = predict_multi_ph(network, images, camera, views=fused.views[:1])
    output = run_method(network, demo_seq, "center-ph", frames=[0, 1, 2])
    assert np.array_equal(centre.depth.numpy(), output.depth[:3])
    own = torch.from_numpy(output.window_poses[0][1])
    for k in range(2):
        reference = relative_pose(own, k, k + 1)
        assert float(rotation_angle(centre.relative[k, :3, :3], reference[:3, :3])) < 1e-5
        assert float(translation_angle(centre.relative[k, :3, 3], reference[:3, 3])) < 1e-5
    # a patched model is not the baseline
    handle = apply(network, camera)
    try:
        with pytest.raises(AlreadyAppliedError):
            predict_multi_ph(network, images, camera)
    finally:
        handle.remove()


def test_run_method_scores_multi_ph_like_the_other_methods(network, demo_seq):
    from raytun3r_plugin.apps.evaluation import METHODS, headline, run_method, score

    assert "multi-ph" in METHODS
    output = run_method(network, demo_seq, "multi-ph")
    assert output.extras["forward_images"] == 5 * len(demo_seq)
    assert output.extras["tilt_deg"] == 50.0
    summary = score(demo_seq, output)
    assert summary["n_pairs"] == 3  # windows [0, 1, 2] and [3, 4], as for every method
    values = headline(summary)
    assert all(
        math.isfinite(values[k])
        for k in ("rot_deg", "trans_deg", "d_reproj_px", "abs_rel", "delta_1.25")
    )
    assert values["coverage"] > 0.99
    centre = headline(score(demo_seq, run_method(network, demo_seq, "center-ph")))
    assert centre["coverage"] < 0.5 and values["abs_rel"] != centre["abs_rel"]
