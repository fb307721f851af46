"""raytun3r_plugin.poses: the one home of rigid inverse, relative pose, angles, back-projection and quaternions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import (
    backproject,
    invert_rigid,
    quaternion_to_rotation,
    relative_pose,
    relative_poses,
    rotation_angle,
    rotation_to_quaternion,
    translation_angle,
)


def axis_angle(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for pose in poses:
        pose[:3, :3] = axis_angle(rng.normal(size=3), rng.uniform(0, math.pi))
        pose[:3, 3] = rng.normal(size=3)
    return poses


def test_invert_rigid_is_the_inverse_in_numpy_and_torch():
    poses = random_poses(5)
    inverse = invert_rigid(poses)
    np.testing.assert_allclose(inverse @ poses, np.broadcast_to(np.eye(4), poses.shape), atol=1e-12)
    np.testing.assert_array_equal(
        inverse[:, :3, :3], np.swapaxes(poses[:, :3, :3], -1, -2)
    )  # exact transpose
    as_torch = invert_rigid(torch.from_numpy(poses))
    assert isinstance(as_torch, torch.Tensor) and as_torch.dtype == torch.float64
    np.testing.assert_allclose(as_torch.numpy(), np.linalg.inv(poses), atol=1e-12)


def test_relative_pose_conventions_agree():
    poses = random_poses(4, seed=1)
    expected = poses[2] @ np.linalg.inv(poses[0])  # cam_2_from_cam_0
    np.testing.assert_array_equal(relative_pose(poses, 0, 2), expected)
    np.testing.assert_allclose(
        relative_pose(torch.from_numpy(poses), 0, 2).numpy(), expected, atol=1e-12
    )
    batched = relative_poses(poses, np.array([[0, 2], [3, 1]]))
    np.testing.assert_allclose(batched[0], expected, atol=1e-12)
    np.testing.assert_allclose(batched[1], poses[1] @ np.linalg.inv(poses[3]), atol=1e-12)


def test_rotation_angle_is_accurate_from_zero_to_pi_in_both_backends():
    base = axis_angle([0.3, -1.0, 0.2], 0.7)
    for angle in (1e-9, 1e-4, 0.5, 2.0, math.pi - 1e-7, math.pi):
        turned = base @ axis_angle([1.0, 2.0, -0.5], angle)
        assert float(rotation_angle(base, turned)) == pytest.approx(angle, rel=1e-6, abs=1e-12)
        as_torch = rotation_angle(torch.from_numpy(base), torch.from_numpy(turned))
        assert float(as_torch) == pytest.approx(angle, rel=1e-6, abs=1e-12)


def test_the_loss_epsilon_keeps_the_gradient_finite_at_zero():
    rotation = torch.eye(3, dtype=torch.float64, requires_grad=True)
    rotation_angle(rotation, torch.eye(3, dtype=torch.float64), eps=1e-12).backward()
    assert torch.isfinite(rotation.grad).all()
    t = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    translation_angle(t, torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64), eps=1e-12).backward()
    assert torch.isfinite(t.grad).all()


def test_translation_angle_is_scale_free_and_signed():
    a = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 3.0, 0]])
    b = np.array([[5.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 1.0]])
    np.testing.assert_allclose(translation_angle(a, b), [0.0, math.pi, math.pi / 4], atol=1e-12)
    assert float(translation_angle(np.zeros(3), np.ones(3))) == 0.0


def test_backproject_range_and_z_depth():
    rays = torch.tensor([[0.0, 0.6, 0.8], [0.6, 0.0, -0.8], [1.0, 0.0, 0.0]])
    depth = torch.tensor([2.0, 2.0, 2.0])
    torch.testing.assert_close(backproject(depth, rays), depth[:, None] * rays)
    points = backproject(depth, rays, "z")
    assert float(points[0, 2]) == pytest.approx(2.0)
    # Behind the camera: divided by its own negative z, as the loss always did (inference's old
    # copy clamped z to 1e-6 and sent the point a million units away).
    torch.testing.assert_close(points[1], 2.0 * rays[1] / -0.8)
    assert torch.isfinite(points[2]).all()  # a sideways ray: floored, not a division by zero
    with pytest.raises(InputError, match="depth_convention"):
        backproject(depth, rays, "disparity")


def test_quaternions_round_trip_on_every_branch():
    rotations = [
        np.eye(3),
        axis_angle([0, 0, 1], math.pi / 2),
        axis_angle([1, 1, 0], math.pi),
        axis_angle([0.2, -1, 0.4], 3.0),
    ]
    rotations += list(random_poses(20, seed=3)[:, :3, :3])
    quaternions = rotation_to_quaternion(np.stack(rotations))
    assert quaternions.shape == (len(rotations), 4)
    assert (quaternions[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(quaternions, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quaternion_to_rotation(quaternions), np.stack(rotations), atol=1e-12)
    np.testing.assert_allclose(
        rotation_to_quaternion(axis_angle([0, 0, 1], math.pi / 2)),
        [math.sqrt(0.5), 0, 0, math.sqrt(0.5)],
        atol=1e-15,
    )


def test_tum_trajectories_store_x_y_z_w(tmp_path):
    from raytun3r_plugin.exports.files import write_tum

    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = axis_angle([0, 0, 1], math.pi / 2)
    world_from_cam[:3, 3] = [1.0, 2.0, 3.0]
    write_tum(tmp_path / "t.txt", np.array([0.5]), np.linalg.inv(world_from_cam)[None])
    values = [float(v) for v in (tmp_path / "t.txt").read_text().splitlines()[1].split()]
    np.testing.assert_allclose(
        values, [0.5, 1.0, 2.0, 3.0, 0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-8
    )


def test_rotations_from_rotvecs_turn_by_the_vector_length_about_its_axis():
    from raytun3r_plugin.poses import rotation_angle, rotations_from_rotvecs

    rotvecs = np.random.default_rng(0).normal(size=(20, 3))
    rotvecs[0] = 0.0
    rotations = rotations_from_rotvecs(rotvecs)
    assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(rotations), 1.0)
    assert np.allclose(rotations[0], np.eye(3))
    axes = rotvecs[1:] / np.linalg.norm(rotvecs[1:], axis=1, keepdims=True)
    assert np.allclose(np.einsum("nij,nj->ni", rotations[1:], axes), axes, atol=1e-12)
    angles = np.linalg.norm(rotvecs[1:], axis=1)  # radians, all below pi here
    found = [float(rotation_angle(r, np.eye(3))) for r in rotations[1:]]
    assert angles.max() < np.pi and np.allclose(found, angles, atol=1e-6)
