"""Issue 12: the pinhole-view teacher (``LossWeights.teacher``, ``adaptation/teacher.py``).

The teacher's samples are the unpatched model's Center-PH depth read back on the fisheye pixels;
its loss leaves one free scale per view; in the trainer the term is off by default (identities
unchanged), validated, keeps the windows the parallax gate finds without signal while leaving
their matches out of the reprojection, and a teacher fit lowers the teacher term.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import apply, synthetic
from raytun3r_plugin.adaptation.config import TEACHER_WEIGHTS, AdaptConfig
from raytun3r_plugin.adaptation.losses import LossWeights, grouped_silog_loss, silog_loss
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adaptation.step import objective_value
from raytun3r_plugin.adaptation.teacher import teacher_targets, teacher_views
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.adapter_report import describe_file
from raytun3r_plugin.apps.evaluation import center_pinhole, run_method
from raytun3r_plugin.cameras import KannalaBrandt4
from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from tests.helpers import small_fit_config, small_kb4

TEACHER_ONLY = LossWeights(**TEACHER_WEIGHTS)


@pytest.fixture(scope="module")
def room():
    camera = small_kb4()
    return camera, synthetic.render_sequence("indoor", camera, n_frames=6, seed=7)


def _config(tmp_path, **changes) -> AdaptConfig:
    return small_fit_config(tmp_path, "matches", **changes)


def test_grouped_silog_leaves_one_scale_per_group():
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(40, generator=generator) + 0.5
    groups = torch.arange(40) % 2
    # The prediction is the target with another scale in each group: no error per group.
    pred = torch.where(groups == 0, 2.0 * target, 0.5 * target)
    assert float(grouped_silog_loss(pred, target, groups)) < 1e-12
    assert float(silog_loss(pred, target)) > 0.1  # one shared scale cannot explain it
    noisy = pred * (1 + 0.1 * torch.rand(40, generator=generator))
    expected = (
        silog_loss(noisy[groups == 0], target[groups == 0])
        + silog_loss(noisy[groups == 1], target[groups == 1])
    ) / 2
    assert torch.allclose(grouped_silog_loss(noisy, target, groups), expected)
    # A group with one sample has no variance to measure and is left out.
    single = torch.tensor([0, 0, 0, 1])
    values = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert torch.allclose(
        grouped_silog_loss(values * 1.5, values, single), torch.tensor(0.0), atol=1e-12
    )


def test_teacher_samples_are_the_center_ph_depth_on_the_fisheye_pixels(room, tmp_path):
    camera, seq = room
    model = build_tiny_network()
    config = _config(tmp_path)
    problem = prepare_problem(camera, seq.images, config)
    targets = teacher_targets(model, problem, ("centre",), 110.0, seed=0, max_samples=10_000)
    assert sorted(targets) == list(range(len(problem.windows)))
    window = problem.windows[0][0]
    center = run_method(model, seq, "center-ph", frames=list(window.frames), window=3)
    valid = problem.valid.numpy()
    for k, frame in enumerate(window.frames):
        uv, values, views = targets[0][k]
        assert uv.shape[0] > 50 and bool((views == 0).all())
        cols, rows = uv[:, 0].long(), uv[:, 1].long()
        assert valid[rows, cols].all() and bool((values > 0).all())
        np.testing.assert_allclose(
            values.numpy(), center.depth[frame][rows, cols], rtol=1e-4, atol=1e-6
        )
    # Seeded: the same call gives the same samples; another seed another subset.
    again = teacher_targets(model, problem, ("centre",), 110.0, seed=0, max_samples=40)
    other = teacher_targets(model, problem, ("centre",), 110.0, seed=1, max_samples=40)
    twice = teacher_targets(model, problem, ("centre",), 110.0, seed=0, max_samples=40)
    assert torch.equal(again[0][0][0], twice[0][0][0])
    assert not torch.equal(again[0][0][0], other[0][0][0])
    assert again[0][0][0].shape[0] == 40


def test_teacher_views_are_named_and_the_teacher_is_the_unpatched_model(room, tmp_path):
    camera, seq = room
    views = teacher_views(camera, ("centre", "left", "right"), 110.0)
    assert {view.name for view in views} == {"centre", "left", "right"}
    assert teacher_views(camera, ("centre",), 90.0)[0].camera.fx == pytest.approx(
        center_pinhole(camera, 90.0).fx
    )
    for bad in ((), ("centre", "centre"), ("front",)):
        with pytest.raises(InputError, match="teacher views"):
            teacher_views(camera, bad, 110.0)
    model = build_tiny_network()
    problem = prepare_problem(camera, seq.images, _config(tmp_path))
    with apply(model, camera), pytest.raises(AlreadyAppliedError, match="unpatched"):
        teacher_targets(model, problem, ("centre",), 110.0, seed=0)


def test_teacher_options_are_validated_and_out_of_the_identity_when_off():
    off = AdaptConfig.from_recipe("matches")
    assert "teacher_views" not in off.to_dict() and "teacher" not in off.to_dict()["weights"]
    on = AdaptConfig.from_recipe(
        "matches", weights={"teacher": 2.0}, teacher_views=("centre",), teacher_fov_deg=90.0
    )
    record = on.to_dict()
    assert record["teacher_views"] == ["centre"] and record["teacher_fov_deg"] == 90.0
    assert AdaptConfig(**json.loads(json.dumps(record))) == on
    assert on.identity() != off.identity()
    for changes in (
        {"teacher_views": ("centre", "sideways")},
        {"teacher_views": ()},
        {"teacher_views": ("left", "left")},
        {"teacher_fov_deg": 180.0},
        {"teacher_fov_deg": 0.0},
        {"teacher_fov_deg": float("nan")},
    ):
        with pytest.raises(InputError, match="AdaptConfig.teacher"):
            AdaptConfig(**changes)
    with pytest.raises(InputError, match="weights.teacher"):
        AdaptConfig(weights=dataclasses.replace(off.weights, teacher=-1.0))


def test_a_teacher_fit_lowers_the_teacher_term_and_leaves_the_backbone(room, tmp_path):
    camera, seq = room
    model = build_tiny_network()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    config = _config(tmp_path, steps=12, lr=3e-2, weights=TEACHER_ONLY)
    adapter = adapt(model, camera, seq.images, config, progress=False, out_path=tmp_path / "t")
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    problem = prepare_problem(camera, seq.images, config)
    problem.teacher = teacher_targets(model, problem, ("centre",), 110.0, seed=0)
    start = objective_value(model, Adapter.for_model(model), problem, config)
    end = objective_value(model, adapter, problem, config)
    assert end["teacher"] < 0.9 * start["teacher"]
    assert adapter.training_info["config"]["teacher_views"] == ["centre"]
    records = [json.loads(line) for line in (tmp_path / "t.log.jsonl").read_text().splitlines()]
    assert all(r["n_teacher"] > 0 and r["n_matches"] == 0 for r in records)


def test_with_a_teacher_the_gate_keeps_every_window_but_not_its_reprojection(room, tmp_path):
    """A threshold no window reaches stops the match fit ("no signal"); with the teacher term the
    windows are kept for it and the pose term, and none of them reprojects."""
    camera, seq = room
    base = _config(tmp_path, min_parallax_px=1e6, pose_source="hybrid")
    stopped = adapt(build_tiny_network(), camera, seq.images, base, progress=False)
    assert stopped.training_info["verdict"]["status"] == "no signal"
    taught = dataclasses.replace(base, weights=dataclasses.replace(base.weights, teacher=10.0))
    fitted = adapt(
        build_tiny_network(), camera, seq.images, taught, progress=False, out_path=tmp_path / "g"
    )
    gate = fitted.training_info["parallax_gate"]
    assert gate["windows_kept"] == 2 and gate["windows_dropped"] == 0
    assert gate["windows_reprojected"] == 0
    records = [json.loads(line) for line in (tmp_path / "g.log.jsonl").read_text().splitlines()]
    assert len(records) == 4
    assert all(r["reproj"] == 0.0 and r["teacher"] > 0 and r["n_pose"] > 0 for r in records)
    assert fitted.training_info["verdict"]["status"] != "no signal"


def test_a_rig_fit_refuses_the_teacher_term_before_any_work():
    from raytun3r_plugin.adaptation.rig import adapt_rig

    config = AdaptConfig(weights=dataclasses.replace(AdaptConfig().weights, teacher=1.0))
    with pytest.raises(InputError, match="no pinhole-view teacher term"):
        adapt_rig(build_tiny_network(), None, config, progress=False)


def test_on_a_lens_the_views_cover_the_fit_runs_without_the_term_bit_for_bit(room, tmp_path):
    """The lens gate: above ``teacher_max_coverage`` the teacher is left out and the fit is the
    one without the term, table for table; the choice and the coverage are recorded."""
    camera, seq = room
    base = _config(tmp_path, pose_source="hybrid", min_parallax_px=0.0)
    taught = dataclasses.replace(base, weights=dataclasses.replace(base.weights, teacher=10.0))
    plain = adapt(build_tiny_network(), camera, seq.images, base, progress=False)
    gated = adapt(
        build_tiny_network(),
        camera,
        seq.images,
        dataclasses.replace(taught, teacher_max_coverage=0.0),
        progress=False,
    )
    record = gated.training_info["teacher"]
    assert record["used"] is False and 0.2 < record["coverage"] < 0.5
    for a, b in zip(plain.parameters(), gated.parameters(), strict=True):
        assert torch.equal(a, b)
    used = adapt(build_tiny_network(), camera, seq.images, taught, progress=False)
    assert used.training_info["teacher"]["used"] is True
    assert not all(
        torch.equal(a, b) for a, b in zip(plain.parameters(), used.parameters(), strict=True)
    )
    assert "teacher" not in plain.training_info
    # raytun3r inspect says which it was, and the fit's verdict.
    for adapter, word in ((gated, "left out"), (used, "used")):
        path = tmp_path / f"{word.replace(' ', '_')}.safetensors"
        adapter.save(path)
        summary = describe_file(path)
        assert f"pinhole-view teacher: {word} (its largest view covers" in summary
        assert "verdict:" in summary


def test_the_lens_gate_counts_each_view_on_its_own(room):
    """Three views cover most of a 190-degree lens together, each about a third of it: the gate
    reads the largest single view, so a wide lens keeps a three-view teacher."""
    from raytun3r_plugin.adaptation.teacher import teacher_coverage
    from raytun3r_plugin.baselines.multi_ph import view_coverage

    camera, _ = room
    names = ("centre", "left", "right")
    views = teacher_views(camera, names, 110.0)
    assert view_coverage(camera, views) > 0.6
    single = teacher_coverage(camera, names, 110.0)
    assert single == max(view_coverage(camera, [view]) for view in views)
    assert 0.2 < single < AdaptConfig().teacher_max_coverage
    narrow = KannalaBrandt4(84, 70, [40.0, 40.0, 41.5, 34.5, 0.0, 0.0, 0.0, 0.0], max_fov_deg=120.0)
    assert teacher_coverage(narrow, ("centre",), 110.0) > 0.8


def test_weighted_groups_are_a_weighted_sum_and_an_empty_group_adds_nothing():
    generator = torch.Generator().manual_seed(1)
    target = torch.rand(60, generator=generator) + 0.5
    pred = target * (1 + 0.2 * torch.rand(60, generator=generator))
    groups = torch.arange(60) % 3
    each = [silog_loss(pred[groups == g], target[groups == g]) for g in range(3)]
    weighted = grouped_silog_loss(pred, target, groups, (1.0, 0.3, 0.0))
    assert torch.allclose(weighted, each[0] + 0.3 * each[1])
    # Equal weights of 1/n are the mean, the default.
    thirds = grouped_silog_loss(pred, target, groups, (1 / 3, 1 / 3, 1 / 3))
    assert torch.allclose(thirds, grouped_silog_loss(pred, target, groups))
    # Group 1 absent: the others keep their own weights (no renormalisation).
    kept = groups != 1
    assert torch.allclose(
        grouped_silog_loss(pred[kept], target[kept], groups[kept], (1.0, 0.3, 2.0)),
        each[0] + 2.0 * each[2],
    )
    # The weights carry the gradient: a zero weight leaves its group's samples untouched.
    leaf = pred.clone().requires_grad_(True)
    grouped_silog_loss(leaf, target, groups, (1.0, 0.0, 1.0)).backward()
    assert bool((leaf.grad[groups == 1] == 0).all()) and bool(leaf.grad[groups == 0].abs().sum())


def test_view_weights_are_validated_ordered_by_the_views_and_out_of_the_identity_by_default():
    on = dataclasses.replace(AdaptConfig().weights, teacher=10.0)
    views = ("centre", "left", "right")
    plain = AdaptConfig(weights=on, teacher_views=views, teacher_view_weights=None)
    weighted = AdaptConfig(
        weights=on,
        teacher_views=views,
        teacher_view_weights={"right": 0.3, "centre": 1, "left": 0.3},
    )
    assert plain.view_weights() is None and "teacher_view_weights" not in plain.to_dict()
    assert weighted.view_weights() == (1.0, 0.3, 0.3)  # in the order of teacher_views
    record = json.loads(json.dumps(weighted.to_dict()))
    assert record["teacher_view_weights"] == {"centre": 1, "left": 0.3, "right": 0.3}
    assert AdaptConfig(**record) == weighted and weighted.identity() != plain.identity()
    # With the term off the weights are not part of the fit and not of its identity.
    off = AdaptConfig.from_recipe(
        "matches", teacher_views=views, teacher_view_weights={"centre": 1, "left": 1, "right": 1}
    )
    assert "teacher_view_weights" not in off.to_dict()
    assert off.identity() == AdaptConfig.from_recipe("matches", teacher_views=views).identity()
    # The default recipe's weights name its own views; other views given alone count equally.
    assert AdaptConfig().view_weights() == (1.0, 0.3, 0.3)
    assert AdaptConfig(teacher_views=("centre", "left")).view_weights() is None
    for bad in (
        {"centre": 1.0, "left": 0.3},  # a view without a weight
        {"centre": 1.0, "left": 0.3, "right": 0.3, "down": 1.0},  # a weight without a view
        {"centre": -1.0, "left": 0.3, "right": 0.3},
        {"centre": float("nan"), "left": 0.3, "right": 0.3},
        {"centre": 0.0, "left": 0.0, "right": 0.0},
        {"centre": True, "left": 0.3, "right": 0.3},
        [1.0, 0.3, 0.3],
    ):
        with pytest.raises(InputError, match="teacher_view_weights .*naming exactly the teacher"):
            AdaptConfig(weights=on, teacher_views=views, teacher_view_weights=bad)


def test_teacher_samples_are_indexed_in_the_order_the_views_are_named(room, tmp_path):
    """The view index of a sample is its view's place in ``names`` (the order of the weights),
    whatever the order of the Multi-PH views; samples are the same either way."""
    camera, seq = room
    model = build_tiny_network()
    problem = prepare_problem(camera, seq.images, _config(tmp_path))
    kwargs = {"seed": 0, "max_samples": 100_000}
    one = teacher_targets(model, problem, ("centre", "left"), 110.0, **kwargs)
    other = teacher_targets(model, problem, ("left", "centre"), 110.0, **kwargs)
    centre = teacher_targets(model, problem, ("centre",), 110.0, **kwargs)
    uv, value, view = one[0][0]
    uv2, value2, view2 = other[0][0]
    assert torch.equal(uv, uv2) and torch.equal(value, value2)
    assert set(view.tolist()) == {0, 1} and torch.equal(view2, 1 - view)
    # The centre view's samples are those of the centre view alone.
    assert torch.equal(uv[view == 0], centre[0][0][0])


def test_a_zero_view_weight_is_the_fit_without_that_view(room, tmp_path):
    """The trainer passes the weights to the term: a side view at weight 0 gives the centre-only
    fit's objective and tables; a positive weight changes the fit."""
    camera, seq = room
    # Every sample kept (no seeded subset draws), so the centre samples are the same either way.
    base = _config(tmp_path, weights=TEACHER_ONLY, lr=3e-2, steps=3)
    centre_only = adapt(build_tiny_network(), camera, seq.images, base, progress=False)
    two = dataclasses.replace(base, teacher_views=("centre", "left"))
    silent, heard = (
        adapt(
            build_tiny_network(),
            camera,
            seq.images,
            dataclasses.replace(two, teacher_view_weights={"centre": 1.0, "left": left}),
            progress=False,
        )
        for left in (0.0, 1.0)
    )
    pairs = list(zip(centre_only.parameters(), silent.parameters(), strict=True))
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in pairs)
    assert not all(
        torch.allclose(a, b, atol=1e-6)
        for a, b in zip(centre_only.parameters(), heard.parameters(), strict=True)
    )
    assert silent.training_info["config"]["teacher_view_weights"] == {"centre": 1.0, "left": 0.0}
