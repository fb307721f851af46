"""The pose gate (``AdaptConfig.pose_gate``): a pose head that does not turn loses the pose term.

Measured on the built-in networks, whose heads differ: v2 answers "no rotation" whatever the
input, v3's head turns with the scene (docs/decisions.md, "The pose gate, second form").
"""

from __future__ import annotations

import copy
import math

import pytest

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.pose_gate import gate_pose_term, pose_agreement
from raytun3r_plugin.adaptation.problem import prepare_problem
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.adapter_report import describe_file
from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.weights import load_backbone

GATE = 0.15


@pytest.fixture(scope="module")
def camera():
    return make_camera(CAMERAS[1], 112)  # KB4 185


@pytest.fixture(scope="module")
def frames(camera):
    # A development seed (the benchmark's held-out seeds are 90000+).
    return synthetic.render_sequence("indoor", camera, n_frames=9, seed=80_010).images


@pytest.fixture(scope="module")
def networks():
    return {name: load_backbone(name) for name in ("raytun3r-da3-tiny", "raytun3r-da3-tiny-v3")}


def settings(tmp_path, **changes) -> AdaptConfig:
    base = dict(input_size=112, n_windows=3, steps=2, checkpoint_every=0, cache_dir=str(tmp_path))
    return AdaptConfig(**{**base, **changes})


@pytest.fixture(scope="module")
def problem(camera, frames, tmp_path_factory):
    return prepare_problem(camera, frames, settings(tmp_path_factory.mktemp("cache")))


def test_responsiveness_separates_a_head_that_does_not_turn(networks, problem, tmp_path):
    config = settings(tmp_path)
    measured = {}
    for name, model in networks.items():
        record = pose_agreement(model, Adapter.for_model(model), problem, config)
        assert record["pairs"] > 0
        # The ratio is the network's own median angle over the targets'.
        expected = record["network_rotation_deg"] / record["no_rotation_deg"]
        assert record["responsiveness"] == pytest.approx(expected, rel=1e-3)
        measured[name] = record["responsiveness"]
    assert measured["raytun3r-da3-tiny"] < GATE < measured["raytun3r-da3-tiny-v3"]


def test_the_gate_switches_a_still_head_to_the_targets_and_the_adapter_says_so(
    networks, camera, frames, tmp_path
):
    still = adapt(
        networks["raytun3r-da3-tiny"],
        camera,
        frames,
        settings(tmp_path, pose_gate=GATE),
        progress=False,
    )
    info = still.training_info
    assert info["pose_gate"]["pose_term"] is False
    assert info["pose_gate"]["threshold"] == GATE
    assert info["config"]["pose_source"] == "targets"
    # The recipe record lists what the user asked for, not the gate's switch.
    assert "pose_source" not in info["recipe"]["changes"]
    still.save(tmp_path / "still.safetensors")
    summary = describe_file(tmp_path / "still.safetensors")
    assert "pose gate: responsiveness" in summary and "pose term dropped" in summary

    turning = adapt(
        networks["raytun3r-da3-tiny-v3"],
        camera,
        frames,
        settings(tmp_path, pose_gate=GATE),
        progress=False,
    )
    assert turning.training_info["pose_gate"]["pose_term"] is True
    assert turning.training_info["config"]["pose_source"] == "hybrid"


def test_the_gate_applies_only_to_a_fit_with_a_pose_term(networks, problem, tmp_path):
    model = networks["raytun3r-da3-tiny"]
    zero = Adapter.for_model(model)
    for config in (
        settings(tmp_path),  # no gate
        settings(tmp_path, pose_gate=GATE, pose_source="targets"),
        settings(tmp_path, pose_gate=GATE, weights={"pose": 0.0}),
    ):
        kept, record = gate_pose_term(model, zero, problem, config)
        assert record is None and kept is config
    # Without a pair to measure on, the measurement is NaN and the pose term stays.
    empty = copy.copy(problem)
    empty.windows = []
    kept, record = gate_pose_term(model, zero, empty, settings(tmp_path, pose_gate=GATE))
    assert math.isnan(record["responsiveness"]) and record["pose_term"] is True
    assert kept.pose_source == "hybrid"


def test_a_negative_gate_is_refused():
    with pytest.raises(InputError, match="pose_gate"):
        AdaptConfig(pose_gate=-0.1)


def test_the_gate_leaves_the_identity_of_settings_without_it_unchanged():
    assert "pose_gate" not in AdaptConfig().to_dict()
    assert AdaptConfig(pose_gate=GATE).to_dict()["pose_gate"] == GATE


def test_a_rig_fit_refuses_the_gate_before_any_work():
    from raytun3r_plugin.adaptation.rig import adapt_rig

    model = load_backbone("raytun3r-da3-tiny")
    config = AdaptConfig.from_recipe("rig", pose_gate=GATE)
    with pytest.raises(InputError, match="no pose gate"):
        adapt_rig(model, None, config, progress=False)
