"""Adaptation losses (docs/conventions.md section 7): zero at ground truth, edge-aware, PE-only regularisers.

Ground truth comes from an analytic textured room (an axis-aligned box seen from inside, so every
surface point is visible from every camera inside it and correspondences need no occlusion test);
``room_sequence`` is also used by ``test_adapt.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin.adaptation.losses import (
    LossWeights,
    pe_correction_grid,
    pe_l2,
    pe_tv,
    relative_pose,
    reprojection_loss,
    smoothness_loss,
    to_input_pixels,
    total_loss,
)
from raytun3r_plugin.adaptation.pose_terms import (
    fit_translation_scale,
    pose_loss,
    rotation_angle,
    translation_angle,
)
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.size_geometry import GeometryCache
from tests.helpers import fisheye, randomise_

ROOM_LO = np.array([-2.0, -1.6, -2.5])
ROOM_HI = np.array([2.4, 1.3, 3.2])


# --------------------------------------------------------------------------------------------
# Analytic room: depth, images, poses, correspondences
# --------------------------------------------------------------------------------------------


def _rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def room_pose(k: int, step: float = 0.25, yaw: float = 0.05) -> np.ndarray:
    """``cam_from_world`` (4, 4) of frame ``k`` of a smooth sideways/forward walk with a slow yaw."""
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = _rotation_y(yaw * k) @ _rotation_y(0.1)
    world_from_cam[:3, 3] = [0.2 + step * k, 0.1 - 0.02 * k, -0.3 + 0.4 * step * k]
    return np.linalg.inv(world_from_cam)


def room_render(camera, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range depth (H, W) float64, valid (H, W) bool and image (H, W, 3) float32 in [0, 1]."""
    rays, valid = camera.ray_table(dtype=torch.float64)
    rays, valid = rays.numpy(), valid.numpy().astype(bool)
    rotation, translation = cam_from_world[:3, :3], cam_from_world[:3, 3]
    origin = -rotation.T @ translation
    directions = rays @ rotation  # world-frame directions (R^T r per pixel)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(directions > 0, ROOM_HI, ROOM_LO)
        t_axis = np.where(np.abs(directions) > 1e-12, (bound - origin) / directions, np.inf)
    depth = t_axis.min(axis=-1)
    points = origin + depth[..., None] * directions
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    pattern = (
        0.5
        + 0.18 * np.sin(5.0 * x + 2.0 * y) * np.cos(4.0 * z - y)
        + 0.12 * np.sin(11.0 * z + 7.0 * x + 3.0 * y)
        + 0.08 * np.cos(17.0 * y - 5.0 * z)
    )
    image = np.stack([pattern, 0.9 * pattern + 0.05, 1.0 - 0.8 * pattern], axis=-1)
    image = np.where(valid[..., None], np.clip(image, 0.0, 1.0), 0.0).astype(np.float32)
    return np.where(valid, depth, 0.0), valid, image


