"""Evaluation metrics: known perturbations give known errors; ground truth scores zero."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.metrics import (
    abs_rel,
    align_scale,
    auc,
    d_reproj,
    delta_125,
    relative_pose_errors,
    relative_poses,
    rotation_error_deg,
    summarize,
    translation_direction_error_deg,
)
from raytun3r_plugin.synthetic import correspondences, relative_pose, render_sequence


def rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


@pytest.fixture(scope="module")
def synth():
    f = 47.0 / math.radians(97.5)
    cam = cameras.KannalaBrandt4(
        96,
        96,
        {"fx": f, "fy": f, "cx": 47.5, "cy": 47.5, "k1": 0.01, "k2": 0.0, "k3": 0.0, "k4": 0.0},
        max_fov_deg=195.0,
    )
    return render_sequence("indoor", cam, n_frames=3, seed=11, flow_px=3.0)


def test_rotation_error_known_values():
    rng = np.random.default_rng(0)
    R = rot(rng.normal(size=3), 37.0)
    assert rotation_error_deg(R @ rot([0, 1, 0], 2.0), R) == pytest.approx(2.0, abs=1e-9)
    assert rotation_error_deg(R, R) == pytest.approx(0.0, abs=1e-9)
    assert rotation_error_deg(rot([1, 1, 0], 180.0), np.eye(3)) == pytest.approx(180.0, abs=1e-6)
    # tiny angles stay accurate (no acos precision loss)
    assert rotation_error_deg(rot([0, 0, 1], 1e-6), np.eye(3)) == pytest.approx(1e-6, rel=1e-6)
    batch = np.stack([rot([1, 0, 0], a) for a in (0.5, 10.0, 90.0)])
    np.testing.assert_allclose(
        rotation_error_deg(batch, np.eye(3)[None]), [0.5, 10.0, 90.0], atol=1e-9
    )
    t = rotation_error_deg(torch.from_numpy(batch), torch.eye(3, dtype=torch.float64))
    assert isinstance(t, torch.Tensor)
    np.testing.assert_allclose(t.numpy(), [0.5, 10.0, 90.0], atol=1e-9)
    f32 = rotation_error_deg(torch.from_numpy(batch).float(), np.eye(3))
    np.testing.assert_allclose(f32.numpy(), [0.5, 10.0, 90.0], atol=2e-3)


def test_translation_direction_signed_and_folded():
    a = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0, 0, 2.0]])
    b = np.array(
        [
            [-3.0, 0, 0],
            [math.cos(math.radians(100)), math.sin(math.radians(100)), 0],
            [2.0, 0, 0],
            [0, 0, 1e-3],
        ]
    )
    np.testing.assert_allclose(
        translation_direction_error_deg(a, b), [180.0, 100.0, 0.0, 0.0], atol=1e-9
    )
    np.testing.assert_allclose(
        translation_direction_error_deg(a, b, folded=True), [0.0, 80.0, 0.0, 0.0], atol=1e-9
    )
    assert math.isnan(translation_direction_error_deg(np.zeros(3), np.ones(3)))
    t = translation_direction_error_deg(torch.tensor(a), torch.tensor(b), folded=True)
    np.testing.assert_allclose(t.numpy(), [0.0, 80.0, 0.0, 0.0], atol=1e-9)


def _trajectory(n: int = 6) -> np.ndarray:
    rng = np.random.default_rng(1)
    out = []
    for k in range(n):
        R = rot(rng.normal(size=3), 5.0 * k)
        out.append(pose(R, rng.normal(size=3)))
    return np.stack(out)


def test_relative_pose_errors_gt_and_similarity_invariance():
    gt = _trajectory()
    res = relative_pose_errors(gt, gt)
    assert res["n_pairs"] == 5 and res["n_skipped"] == 0
    assert np.array_equal(res["pairs"], np.stack([np.arange(5), np.arange(1, 6)], -1))
    np.testing.assert_allclose(res["rotation_deg"], 0.0, atol=1e-6)
    np.testing.assert_allclose(res["translation_deg"], 0.0, atol=1e-6)
    # another world frame and another global scale: still zero
    S = pose(rot([1, 2, 3], 70.0), [5.0, -1.0, 2.0])
    pred = gt @ np.linalg.inv(S)
    pred[:, :3, 3] *= 3.7
    res = relative_pose_errors(pred, gt)
    np.testing.assert_allclose(res["rotation_deg"], 0.0, atol=1e-6)
    np.testing.assert_allclose(res["translation_deg"], 0.0, atol=1e-6)


def test_relative_pose_errors_known_perturbation_and_skips():
    gt = _trajectory()
    pred = gt.copy()
    # rotate camera 3 by 2 degrees about its optical axis (position unchanged)
    pred[3] = pose(rot([0, 0, 1], 2.0), [0, 0, 0]) @ gt[3]
    res = relative_pose_errors(pred, gt)
    np.testing.assert_allclose(res["rotation_deg"], [0, 0, 2.0, 2.0, 0], atol=1e-9)
    # the same camera centre: the direction error equals the angle the rotation moved it
    assert res["translation_deg"][[0, 1, 4]] == pytest.approx([0, 0, 0], abs=1e-6)
    # a pair with (almost) no ground-truth motion is skipped and counted, for every method
    gt2 = gt.copy()
    gt2[2] = pose(gt[1][:3, :3], gt[1][:3, 3])  # frame 2 identical to frame 1
    res2 = relative_pose_errors(pred, gt2, min_translation=1e-3)
    assert res2["n_skipped"] == 1 and res2["skipped_pairs"].tolist() == [[1, 2]]
    assert [1, 2] not in res2["pairs"].tolist() and res2["n_pairs"] == 4
    res3 = relative_pose_errors(gt, gt2, pairs=[(0, 2), (1, 2), (0, 5)])
    assert res3["pairs"].tolist() == [[0, 2], [0, 5]] and res3["n_skipped"] == 1
    with pytest.raises(ValueError):
        relative_pose_errors(gt, gt, pairs=[(0, 9)])
    rel = relative_poses(gt, np.array([[0, 1]]))[0]
    np.testing.assert_allclose(rel, gt[1] @ np.linalg.inv(gt[0]), atol=1e-12)


def test_d_reproj_zero_for_ground_truth(synth):
    cam = synth.camera
    for i, j in ((0, 1), (1, 2), (2, 0)):
        uv_i, uv_j, vis = correspondences(synth, i, j)
        T = relative_pose(synth.cam_from_world, i, j)
        det = d_reproj(synth.depth[i], cam, uv_i[vis], uv_j[vis], T, return_details=True)
        assert det["d_reproj"] < 0.05 and det["scale"] == pytest.approx(1.0, abs=1e-6)
        assert det["n_used"] == vis.sum() > 1000
        # depth known only up to scale: the fitted scale absorbs it
        det = d_reproj(synth.depth[i] * 2.5, cam, uv_i[vis], uv_j[vis], T, return_details=True)
        assert det["d_reproj"] < 0.05 and det["scale"] == pytest.approx(0.4, rel=1e-6)
        # 3-D residual variant with the other view's depth
        dj = d_reproj(
            synth.depth[i] * 2.5, cam, uv_i[vis], uv_j[vis], T, depth_j=synth.depth[j] * 2.5
        )
        assert dj < 0.05


def test_d_reproj_robust_and_sensitive(synth):
    cam = synth.camera
    uv_i, uv_j, vis = correspondences(synth, 0, 1)
    T = relative_pose(synth.cam_from_world, 0, 1)
    rng = np.random.default_rng(3)
    bad = synth.depth[0].copy()
    bad[rng.uniform(size=bad.shape) < 0.05] *= 4.0
    det = d_reproj(bad, cam, uv_i[vis], uv_j[vis], T, return_details=True)
    assert det["scale"] == pytest.approx(1.0, abs=0.03)  # outliers do not drag the scale
    conf = np.ones(vis.sum())
    det2 = d_reproj(
        synth.depth[0],
        cam,
        uv_i[vis],
        uv_j[vis],
        T,
        conf=conf * 0.2,
        conf_threshold=0.5,
        return_details=True,
    )
    assert det2["n_used"] == 0 and math.isnan(det2["d_reproj"])
    # a wrong depth shape (not a scale) gives a clearly non-zero error
    warped = synth.depth[0] ** 1.5
    assert d_reproj(warped, cam, uv_i[vis], uv_j[vis], T) > 0.3
    # a wrong pose too
    T_bad = pose(rot([0, 1, 0], 3.0), [0, 0, 0]) @ T
    assert d_reproj(synth.depth[0], cam, uv_i[vis], uv_j[vis], T_bad) > 1.0
    # torch inputs work
    v = d_reproj(
        torch.from_numpy(synth.depth[0]),
        cam,
        torch.from_numpy(uv_i[vis]),
        torch.from_numpy(uv_j[vis]),
        torch.from_numpy(T),
    )
    assert v < 0.05


def test_abs_rel_and_delta_known_values():
    rng = np.random.default_rng(5)
    gt = rng.uniform(1.0, 10.0, size=(20, 30))
    gt[0, :5] = 0.0  # unknown ground truth is ignored
    valid = gt > 0
    assert abs_rel(gt * 1.3, gt) == pytest.approx(0.0, abs=1e-12)
    assert abs_rel(gt * 1.3, gt, align="lstsq") == pytest.approx(0.0, abs=1e-12)
    assert delta_125(gt * 1.3, gt) == 1.0
    assert abs_rel(gt * 1.3, gt, align="none") == pytest.approx(0.3, abs=1e-12)
    # bias: AbsRel computed independently
    b = 0.7
    g = gt[valid]
    s = np.median(g) / np.median(g + b)
    expect = np.mean(np.abs(s * (g + b) - g) / g)
    assert abs_rel(gt + b, gt) == pytest.approx(expect, rel=1e-12)
    s_ls = np.sum((g + b) * g) / np.sum((g + b) ** 2)
    assert abs_rel(gt + b, gt, align="lstsq") == pytest.approx(
        np.mean(np.abs(s_ls * (g + b) - g) / g), rel=1e-12
    )
    assert abs_rel(gt + b, gt, align="none") == pytest.approx(np.mean(b / g), rel=1e-12)
    r = (s * (g + b)) / g
    assert delta_125(gt + b, gt) == pytest.approx(np.mean(np.maximum(r, 1 / r) < 1.25))
    # masks, batches, scale helper
    m = np.zeros_like(valid)
    m[5:, :] = True
    assert abs_rel(gt + b, gt, valid=m) == pytest.approx(
        np.mean(
            np.abs((np.median(gt[5:]) / np.median(gt[5:] + b)) * (gt[5:] + b) - gt[5:]) / gt[5:]
        )
    )
    batch = abs_rel(np.stack([gt * 2, gt + b]), np.stack([gt, gt]))
    assert batch.shape == (2,) and batch[0] == pytest.approx(0.0, abs=1e-12)
    assert align_scale(gt * 4.0, gt) == pytest.approx(0.25)
    assert math.isnan(abs_rel(gt, np.zeros_like(gt)))
    neg = gt.copy()
    neg[1, :] = -1.0
    assert delta_125(neg, gt, align="none") == pytest.approx(1.0 - 30 / valid.sum())


def test_depth_metrics_on_synthetic(synth):
    gt = synth.depth
    assert np.allclose(abs_rel(gt * 1.3, gt), 0.0, atol=1e-6)
    assert np.allclose(delta_125(gt * 0.2, gt, valid=synth.mask), 1.0)


def test_summarize_and_auc():
    gt = _trajectory()
    pred = gt.copy()
    pred[3] = pose(rot([0, 0, 1], 8.0), [0, 0, 0]) @ gt[3]
    res = relative_pose_errors(pred, gt)
    out = summarize(
        res, d_reproj=[0.1, 0.3, np.nan], abs_rel=[0.1, 0.2], delta_125=[0.9, 1.0], name="seq"
    )
    assert out["name"] == "seq" and out["n_pairs"] == 5 and out["n_skipped"] == 0
    assert out["rotation_deg"]["count"] == 5 and out["rotation_deg"]["median"] == pytest.approx(
        0.0, abs=1e-6
    )
    assert out["d_reproj"] == {
        "mean": pytest.approx(0.2),
        "median": pytest.approx(0.2),
        "count": 3,
        "n_nan": 1,
    }
    assert out["abs_rel"]["mean"] == pytest.approx(0.15) and out["delta_125"][
        "median"
    ] == pytest.approx(0.95)
    assert out["acc@5"] == pytest.approx(3 / 5) and out["acc@20"] == 1.0
    assert 0.6 < out["auc@10"] < 1.0
    assert auc([0.0, 5.0, np.nan], 10.0) == pytest.approx((1.0 + 0.5 + 0.0) / 3)
    assert math.isnan(auc([], 5.0))
