"""Fit recipes: one home for the settings a fit uses, recorded in every adapter file
(docs/recipes.md)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from raytun3r_plugin import registry, synthetic
from raytun3r_plugin.adaptation.check import check_frame_count, held_out_reprojection
from raytun3r_plugin.adaptation.config import DEFAULT_WEIGHTS, RECIPE_LR, AdaptConfig
from raytun3r_plugin.adaptation.losses import LossWeights
from raytun3r_plugin.adaptation.recipes import RECIPES, get_recipe, recipe_names
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.adapter_report import describe_file
from raytun3r_plugin.errors import InputError, Raytun3rError
from raytun3r_plugin.registry import native_input_size

pytest.importorskip("depth_anything_3")


@pytest.fixture(scope="module")
def network():
    from raytun3r_plugin.weights import load_backbone

    return load_backbone("raytun3r-da3-tiny-v3")


@pytest.fixture(scope="module")
def segment():
    """18 frames of a synthetic indoor room through a 190-degree KB4 lens at 112 px."""
    from raytun3r_plugin.apps.demo import demo_camera

    camera = demo_camera(112)
    return camera, synthetic.render_sequence("indoor", camera, n_frames=18, seed=31).images


@pytest.fixture
def short_default(monkeypatch):
    """The default recipe with a test-sized budget (3 steps, 3 windows), as the registry's own:
    everything that reads the recipe by name sees it."""
    short = dataclasses.replace(RECIPES["default"], changes={"steps": 3, "n_windows": 3})
    monkeypatch.setitem(RECIPES, "default", short)
    return short


def test_the_default_recipe_is_adapt_configs_defaults_and_every_recipe_builds():
    assert recipe_names()[0] == "default"
    assert {"default", "paper", "supervised"} <= set(recipe_names())
    assert AdaptConfig.from_recipe("default") == AdaptConfig()
    shipped = AdaptConfig()
    assert shipped.pose_source == "hybrid" and shipped.weights.as_dict() == DEFAULT_WEIGHTS
    assert shipped.weights.pose == pytest.approx(0.3) and shipped.weights.teacher == 10.0
    assert shipped.view_weights() == (1.0, 0.3, 0.3) and shipped.input_size is None
    for name in recipe_names():
        recipe = get_recipe(name)
        config = AdaptConfig.from_recipe(name)
        assert config.recipe == name and isinstance(recipe.version, int) and recipe.summary
        assert recipe.evidence, f"{name}: every recipe says where it was chosen"
        # What a recipe records is itself: no change from itself, and its file form rebuilds it.
        assert config.recipe_record() == {"name": name, "version": recipe.version, "changes": {}}
        assert AdaptConfig(**json.loads(json.dumps(config.to_dict()))) == config
    paper = AdaptConfig.from_recipe("paper")
    assert paper.weights.as_dict() == {k: v for k, v in LossWeights(depth=0.0).as_dict().items()}
    assert (paper.pose_source, paper.pe_regulariser, paper.robust_px, paper.lr) == (
        "model",
        "absolute",
        None,
        1e-3,
    )
    assert AdaptConfig.supervised() == AdaptConfig.from_recipe("supervised")
    assert get_recipe("supervised").supervised and not get_recipe("default").supervised


def test_unknown_recipes_and_fields_are_refused_by_name():
    with pytest.raises(InputError, match="unknown fit recipe 'fast'.*default, "):
        AdaptConfig.from_recipe("fast")
    with pytest.raises(InputError, match="no field 'step'"):
        AdaptConfig.from_recipe("default", step=3)
    with pytest.raises(Raytun3rError, match="weights.pose"):
        AdaptConfig.from_recipe("default", weights={"pose": -1.0})


def test_changes_are_recorded_against_the_recipe_and_weights_merge():
    config = AdaptConfig.from_recipe(
        "default", weights={"pose": 1.0}, steps=50, cache_dir="/tmp/x", checkpoint_every=0
    )
    assert config.weights.as_dict() == {**DEFAULT_WEIGHTS, "pose": 1.0}
    record = config.recipe_record()
    # Where files go and how often a run saves are not settings of the fit.
    assert record == {
        "name": "default",
        "version": RECIPES["default"].version,
        "changes": {"steps": [300, 50], "weights.pose": [0.3, 1.0]},
    }
    replaced = AdaptConfig.from_recipe("default", weights=LossWeights())
    assert replaced.weights == LossWeights()
    # A config built by hand records its changes from the default recipe.
    by_hand = AdaptConfig(pose_source="targets", input_size=280)
    assert by_hand.recipe_record()["changes"] == {
        "pose_source": ["hybrid", "targets"],
        "input_size": [None, 280],
    }


def test_the_input_size_is_the_backbones_own(network):
    assert native_input_size(network) == 112
    from raytun3r_plugin.patches.da3_networks import build_network

    assert native_input_size(build_network("da3-small")) == 504
    # A size given to the backbone's own is no change from the recipe.
    at_own = AdaptConfig.from_recipe("default", model=network, input_size=112)
    assert at_own.recipe_record(network)["changes"] == {}
    other = AdaptConfig.from_recipe("default", model=network, input_size=84)
    assert other.recipe_record(network)["changes"] == {"input_size": [112, 84]}


def test_a_backbone_familys_declared_changes_apply_and_are_recorded(network, monkeypatch):
    spec, _ = registry.spec_for(network)
    changed = dataclasses.replace(spec, recipe_changes={"default": {"lr": 0.01}})
    monkeypatch.setitem(registry._SPECS, spec.family, changed)
    assert registry.spec_for(network)[0] is changed
    config = AdaptConfig.from_recipe("default", model=network)
    assert config.lr == 0.01 and AdaptConfig.from_recipe("default").lr is None
    record = config.recipe_record(network)
    assert record["changes"] == {} and record["backbone_changes"] == {"lr": 0.01}
    # A user's change still wins over the family's, and is recorded against it.
    mine = AdaptConfig.from_recipe("default", model=network, lr=0.02)
    assert mine.recipe_record(network)["changes"] == {"lr": [0.01, 0.02]}
    assert AdaptConfig.from_recipe("paper", model=network).lr == 1e-3


def test_every_path_that_fits_takes_the_familys_declared_changes(network, monkeypatch, capsys):
    """``raytun3r adapt`` and ``adapt-rig``, the fleet, the demo and the benchmark build their
    settings with the model, so a family's declared change reaches them as it reaches
    ``adapt()`` without a config; a user's option still wins."""
    from raytun3r_plugin.apps import cli_adapt, fleet
    from raytun3r_plugin.apps.cli import build_parser
    from raytun3r_plugin.apps.fits import adapt_config, fit_description

    spec, _ = registry.spec_for(network)
    declared = {"lr": 0.01, "n_windows": 12}
    changed = dataclasses.replace(spec, recipe_changes={"default": declared})
    monkeypatch.setitem(registry._SPECS, spec.family, changed)
    words = ["adapt", "--backbone", "da3-small", "--camera", "c.yaml", "--frames", "f"]
    words += ["--out", "a.safetensors"]
    args = build_parser().parse_args(words)
    settings = cli_adapt._adapt_settings(args)
    assert cli_adapt._adapt_config(args, settings, False, model=network).lr == 0.01
    # No model: the step is left to the backbone, resolved when the fit starts.
    assert cli_adapt._adapt_config(args, settings, False).lr is None
    mine = build_parser().parse_args([*words, "--windows", "20"])
    config = cli_adapt._adapt_config(mine, cli_adapt._adapt_settings(mine), False, network)
    assert (config.lr, config.n_windows) == (0.01, 20)
    record = {"recipe": "default", "recipe_changes": {}, "size": 112}
    assert fleet._config(record, False, network).lr == 0.01
    assert fleet._config(record, True, network).lr == AdaptConfig.supervised().lr
    fit = adapt_config(112, 3, model=network)
    # Without a model, the recipe alone (experiments/README.md): its own step, not the family's.
    assert adapt_config(112, 3).resolved_for(network).lr == RECIPE_LR
    assert fit.lr == 0.01 and fit.recipe_record(network)["changes"] == {"steps": [300, 3]}
    assert "the backbone family's: lr 0.01, n_windows 12" in fit_description(fit, network)
    assert "changed: steps 3" in fit_description(fit, network)
    from raytun3r_plugin.apps.cli import main

    assert main(["recipes"]) == 0  # the listing names what each family changes
    listing = capsys.readouterr().out
    assert f"backbone family {spec.family!r} changes 'default': lr 0.01, n_windows 12" in listing
    assert main(["recipes", "--verbose"]) == 0  # what the recipe leaves to the backbone, said
    verbose = capsys.readouterr().out
    assert "    lr: the backbone family's step (0.003 unless the family declares one)" in verbose
    assert "    input_size: the backbone's own" in verbose