def room_sequence(
    camera, n_frames: int, step: float = 0.25, yaw: float = 0.05
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Images (N, H, W, 3) float32, range depth (N, H, W) float64, cam_from_world (N, 4, 4)."""
    poses = np.stack([room_pose(k, step, yaw) for k in range(n_frames)])
    rendered = [room_render(camera, pose) for pose in poses]
    return np.stack([r[2] for r in rendered]), np.stack([r[0] for r in rendered]), poses


def room_matches(
    camera, depth_i: np.ndarray, valid: np.ndarray, cam_j_from_cam_i: np.ndarray, stride: int = 2
):
    """Ground-truth matches: pixel centres of frame i (every ``stride``) and their images in j."""
    rows, cols = np.mgrid[0 : camera.height : stride, 0 : camera.width : stride]
    keep = valid[rows, cols]
    uv_i = np.stack([cols[keep], rows[keep]], axis=-1).astype(np.float64)
    rays, _ = camera.unproject(torch.from_numpy(uv_i))
    points = depth_i[rows[keep], cols[keep]][:, None] * rays.numpy()
    moved = points @ cam_j_from_cam_i[:3, :3].T + cam_j_from_cam_i[:3, 3]
    uv_j, ok = camera.project(torch.from_numpy(moved))
    uv_j, ok = uv_j.numpy(), ok.numpy().astype(bool)
    inside = (
        (uv_j[:, 0] > 0)
        & (uv_j[:, 0] < camera.width - 1)
        & (uv_j[:, 1] > 0)
        & (uv_j[:, 1] < camera.height - 1)
    )
    ok &= inside
    ok[ok] &= valid[np.rint(uv_j[ok, 1]).astype(int), np.rint(uv_j[ok, 0]).astype(int)]
    return uv_i[ok], uv_j[ok]


@pytest.fixture(scope="module")
def room():
    camera = fisheye(84, 70, 190.0)
    images, depth, poses = room_sequence(camera, 2)
    valid = camera.valid_mask().numpy().astype(bool)
    return camera, images, depth, poses, valid


# --------------------------------------------------------------------------------------------
# Reprojection
# --------------------------------------------------------------------------------------------


def test_reprojection_vanishes_at_ground_truth(room):
    camera, _, depth, poses, valid = room
    poses_t = torch.from_numpy(poses).float()
    relative = relative_pose(poses_t, 0, 1)
    assert torch.allclose(
        relative.double(), torch.from_numpy(poses[1] @ np.linalg.inv(poses[0])), atol=1e-5
    )
    uv_i, uv_j = room_matches(camera, depth[0], valid, poses[1] @ np.linalg.inv(poses[0]))
    assert len(uv_i) > 200
    depth_t = torch.from_numpy(depth[0]).float()
    uv_i_t, uv_j_t = torch.from_numpy(uv_i).float(), torch.from_numpy(uv_j).float()
    loss, n_valid = reprojection_loss(depth_t, relative, uv_i_t, uv_j_t, None, camera)
    assert n_valid >= 0.95 * len(uv_i)
    assert float(loss) < 1e-2  # pixels; float32 rounding only

    # A wrong pose or a wrong depth scale costs pixels; the loss is differentiable in both.
    depth_var = (depth_t * 1.3).requires_grad_(True)
    wrong = relative.clone().requires_grad_(True)
    bad, _ = reprojection_loss(
        depth_var, wrong, uv_i_t, uv_j_t, torch.full((len(uv_i),), 0.5), camera
    )
    assert float(bad.detach()) > 0.1
    bad.backward()
    assert torch.isfinite(depth_var.grad).all() and depth_var.grad.abs().sum() > 0
    assert torch.isfinite(wrong.grad).all() and wrong.grad.abs().sum() > 0

    # Confidence weights scale the error; matches outside the valid region do not count.
    half, _ = reprojection_loss(
        depth_t * 1.3, relative, uv_i_t, uv_j_t, torch.full((len(uv_i),), 0.5), camera
    )
    full, _ = reprojection_loss(depth_t * 1.3, relative, uv_i_t, uv_j_t, None, camera)
    assert float(half) == pytest.approx(float(full) / 2, rel=1e-5)
    outside = torch.tensor([[0.0, 0.0]])  # corner of the image: outside the 190-degree circle
    none, count = reprojection_loss(depth_t, relative, outside, outside, None, camera)
    assert count == 0 and float(none) == 0.0


def test_reprojection_scales_native_matches_to_the_input_size():
    """Matches found at native resolution, depth predicted at the network's input size."""
    native = fisheye(168, 140, 190.0)
    small = native.resized(84, 70)
    pose_i, pose_j = room_pose(0), room_pose(1)
    relative = pose_j @ np.linalg.inv(pose_i)
    depth_native, valid_native, _ = room_render(native, pose_i)
    depth_small, _, _ = room_render(small, pose_i)
    uv_i, uv_j = room_matches(native, depth_native, valid_native, relative, stride=3)
    uv_i_in = to_input_pixels(torch.from_numpy(uv_i).float(), (168, 140), (84, 70))
    uv_j_in = to_input_pixels(torch.from_numpy(uv_j).float(), (168, 140), (84, 70))
    rel_t = torch.from_numpy(relative).float()
    loss, n_valid = reprojection_loss(
        torch.from_numpy(depth_small).float(), rel_t, uv_i_in, uv_j_in, None, small
    )
    assert n_valid > 200
    assert float(loss) < 0.1  # input pixels: bilinear depth between pixel centres only
    # Rescaling without the pixel-centre shift (u / 2) is already measurably wrong.
    wrong, _ = reprojection_loss(
        torch.from_numpy(depth_small).float(),
        rel_t,
        torch.from_numpy(uv_i).float() / 2,
        torch.from_numpy(uv_j).float() / 2,
        None,
        small,
    )
    assert float(wrong) > 5 * float(loss)


def test_reprojection_matches_synthetic_ground_truth():
    """Cross-check with the synthetic renderer's own depth, poses and correspondences."""
    synthetic = pytest.importorskip("raytun3r_plugin.synthetic")
    camera = fisheye(64, 64, 190.0)
    seq = synthetic.render_sequence("indoor", camera, n_frames=2, seed=3, supersample=1)
    uv_i, uv_j, visible = synthetic.correspondences(seq, 0, 1, stride=2)
    uv_i, uv_j = uv_i[visible], uv_j[visible]
    assert len(uv_i) > 100
    relative = torch.from_numpy(synthetic.relative_pose(seq.cam_from_world, 0, 1)).float()
    depth = torch.from_numpy(np.asarray(seq.range_depth(0))).float()
    loss, n_valid = reprojection_loss(
        depth,
        relative,
        torch.from_numpy(uv_i).float(),
        torch.from_numpy(uv_j).float(),
        None,
        camera,
        depth > 0,
    )
    assert n_valid >= 0.9 * len(uv_i)
    assert float(loss) < 1e-2


def test_translation_scale_recovers_the_depth_scale(room):
    camera, _, depth, poses, valid = room
    relative = poses[1] @ np.linalg.inv(poses[0])
    uv_i, uv_j = room_matches(camera, depth[0], valid, relative)
    rays_i, _ = camera.unproject(torch.from_numpy(uv_i))
    rays_j, _ = camera.unproject(torch.from_numpy(uv_j))
    points = (
        torch.from_numpy(depth[0][uv_i[:, 1].astype(int), uv_i[:, 0].astype(int)])[:, None] * rays_i
    )
    translation = torch.from_numpy(relative[:3, 3])
    direction = translation / translation.norm()
    scale = fit_translation_scale(
        points * 2.0, rays_j, torch.from_numpy(relative[:3, :3]), direction
    )
    assert float(scale) == pytest.approx(2.0 * float(translation.norm()), rel=1e-6)


# --------------------------------------------------------------------------------------------
# Pose term
# --------------------------------------------------------------------------------------------


def _axis_angle(axis, angle: float) -> torch.Tensor:
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    k = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
        dtype=torch.float64,
    )
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_pose_term_vanishes_at_ground_truth(room):
    _, _, _, poses, _ = room
    relative = torch.from_numpy(poses[1] @ np.linalg.inv(poses[0]))
    target_t = relative[:3, 3] / relative[:3, 3].norm()
    assert float(pose_loss(relative.float(), relative[:3, :3], target_t)) < 1e-5
    # Scale of the translation does not matter, its direction does.
    scaled = relative.clone()
    scaled[:3, 3] *= 7.0
    assert float(pose_loss(scaled, relative[:3, :3], target_t)) < 1e-9


