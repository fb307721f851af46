"""Rough calibration (raytun3r_plugin.adaptation.intrinsics, docs/intrinsics.md).

A synthetic indoor hand-held sequence is rendered with a known 190-degree KB4 camera at 128 px;
the adaptation set is matched with the default DIS matcher through a rough camera (focal +5 %,
k1 0.02 -> 0.05), and :func:`refine_intrinsics` must bring both back. Tolerances (measured,
docs/intrinsics.md): the refined focal lies within 2 % of the truth (DIS's flow shrinks by about
0.5 % towards the image-circle rim, which biases the focal long by 1.2-1.5 % at 128 px; with exact
matches the solver recovers it to 1e-8) and k1 ends at least 5 times closer to the truth than it
started (measured 13-29 times over seeds 0-4).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.adaptation import (
    AdaptationSet,
    AdaptConfig,
    Matches,
    Window,
    estimate_relative_pose,
    get_matcher,
    prepare_adaptation_set,
    refine_intrinsics,
)
from raytun3r_plugin.adaptation.intrinsics import DISTORTION_TERM, distortion_term
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.synthetic import render_sequence
from raytun3r_plugin.threads import torch_threads

SIZE, FRAMES, TRUE_K1, K1_START, FOCAL_OFF = 128, 16, 0.02, 0.05, 0.05
FOCAL_TOL = 0.02  # relative focal error after refinement (measured 1.2-1.5 %)
K1_FACTOR = 5.0  # k1 error shrinks at least this much (measured 13-29 x)


def rough_camera(true: cameras.Camera) -> cameras.Camera:
    """``true`` with a 5 % longer focal and k1 = K1_START."""
    rough = cameras.perturbed(true, focal=FOCAL_OFF)
    p = rough.params.clone()
    p[4] = K1_START
    return type(true)(true.width, true.height, p, max_fov_deg=true.max_fov_deg)


@pytest.fixture(scope="module")
def scene():
    """The module's tests run on one torch thread (tiny tensors); the setting is restored after."""
    with torch_threads(1):
        true = cameras.fisheye(SIZE, 190.0, "kb4", k=(TRUE_K1, 0.0, 0.0, 0.0))
        sequence = render_sequence("indoor", true, FRAMES, seed=0)
        rough = rough_camera(true)
        adaptation = prepare_adaptation_set(
            sequence.images, rough, get_matcher("dis"), n_windows=30
        )
        yield true, rough, sequence, adaptation


@pytest.fixture(scope="module")
def refined(scene):
    _, rough, _, adaptation = scene
    return refine_intrinsics(rough, adaptation)


def test_recovers_focal_and_k1_from_a_rough_camera(scene, refined):
    true, rough, _, _ = scene
    camera, report = refined
    f_true = float(true.params[0])
    assert report.refined and report.reason == "" and report.converged
    assert report.params == ["focal", "k1"]
    assert report.initial["fx"] == pytest.approx(f_true * (1 + FOCAL_OFF))
    assert report.initial["k1"] == pytest.approx(K1_START)
    # The focal: from 5 % off to within the stated tolerance, fx and fy scaled together.
    assert abs(float(camera.params[0]) / f_true - 1.0) < FOCAL_TOL
    assert float(camera.params[1]) == pytest.approx(
        float(camera.params[0]) * float(rough.params[1]) / float(rough.params[0])
    )
    assert report.final["fx"] == pytest.approx(float(camera.params[0]))
    # k1: at least K1_FACTOR times closer to the truth than it started.
    start_err = abs(K1_START - TRUE_K1)
    assert abs(float(camera.params[4]) - TRUE_K1) < start_err / K1_FACTOR
    # Everything else untouched.
    assert torch.equal(camera.params[2:4], rough.params[2:4])
    assert torch.equal(camera.params[5:], rough.params[5:])
    assert (type(camera), camera.width, camera.height, camera.max_fov_deg) == (
        type(rough),
        rough.width,
        rough.height,
        rough.max_fov_deg,
    )
    # The error goes down, and the report is JSON-able.
    assert report.error_after_px < 0.8 * report.error_before_px
    assert report.cost_after < report.cost_before
    assert report.pairs_used >= 20 and report.pairs_rotating == report.pairs_used
    assert 0 < report.focal_std < 0.01
    assert json.loads(json.dumps(report.to_dict()))["final"]["k1"] == pytest.approx(
        report.final["k1"]
    )


def test_deterministic(scene, refined):
    _, rough, _, adaptation = scene
    again, report = refine_intrinsics(rough, adaptation)
    assert torch.equal(again.params, refined[0].params)
    assert report.to_dict() == refined[1].to_dict()


def test_focal_only_keeps_k1(scene):
    true, rough, _, adaptation = scene
    camera, report = refine_intrinsics(rough, adaptation, params=("focal",))
    assert report.refined and report.params == ["focal"] and report.distortion_std is None
    assert float(camera.params[4]) == K1_START
    # With k1 held wrong the focal absorbs part of it, but still moves towards the truth.
    f_true = float(true.params[0])
    assert abs(float(camera.params[0]) / f_true - 1) < FOCAL_OFF


def test_first_distortion_term_per_model():
    assert distortion_term(cameras.fisheye(64, 190.0, "kb4")) == "k1"
    assert distortion_term(cameras.fisheye(64, 195.0, "ds")) == "xi"
    assert DISTORTION_TERM["pinhole"] is None


# --------------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------------