def test_the_da3_family_declares_its_step_for_both_of_its_specs(network):
    """Depth Anything 3's measured change (patches/da3.py): Adam's step 1e-2 where the teacher is
    on, the recipe's 3e-3 where it is off; the nested model is the same family."""
    from raytun3r_plugin.patches import da3

    config = AdaptConfig.from_recipe("default", model=network)
    assert (config.lr, config.lr_without_teacher) == (1e-2, 3e-3)
    assert da3.NESTED_SPEC.recipe_changes == da3.SPEC.recipe_changes
    # A step the user chooses is the step everywhere, unless they give the other one too.
    mine = AdaptConfig.from_recipe("default", model=network, lr=2e-2)
    assert (mine.lr, mine.lr_without_teacher) == (2e-2, None)
    assert mine.recipe_record(network)["changes"] == {
        "lr": [0.01, 0.02],
        "lr_without_teacher": [0.003, None],
    }
    both = AdaptConfig.from_recipe("default", model=network, lr=2e-2, lr_without_teacher=1e-3)
    assert (both.lr, both.lr_without_teacher) == (2e-2, 1e-3)
    # Only the default recipe is changed: another recipe, or no model, is the recipe's own.
    assert AdaptConfig.from_recipe("paper", model=network).lr == 1e-3
    assert AdaptConfig.from_recipe("default").lr_without_teacher is None