def test_pose_term_measures_angles_in_radians():
    rotation = _axis_angle([0.3, 1.0, -0.2], 0.0)
    turned = _axis_angle([0.3, 1.0, -0.2], 0.2)
    assert float(rotation_angle(rotation, turned)) == pytest.approx(0.2, abs=1e-9)
    assert float(rotation_angle(rotation, _axis_angle([1.0, 0.0, 0.0], math.pi))) == pytest.approx(
        math.pi, abs=1e-6
    )
    t = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert float(
        translation_angle(t, torch.tensor([math.cos(0.3), math.sin(0.3), 0.0], dtype=torch.float64))
    ) == pytest.approx(0.3, abs=1e-9)
    assert float(translation_angle(t, -t)) == pytest.approx(math.pi, abs=1e-6)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = turned
    pose[:3, 3] = torch.tensor([math.cos(0.3), math.sin(0.3), 0.0]) * 2.5
    assert float(pose_loss(pose, rotation, t)) == pytest.approx(0.5, abs=1e-6)


@pytest.mark.parametrize("angle", [0.0, 1e-9, math.pi])
def test_pose_term_gradients_are_finite(angle):
    target = _axis_angle([0.0, 1.0, 0.0], 0.0)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = _axis_angle([0.0, 1.0, 0.0], angle)
    pose[:3, 3] = torch.tensor([0.0, 0.0, 1.0])
    pose.requires_grad_(True)
    loss = pose_loss(pose, target, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    (grad,) = torch.autograd.grad(loss, pose)
    assert torch.isfinite(grad).all()


# --------------------------------------------------------------------------------------------
# Smoothness
# --------------------------------------------------------------------------------------------


def test_smoothness_follows_image_edges():
    height, width, edge = 20, 30, 15
    depth = torch.ones(height, width)
    depth[:, edge:] = 2.0
    edged = torch.zeros(3, height, width)
    edged[:, :, edge:] = 1.0
    flat = torch.full((3, height, width), 0.5)
    aligned = smoothness_loss(depth, edged)
    in_flat_region = smoothness_loss(depth, flat)
    assert float(aligned) < 0.5 * float(in_flat_region)
    assert float(aligned) == pytest.approx(math.exp(-1.0) * float(in_flat_region), rel=1e-5)
    # An image edge elsewhere does not discount the depth step.
    elsewhere = torch.zeros(3, height, width)
    elsewhere[:, :, 5:] = 1.0
    assert float(smoothness_loss(depth, elsewhere)) == pytest.approx(
        float(in_flat_region), rel=1e-5
    )
    # Mean-normalised: scaling the depth changes nothing; a constant depth costs nothing.
    assert float(smoothness_loss(depth * 9.0, edged)) == pytest.approx(float(aligned), rel=1e-5)
    assert float(smoothness_loss(torch.full((height, width), 3.0), edged)) == 0.0
    # Pixels outside the valid region do not count (the step lies between invalid pixels).
    valid = torch.ones(height, width, dtype=torch.bool)
    valid[:, edge - 1 : edge + 1] = False
    assert float(smoothness_loss(depth, flat, valid)) == 0.0
    # Batched frames average.
    both = smoothness_loss(torch.stack([depth, depth]), torch.stack([edged, flat]))
    assert float(both) == pytest.approx((float(aligned) + float(in_flat_region)) / 2, rel=1e-5)


# --------------------------------------------------------------------------------------------
# PE regularisers
# --------------------------------------------------------------------------------------------


def _measured_correction(model, camera, adapter, height: int, width: int) -> torch.Tensor:
    """P' - P_A read from the patched model's own PE interpolation (patch rows), (h, w, C)."""
    from raytun3r_plugin import apply

    vit = model.backbone.pretrained
    tokens = torch.zeros(1, 1 + (height // 14) * (width // 14), vit.embed_dim)
    with torch.no_grad(), apply(model, camera, adapter) as handle:
        patched = vit.interpolate_pos_encoding(tokens, height, width)
        with handle.disabled():
            upstream = vit.interpolate_pos_encoding(tokens, height, width)
    return (patched - upstream)[0, 1:].reshape(height // 14, width // 14, -1)


def test_pe_regularisers_act_on_the_correction_only():
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    camera = fisheye(84, 70, 190.0)
    geometry = GeometryCache(camera, 14).at(70, 84)
    model_a, model_b = build_tiny_network(seed=0), build_tiny_network(seed=1)
    assert not torch.equal(
        model_a.backbone.pretrained.pos_embed, model_b.backbone.pretrained.pos_embed
    )

    zero = Adapter.for_model(model_a, camera)
    correction = pe_correction_grid(zero, geometry)
    assert correction.shape == (5, 6, 64)
    assert float(pe_l2(correction.detach())) == 0.0 and float(pe_tv(correction.detach())) == 0.0

    values = {}
    for name, model in (("a", model_a), ("b", model_b)):
        adapter = randomise_(Adapter.for_model(model, camera), scale=0.05, seed=4)
        correction = pe_correction_grid(adapter, geometry)
        measured = _measured_correction(model, camera, adapter, 70, 84)
        torch.testing.assert_close(correction, measured, atol=1e-6, rtol=1e-5)
        l2, tv = pe_l2(correction), pe_tv(correction)
        values[name] = (float(l2.detach()), float(tv.detach()))
        assert values[name][0] > 0 and values[name][1] > 0
        assert float(pe_l2(measured)) == pytest.approx(values[name][0], rel=1e-5)
        # Gradients reach the PE tables (and only them: the RoPE table is not involved).
        (2 * l2 + 20 * tv).backward()
        assert (
            adapter.pe["radial"].grad.abs().sum() > 0 and adapter.pe["angular"].grad.abs().sum() > 0
        )
        assert adapter.rope["radial"].grad is None
    assert values["a"] == values["b"]


def test_pe_tv_is_the_squared_neighbour_difference():
    correction = torch.zeros(2, 3, 1)
    correction[0, 1, 0] = 1.0
    # Neighbours of the bump: 2 horizontal + 1 vertical differences of 1 each; 6 tokens.
    assert float(pe_tv(correction)) == pytest.approx(3 / 6)
    assert float(pe_l2(correction)) == pytest.approx(1 / 6)


def test_total_loss_uses_the_paper_weights():
    weights = LossWeights()
    assert weights.as_dict() == {
        "reproj": 1.0,
        "smooth": 10.0,
        "l2": 2.0,
        "tv": 20.0,
        "pose": 1.0,
        "depth": 1.0,
    }
    terms = {name: torch.tensor(1.0) for name in ("reproj", "smooth", "l2", "tv", "pose")}
    assert float(total_loss(terms, weights)) == 34.0
    del terms["pose"]
    assert float(total_loss(terms, weights)) == 33.0
