"""Relative-pose targets (MAGSAC++ on fisheye rays) against known geometry."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin.adaptation.matchers import Matches
from raytun3r_plugin.adaptation.pose_targets import (
    PoseTarget,
    camera_focal_px,
    estimate_relative_pose,
    rotation_error_deg,
    translation_direction_error_deg,
    unproject_pixels,
)
from raytun3r_plugin.cameras import KannalaBrandt4, Pinhole
from raytun3r_plugin.errors import InputError

# ~190 degree KB4 fisheye on a 160x160 image (image circle radius ~76 px).
FISHEYE = KannalaBrandt4(
    160, 160, [45.0, 45.0, 79.5, 79.5, 0.01, -0.004, 0.0005, 0.0], max_fov_deg=190.0
)


def _scene_matches(
    camera,
    R: np.ndarray,
    t: np.ndarray,
    n: int = 1500,
    noise_px: float = 0.2,
    outlier_frac: float = 0.15,
    seed: int = 0,
) -> tuple[Matches, np.ndarray]:
    """Random 3-D points seen by two cameras ``cam_j_from_cam_i = (R, t)``; pixel noise + outliers.

    Returns the matches and the (M,) bool mask of outliers.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    X = d * rng.uniform(1.0, 5.0, (4 * n, 1))
    Y = X @ R.T + t
    uv_i, ok_i = camera.project(torch.from_numpy(X))
    uv_j, ok_j = camera.project(torch.from_numpy(Y))
    uv_i, uv_j = uv_i.numpy(), uv_j.numpy()
    inside = (
        ok_i.numpy()
        & ok_j.numpy()
        & (uv_i >= 0).all(1)
        & (uv_i <= 159).all(1)
        & (uv_j >= 0).all(1)
        & (uv_j <= 159).all(1)
    )
    uv_i, uv_j = uv_i[inside][:n], uv_j[inside][:n]
    uv_i = uv_i + rng.normal(0, noise_px, uv_i.shape)
    uv_j = uv_j + rng.normal(0, noise_px, uv_j.shape)
    out = rng.random(len(uv_i)) < outlier_frac
    uv_j[out] += rng.uniform(-15, 15, (int(out.sum()), 2))
    uv_j = np.clip(uv_j, 0, 159)
    return Matches(uv_i, uv_j, np.ones(len(uv_i))), out