def test_a_hand_built_config_leaves_the_step_to_the_backbone_family(network, monkeypatch):
    """``AdaptConfig(...)`` built by hand is the default recipe with the family's step, as
    ``adapt()`` without a config is: the step is resolved with the model (as the input size is);
    a step given is kept, and recorded as a change."""
    hand_built = AdaptConfig(steps=3)
    assert hand_built.lr is None
    resolved = hand_built.resolved_for(network)
    assert (resolved.lr, resolved.lr_without_teacher, resolved.input_size) == (1e-2, 3e-3, 112)
    assert (
        resolved.to_dict()
        == AdaptConfig.from_recipe("default", model=network, steps=3)
        .resolved_for(network)
        .to_dict()
    )
    assert hand_built.recipe_record(network)["changes"] == {"steps": [300, 3]}
    # A step of the user's own is every fit's step, and differs from the family's.
    mine = AdaptConfig(steps=3, lr=3e-3).resolved_for(network)
    assert (mine.lr, mine.lr_without_teacher) == (3e-3, None)
    assert mine.recipe_record(network)["changes"] == {
        "lr": [0.01, 0.003],
        "lr_without_teacher": [0.003, None],
        "steps": [300, 3],
    }
    # Their own step where the teacher is off is kept beside the family's larger one.
    theirs = AdaptConfig(lr_without_teacher=1e-3).resolved_for(network)
    assert (theirs.lr, theirs.lr_without_teacher) == (1e-2, 1e-3)
    # A recipe that sets its own step is not the family's to change.
    assert AdaptConfig.from_recipe("supervised").resolved_for(network).lr == 3e-2
    # A family that declares no step: the recipe's own.
    spec, _ = registry.spec_for(network)
    monkeypatch.setitem(registry._SPECS, spec.family, dataclasses.replace(spec, recipe_changes={}))
    plain = AdaptConfig().resolved_for(network)
    assert (plain.lr, plain.lr_without_teacher) == (RECIPE_LR, None) == (3e-3, None)
    with pytest.raises(InputError, match="AdaptConfig.lr"):
        AdaptConfig(lr=0.0)
    with pytest.raises(InputError, match="resolved_for"):
        AdaptConfig().step_size()  # the optimiser never meets an unresolved step