def _exact_set(camera, poses, seed=0) -> AdaptationSet:
    """One window per consecutive pose pair, with exact matches of random scene points."""
    rng = np.random.default_rng(seed)
    windows = []
    for k in range(len(poses) - 1):
        uv = rng.uniform(8, camera.width - 8, (400, 2))
        with torch.no_grad():
            rays, ok = camera.unproject(torch.from_numpy(uv))
        points = rays.numpy() * rng.uniform(2.0, 6.0, (len(uv), 1))
        rel = poses[k + 1] @ np.linalg.inv(poses[k])
        moved = points @ rel[:3, :3].T + rel[:3, 3]
        with torch.no_grad():
            uv_j, ok_j = camera.project(torch.from_numpy(moved))
        keep = ok.numpy() & ok_j.numpy()
        matches = Matches(
            uv[keep].astype(np.float32),
            uv_j.numpy()[keep].astype(np.float32),
            np.ones(int(keep.sum()), np.float32),
        )
        window = Window((k, k + 1))
        window.pairs[(0, 1)] = matches
        window.targets[(0, 1)] = estimate_relative_pose(matches, camera)
        windows.append(window)
    return AdaptationSet(windows, 0, [], "test")


def _forward_poses(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        pose = np.eye(4)
        pose[2, 3] = -0.3 * k  # cam_from_world: the camera drives forward along +z
        out.append(pose)
    return out


def test_pure_forward_translation_is_left_unchanged_with_a_reason():
    camera = rough_camera(cameras.fisheye(SIZE, 190.0, "kb4", k=(TRUE_K1, 0.0, 0.0, 0.0)))
    adaptation = _exact_set(camera, _forward_poses(7))
    assert all(w.targets[(0, 1)].ok for w in adaptation.windows)
    result, report = refine_intrinsics(camera, adaptation)
    assert result is camera and not report.refined
    assert "do not determine the focal" in report.reason and "forward" in report.reason
    assert report.pairs_rotating == 0
    assert not report.focal_std_before <= 0.01  # infinite or large: nothing determines it
    assert report.final == report.initial


def test_too_few_pairs_and_bad_params_are_refused(scene):
    _, rough, _, adaptation = scene
    window = adaptation.windows[0]
    single = Window(window.frames[:2])
    single.pairs[(0, 1)] = window.pairs[(0, 1)]
    single.targets[(0, 1)] = window.targets[(0, 1)]
    with pytest.raises(InputError, match="at least 3 frame pairs"):
        refine_intrinsics(rough, AdaptationSet([single], 0, [], "one"))
    with pytest.raises(InputError, match="unknown parameter"):
        refine_intrinsics(rough, adaptation, params=("cx",))
    with pytest.raises(InputError, match="params is empty"):
        refine_intrinsics(rough, adaptation, params=())
    pinhole = cameras.Pinhole(64, 64, {"fx": 40.0, "fy": 40.0, "cx": 31.5, "cy": 31.5})
    with pytest.raises(InputError, match="no distortion term"):
        refine_intrinsics(pinhole, adaptation)


# --------------------------------------------------------------------------------------------
# Opt-in in adapt
# --------------------------------------------------------------------------------------------


def test_config_field_is_off_by_default_and_out_of_the_identity():
    import hashlib
    from dataclasses import asdict

    assert AdaptConfig().refine_intrinsics is False
    # The self-supervised fit without a teacher (the library's default before recipes), at its
    # old input size: the identity of a configuration without the option is what it was before
    # it existed. (The photometric and teacher options, added later, are left out the same way;
    # the recipe's name takes no part in it.)
    off = AdaptConfig.from_recipe("matches", input_size=504)
    assert "refine_intrinsics" not in off.to_dict()
    later = (
        "refine_intrinsics",
        "photo_sigma",
        "photo_pixels",
        "teacher_views",
        "teacher_fov_deg",
        "teacher_max_coverage",
        "teacher_view_weights",
        "pose_gate",
        "check_frames",
        "check_veto",
        "pose_windows",
        "lr_without_teacher",
    )
    legacy = {k: v for k, v in asdict(off).items() if k not in (*later, "recipe")}
    del legacy["weights"]["photo"], legacy["weights"]["teacher"]
    for resumable in ("steps", "checkpoint_every", "cache_dir"):
        legacy.pop(resumable)
    digest = hashlib.sha256(json.dumps(legacy, sort_keys=True, default=str).encode()).hexdigest()
    assert off.identity() == digest[:16]
    on = AdaptConfig.from_recipe("matches", input_size=504, refine_intrinsics=True)
    assert on.to_dict()["refine_intrinsics"] is True and on.identity() != off.identity()
    assert AdaptConfig(**json.loads(json.dumps(on.to_dict()))) == on
    with pytest.raises(InputError):
        AdaptConfig(refine_intrinsics=1)


def test_adapt_refines_the_camera_only_when_asked(scene):
    pytest.importorskip("depth_anything_3")
    from depth_anything_3.utils.logger import logger
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    from raytun3r_plugin.adaptation import adapt

    true, rough, sequence, _ = scene
    level, logger.level = logger.level, 1
    try:
        torch.manual_seed(0)
        model = build_tiny_network().eval()
        base = dict(steps=1, input_size=112, n_windows=30, seed=0, guard=False)
        off = adapt(model, rough, sequence.images, AdaptConfig(**base), progress=False)
        on = adapt(
            model,
            rough,
            sequence.images,
            AdaptConfig(**base, refine_intrinsics=True),
            progress=False,
        )
    finally:
        logger.level = level
    assert "intrinsics" not in off.training_info
    assert torch.equal(off.camera.params, rough.params)
    report = on.training_info["intrinsics"]
    assert report["refined"] and report["initial"]["fx"] == pytest.approx(float(rough.params[0]))
    assert on.training_info["config"]["refine_intrinsics"] is True
    # The adapter carries the refined camera.
    assert float(on.camera.params[0]) == pytest.approx(report["final"]["fx"])
    assert abs(float(on.camera.params[0]) / float(true.params[0]) - 1) < FOCAL_TOL