def _pose(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(100 + seed)
    R, _ = cv2.Rodrigues(rng.normal(0, math.radians(3.0), 3))
    t = rng.normal(0, 1, 3)
    return R, 0.3 * t / np.linalg.norm(t)


def test_focal_and_unproject_helpers() -> None:
    assert camera_focal_px(FISHEYE) == pytest.approx(45.0, rel=1e-4)
    pin = Pinhole(64, 48, [50.0, 52.0, 31.5, 23.5])
    assert camera_focal_px(pin) == pytest.approx(51.0, rel=1e-4)
    rays, ok = unproject_pixels(FISHEYE, np.array([[79.5, 79.5], [0.0, 0.0], [150.0, 80.0]]))
    assert ok.tolist() == [True, False, True]  # the image corner is outside the lens circle
    np.testing.assert_allclose(rays[0], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(rays[[0, 2]], axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fisheye_pose_recovered(seed: int) -> None:
    R, t = _pose(seed)
    m, out = _scene_matches(FISHEYE, R, t, seed=seed)
    target = estimate_relative_pose(m, FISHEYE)
    assert target.ok, target.reason
    assert rotation_error_deg(target.R, R) < 0.3
    assert translation_direction_error_deg(target.t, t) < 3.0
    assert np.linalg.norm(target.t) == pytest.approx(1.0)
    assert target.inlier_mask.shape == (len(m),)
    assert target.n_inliers == int(target.inlier_mask.sum())
    # Outliers are rejected, most inliers kept (the ones within 80 degrees of the axis).
    assert (target.inlier_mask & out).sum() <= 0.1 * out.sum()
    assert target.n_inliers > 0.5 * (~out).sum()
    np.testing.assert_allclose(target.matrix()[:3, :3], target.R)


def test_translation_sign_convention() -> None:
    # Camera j = camera i moved 0.3 m to the right (+x in camera i): X_j = X_i - (0.3, 0, 0).
    R = np.eye(3)
    t = np.array([-0.3, 0.0, 0.0])
    m, _ = _scene_matches(FISHEYE, R, t, outlier_frac=0.0, seed=5)
    target = estimate_relative_pose(m, FISHEYE)
    assert target.ok
    np.testing.assert_allclose(target.t, [-1.0, 0.0, 0.0], atol=0.03)
    # The reversed pair gives the inverse pose.
    back = estimate_relative_pose(m.reversed(), FISHEYE)
    assert rotation_error_deg(back.R, target.R.T) < 0.2
    assert translation_direction_error_deg(back.t, -target.R.T @ target.t) < 2.0


def test_deterministic_and_unrefined() -> None:
    R, t = _pose(3)
    m, _ = _scene_matches(FISHEYE, R, t, seed=3)
    a = estimate_relative_pose(m, FISHEYE, seed=7)
    b = estimate_relative_pose(m, FISHEYE, seed=7)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    raw = estimate_relative_pose(m, FISHEYE, refine=False)
    assert raw.ok  # OpenCV's own result: looser accuracy
    assert rotation_error_deg(raw.R, R) < 3.0


def test_pinhole_camera_pose() -> None:
    pin = Pinhole(160, 160, [80.0, 80.0, 79.5, 79.5])
    R, t = _pose(4)
    t = t * np.array([1.0, 1.0, 0.2])  # mostly sideways: keeps points in the narrow view
    t = 0.3 * t / np.linalg.norm(t)
    m, _ = _scene_matches(pin, R, t, seed=4)
    target = estimate_relative_pose(m, pin)
    assert target.ok
    assert rotation_error_deg(target.R, R) < 0.3
    assert translation_direction_error_deg(target.t, t) < 3.0


def test_fails_soft() -> None:
    few = Matches(np.random.rand(5, 2) * 100, np.random.rand(5, 2) * 100, np.ones(5))
    target = estimate_relative_pose(few, FISHEYE)
    assert not target.ok and "too few" in target.reason
    assert target.inlier_mask.shape == (5,) and target.n_inliers == 0
    assert np.allclose(target.t, 0) and np.allclose(target.R, np.eye(3))
    empty = estimate_relative_pose(Matches.empty(), FISHEYE)
    assert not empty.ok and empty.inlier_mask.shape == (0,)
    # Every match beyond 80 degrees from the axis (a ring near the lens edge).
    ang = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    ring = np.stack([79.5 + 72 * np.cos(ang), 79.5 + 72 * np.sin(ang)], axis=1)
    edge = estimate_relative_pose(Matches(ring, ring + 0.5, np.ones(100)), FISHEYE)
    assert not edge.ok and "within 80" in edge.reason
    # Pure noise: no consistent geometry -> few inliers or a failure, never an exception.
    rng = np.random.default_rng(0)
    noise = Matches(rng.uniform(40, 120, (200, 2)), rng.uniform(40, 120, (200, 2)), np.ones(200))
    assert isinstance(estimate_relative_pose(noise, FISHEYE), PoseTarget)
    with pytest.raises(InputError):
        estimate_relative_pose(few, FISHEYE, max_angle_deg=95.0)


@pytest.mark.parametrize(
    ("kind", "max_rot_deg", "max_t_deg"), [("indoor", 0.5, 2.0), ("outdoor", 1.0, 5.0)]
)
def test_pose_targets_on_synthetic_fisheye(kind: str, max_rot_deg: float, max_t_deg: float) -> None:
    """DIS matches on consecutive frames of a rendered ~190 degree KB4 sequence (hand-held
    indoors, driving outdoors) against the ground-truth relative poses."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.matchers import DISFlowMatcher

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # rendering is much faster without thread contention
    try:
        seq = synthetic.render_sequence(kind, FISHEYE, n_frames=3, seed=0)
    finally:
        torch.set_num_threads(threads)
    valid = FISHEYE.valid_mask().numpy()
    matcher = DISFlowMatcher()
    for i, j in ((0, 1), (1, 0), (1, 2)):
        m = matcher.match(seq.images[i], seq.images[j], valid)
        target = estimate_relative_pose(m, FISHEYE)
        gt = synthetic.relative_pose(seq.cam_from_world, i, j)
        assert target.ok, target.reason
        assert target.n_inliers > 0.5 * len(m)
        assert rotation_error_deg(target.R, gt[:3, :3]) < max_rot_deg
        assert translation_direction_error_deg(target.t, gt[:3, 3]) < max_t_deg