def test_adapt_with_a_hand_built_config_fits_with_the_familys_step(network, segment):
    camera, frames = segment
    info = adapt(network, camera, frames[:9], AdaptConfig(steps=2), progress=False).training_info
    assert info["config"]["lr"] == 0.01 and info["teacher"]["used"] is True
    assert info["recipe"]["changes"] == {"steps": [300, 2]}


def test_adapt_without_a_config_fits_the_default_recipe_at_the_backbones_size(
    network, segment, short_default, capsys
):
    camera, frames = segment
    before = {k: v.clone() for k, v in network.state_dict().items()}
    adapter = adapt(network, camera, frames[:9], progress=False)
    info = adapter.training_info
    assert info["recipe"] == {
        "name": "default",
        "version": short_default.version,
        "changes": {},
        "backbone_changes": {"lr": 0.01, "lr_without_teacher": 0.003},  # the DA3 family's
    }
    assert info["config"]["input_size"] == 112 and info["input"]["long_side"] == 112
    assert info["config"]["pose_source"] == "hybrid" and info["teacher"]["used"] is True
    assert info["config"]["lr"] == 0.01  # the teacher is on: the family's larger step
    assert info["steps"] == 3
    assert all(torch.equal(before[k], v) for k, v in network.state_dict().items())


def test_the_recipe_survives_the_file_and_inspect_shows_it(network, segment, tmp_path):
    camera, frames = segment
    config = AdaptConfig.from_recipe(
        "default", model=network, steps=2, n_windows=2, lr=2e-2, checkpoint_every=0
    )
    out = tmp_path / "cam.safetensors"
    adapter = adapt(network, camera, frames[:6], config, out_path=out, progress=False)
    loaded = Adapter.load(out)
    assert loaded.training_info["recipe"] == adapter.training_info["recipe"]
    assert loaded.training_info["recipe"]["changes"] == {
        "lr": [0.01, 0.02],  # against the DA3 family's step, which the file also records
        "lr_without_teacher": [0.003, None],  # the user's step is the whole fit's
        "n_windows": [30, 2],
        "steps": [300, 2],
    }
    text = describe_file(out)
    assert (
        "recipe 'default' v1 (the backbone family's: lr 0.01, lr_without_teacher 0.003)"
        " (changed: lr 0.01 -> 0.02; lr_without_teacher 0.003 -> None; n_windows 30 -> 2;"
        " steps 300 -> 2)"
    ) in (" ".join(text.split()))


def test_progress_off_a_terminal_is_lines_not_one_long_line(network, segment, capsys, monkeypatch):
    from raytun3r_plugin.adaptation import loop

    camera, frames = segment
    config = AdaptConfig.from_recipe("matches", steps=4, n_windows=2, checkpoint_every=0)
    monkeypatch.setattr(loop._Progress, "every_s", 0.0)
    adapt(network, camera, frames[:6], config, progress=True)
    lines = capsys.readouterr().err.splitlines()
    steps = [line for line in lines if line.startswith("adapt: step")]
    assert len(steps) == 4 and all(len(line) < 120 for line in lines)
    assert not any("\r" in line for line in lines)
    monkeypatch.setattr(loop._Progress, "every_s", 3600.0)
    adapt(network, camera, frames[:6], config, progress=True)
    steps = [line for line in capsys.readouterr().err.splitlines() if "adapt: step" in line]
    assert steps == ["adapt: step 4/4 " + steps[0].split(" 4/4 ")[1]]


def test_check_frame_counts():
    assert check_frame_count(14) == 0 and check_frame_count(15) == 3
    assert check_frame_count(40) == 8
    assert check_frame_count(20, "0") == 0 and check_frame_count(20, 5) == 5
    for frames, asked, message in (
        (20, "x", "'auto' or an integer"),
        (20, 2, "at least 3"),
        (5, 3, "leaves 2 of 5 frames"),
    ):
        with pytest.raises(InputError, match=message):
            check_frame_count(frames, asked)


def test_the_held_out_check_scores_both_adapters_on_the_same_matches(network, segment):
    camera, frames = segment
    config = AdaptConfig(input_size=112)
    zero = Adapter.for_model(network, camera)
    result = held_out_reprojection(network, camera, frames[12:], zero, config)
    assert result["frames"] == 6 and result["windows"] >= 1
    assert result["zero_adapter_px"] == result["adapted_px"] and result["change"] == 0.0
    assert 0 < result["zero_adapter_px"] < 10
    moved = Adapter.for_model(network, camera)
    with torch.no_grad():
        for table in moved.parameters():
            table.normal_(0, 0.5)
    worse = held_out_reprojection(network, camera, frames[12:], moved, config)
    assert worse["zero_adapter_px"] == result["zero_adapter_px"]
    assert worse["adapted_px"] != worse["zero_adapter_px"]
    still = held_out_reprojection(network, camera, frames[12:13].repeat(3, 0), zero, config)
    assert still["adapted_px"] is None and "reason" in still


def test_the_command_line_fits_the_default_recipe_and_reports_the_check(
    segment, short_default, tmp_path, capsys
):
    import cv2

    from raytun3r_plugin import cameras
    from raytun3r_plugin.apps.cli import main

    camera, frames = segment
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, image in enumerate(frames):
        cv2.imwrite(str(folder / f"{k:04d}.png"), (image[..., ::-1] * 255).round().astype("uint8"))
    cameras.save(camera, tmp_path / "camera.json")
    out = tmp_path / "cam.safetensors"
    base = ["adapt", "--backbone", "raytun3r-da3-tiny-v3", "--frames", str(folder)]
    base += ["--camera", str(tmp_path / "camera.json")]
    assert main([*base, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert (
        "fitting with recipe 'default' v1 (the backbone family's: lr 0.01,"
        " lr_without_teacher 0.003); input 112 px"
    ) in captured.err
    assert "the last 3 frames held out" in captured.err
    assert "recipe 'default' v1" in captured.out
    assert "check on the last 3 frames (not fitted): reprojection error" in captured.out
    info = Adapter.load(out).training_info
    assert info["recipe"]["changes"] == {} and info["check"]["frames"] == 3
    assert info["segment"]["n_frames"] == 15  # the held-out frames were not fitted
    assert "check on 3 held-out frames" in describe_file(out)
    # A recipe by name, and what it changes.
    # Another recipe to the same file meets the first run's checkpoint: refused with the way out.
    assert main([*base, "--recipe", "targets", "--steps", "2", "--out", str(out)]) == 2
    assert "--restart" in capsys.readouterr().err
    assert main([*base, "--recipe", "targets", "--steps", "2", "--restart", "--out", str(out)]) == 0
    capsys.readouterr()
    assert Adapter.load(out).training_info["recipe"] == {
        "name": "targets",
        "version": 1,
        "changes": {"steps": [300, 2]},
    }
    for extra, message in (
        (["--recipe", "supervised"], "give --depth"),
        (["--recipe", "nope"], "invalid choice"),
        (["--recipe", "paper", "--teacher-views", "centre"], "add --teacher WEIGHT"),
    ):
        code = None
        try:
            code = main([*base, *extra, "--out", str(tmp_path / "x.safetensors")])
        except SystemExit as stop:  # argparse's own refusal
            code = stop.code
        assert code == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "x.safetensors").exists()


def test_adapt_help_leads_with_the_recipe_and_groups_the_internals(capsys):
    from raytun3r_plugin.apps.cli import main

    with pytest.raises(SystemExit):
        main(["adapt", "--help"])
    text = capsys.readouterr().out
    options = text[text.index("options:") :]
    assert options.index("--recipe") < options.index("--backbone") < options.index("--out")
    advanced = text.index("advanced:")
    assert all(text.index(f"  {flag}") > advanced for flag in ("--pose-weight", "--teacher "))
    assert main(["recipes"]) == 0
    listing = capsys.readouterr().out
    assert all(f"{name} (v" in listing for name in recipe_names())


def test_the_pose_oracle_fits_the_tables_to_the_true_relative_poses(network, segment):
    from raytun3r_plugin.adaptation.problem import prepare_problem, with_pose_targets
    from raytun3r_plugin.poses import relative_pose, rotation_angle

    camera, frames = segment
    seq = synthetic.render_sequence("indoor", camera, n_frames=8, seed=31)
    config = AdaptConfig.from_recipe(
        "pose-oracle", steps=12, n_windows=3, input_size=112, checkpoint_every=0
    )
    problem = with_pose_targets(prepare_problem(camera, seq.images, config), seq.cam_from_world)
    assert problem.supervision == {"kind": "poses", "frames": 8}
    for window, pairs in problem.windows:
        for pair in pairs:
            truth = relative_pose(
                torch.as_tensor(seq.cam_from_world, dtype=torch.float64),
                window.frames[pair.a],
                window.frames[pair.b],
            )
            assert float(rotation_angle(pair.rotation, truth[:3, :3])) < 1e-9
    adapter = adapt(network, camera, seq.images, config, poses=seq.cam_from_world, progress=False)
    info = adapter.training_info
    assert info["supervision"]["kind"] == "poses" and info["recipe"]["name"] == "pose-oracle"
    assert info["config"]["weights"] == {
        "reproj": 0.0,
        "smooth": 0.0,
        "l2": 0.0,
        "tv": 0.0,
        "pose": 1.0,
        "depth": 0.0,
    }
    assert not adapter.is_zero()
    for bad, message in (
        (seq.cam_from_world[:2], "at least"),
        (seq.cam_from_world[..., :3], r"\(N, 4, 4\)"),
    ):
        with pytest.raises(InputError, match=message):
            adapt(network, camera, seq.images, config, poses=bad, progress=False)
    with pytest.raises(InputError, match="depth .* or poses"):
        adapt(network, camera, seq.images, poses=seq.cam_from_world, depth=seq.depth)


def test_refined_intrinsics_keep_the_pose_oracles_true_targets(network, segment, monkeypatch):
    """With ``refine_intrinsics``, the problem is prepared again for the refined camera; the true
    relative poses given to ``adapt`` must be its targets still, not the matches' own."""
    from types import SimpleNamespace

    from raytun3r_plugin.adaptation import intrinsics

    camera, _ = segment
    seq = synthetic.render_sequence("indoor", camera, n_frames=8, seed=31)
    refined = SimpleNamespace(refined=True, to_dict=lambda: {"refined": True})
    monkeypatch.setattr(intrinsics, "refine_intrinsics", lambda cam, _set: (cam, refined))
    config = AdaptConfig.from_recipe(
        "pose-oracle",
        steps=1,
        n_windows=3,
        input_size=112,
        checkpoint_every=0,
        refine_intrinsics=True,
    )
    adapter = adapt(network, camera, seq.images, config, poses=seq.cam_from_world, progress=False)
    assert adapter.training_info["intrinsics"] == {"refined": True}
    assert adapter.training_info["supervision"]["kind"] == "poses"


def test_the_trajectory_recipe_is_the_pose_oracle_on_the_matches_own_targets(network, segment):
    """``trajectory``: the oracle's settings, fitted without ground truth (the MAGSAC++ relative
    poses), so a user can run it on their own footage; it moves the tables through the pose term
    alone."""
    camera, frames = segment
    oracle, trajectory = get_recipe("pose-oracle"), get_recipe("trajectory")
    assert trajectory.changes == oracle.changes
    assert oracle.needs_poses and not trajectory.needs_poses
    config = AdaptConfig.from_recipe(
        "trajectory", steps=12, n_windows=3, input_size=112, checkpoint_every=0
    )
    adapter = adapt(network, camera, frames, config, progress=False)
    info = adapter.training_info
    assert info["recipe"]["name"] == "trajectory" and info["supervision"]["kind"] != "poses"
    assert {k for k, v in info["config"]["weights"].items() if v} == {"pose"}
    assert not adapter.is_zero()


def test_the_check_frames_are_cut_from_the_last_segment_with_their_depth_and_poses():
    import numpy as np

    from raytun3r_plugin.adaptation.check import split_off_check

    frames, depth, poses = np.zeros((20, 8, 8, 3)), np.ones((20, 8, 8)), np.zeros((20, 4, 4))
    fit, fit_depth, fit_poses, check = split_off_check(frames, depth, poses, "auto")
    assert len(fit) == len(fit_depth) == len(fit_poses) == 16 and len(check) == 4
    assert split_off_check(frames, depth, poses, 0)[3] is None
    assert split_off_check(frames[:14], None, None, "auto")[3] is None  # too short for a check
    segments = [
        np.zeros((6, 8, 8, 3)),
        np.arange(20.0)[:, None, None, None] * np.ones((20, 8, 8, 3)),
    ]
    fit, fit_depth, _, check = split_off_check(segments, None, None, 5)
    assert [len(s) for s in fit] == [6, 15] and fit_depth is None
    assert [float(c[0, 0, 0]) for c in check] == [15.0, 16.0, 17.0, 18.0, 19.0]
    with pytest.raises(InputError, match="leaves 2 of 8 frames"):
        split_off_check(frames[:8], None, None, 6)


def test_check_and_keep_settings_are_checked_and_stay_out_of_old_identities():
    assert AdaptConfig(check_frames="4").check_frames == 4
    assert AdaptConfig(check_frames="auto", check_veto=0.02).to_dict()["check_veto"] == 0.02
    assert AdaptConfig().identity() == AdaptConfig(check_frames=0, check_veto=None).identity()
    for field_name, changes in (
        ("check_frames", {"check_frames": 2}),
        ("check_frames", {"check_frames": "some"}),
        ("check_veto", {"check_veto": 0.02}),  # nothing to check it on
        ("check_veto", {"check_frames": "auto", "check_veto": 1.5}),
    ):
        with pytest.raises(InputError, match=f"AdaptConfig.{field_name}"):
            AdaptConfig(**changes)


@pytest.mark.parametrize(
    ("change", "kept"), [(-0.05, True), (0.01, True), (None, True), (0.05, False)]
)
def test_a_fit_that_raises_the_check_by_more_than_the_veto_is_not_kept(
    network, segment, monkeypatch, change, kept
):
    from raytun3r_plugin.adaptation import check as check_module

    camera, frames = segment
    seen: dict = {}

    def scored(model, camera, frames, adapter, config, *, mask=None, reference=None):
        seen["frames"], seen["reference"] = len(frames), reference
        return {"frames": len(frames), "windows": 1, "change": change}

    monkeypatch.setattr(check_module, "held_out_reprojection", scored)
    config = AdaptConfig(
        input_size=112, steps=3, n_windows=3, lr=5e-2, check_frames=3, check_veto=0.02
    )
    start = Adapter.for_model(network, camera)
    with torch.no_grad():
        start.pe["radial"].normal_(0, 0.01)  # not zero: "not kept" goes back to it, not to zero
    adapter = adapt(network, camera, frames, config, adapter=start, progress=False)
    info = adapter.training_info
    assert seen["frames"] == 3 and info["segment"]["n_frames"] == 15
    assert torch.equal(seen["reference"].pe["radial"], start.pe["radial"])
    assert info["check"]["kept"] is kept
    same = all(
        torch.equal(a, b) for a, b in zip(adapter.parameters(), start.parameters(), strict=True)
    )
    assert same is not kept  # the 3-step fit moved the tables; "not kept" restores the start
    assert (info["verdict"]["status"] == "not kept") is not kept
    if not kept:
        assert info["verdict"]["summary"].startswith(
            "NOT KEPT: on the 3 held-out frames the fit raised the reprojection error by +5.0 %"
        )


def test_the_check_is_recorded_and_changes_nothing_without_a_veto(network, segment):
    camera, frames = segment
    config = AdaptConfig(input_size=112, steps=2, n_windows=2, lr=5e-2, check_frames="auto")
    adapter = adapt(network, camera, frames, config, progress=False)
    check = adapter.training_info["check"]
    assert check["frames"] == 3 and "kept" not in check
    assert check["zero_adapter_px"] > 0 and check["adapted_px"] > 0
    assert adapter.training_info["verdict"]["status"] != "not kept"
    assert any(float(table.detach().abs().max()) > 0 for table in adapter.parameters())
