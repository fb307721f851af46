"""LoRA baseline: the paper's parameter count, identity at initialisation, exact removal, the
gradient reaching only its own factors, and PEFT's file layout."""

from __future__ import annotations

import copy
import gc
import importlib.util
import json
import weakref

import pytest
import torch

pytest.importorskip("depth_anything_3")

from raytun3r_plugin.patches.da3_networks import build_network, build_tiny_network  # noqa: E402

import raytun3r_plugin as rt  # noqa: E402
from raytun3r_plugin.baselines import LoraWeights, inject_lora, lora_targets  # noqa: E402
from raytun3r_plugin.errors import AdapterError, AlreadyAppliedError  # noqa: E402
from tests.helpers import fisheye  # noqa: E402


@pytest.fixture
def net():
    return build_tiny_network(seed=0)


def _depth(model, images):
    with torch.no_grad():
        return rt.predict(model, images).depth


def _randomise(weights, seed=1):
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for b in weights.lora_B:
            b.copy_(torch.randn(b.shape, generator=generator) * 0.05)


def test_da3_small_has_the_papers_parameter_count():
    model = build_network("da3-small")
    targets = lora_targets(model)
    assert len(targets) == 12 and all(t.startswith("backbone.pretrained.blocks.") for t in targets)
    with inject_lora(model) as handle:
        assert handle.weights.num_parameters() == 147_456


def test_identity_at_initialisation_and_exact_removal(net):
    images = torch.rand(2, 3, 56, 56)
    before_state = {k: v.clone() for k, v in net.state_dict().items()}
    reference = _depth(net, images)
    handle = inject_lora(net)
    assert torch.equal(_depth(net, images), reference), "B = 0: a fresh LoRA changes nothing"
    _randomise(handle.weights)
    changed = _depth(net, images)
    assert not torch.allclose(changed, reference)
    with handle.disabled():
        assert torch.equal(_depth(net, images), reference)
    assert set(net.state_dict()) == set(before_state), "no module or parameter was replaced"
    handle.remove()
    handle.remove()  # idempotent
    assert torch.equal(_depth(net, images), reference)
    assert all(torch.equal(before_state[k], v) for k, v in net.state_dict().items())
    with inject_lora(net):  # the model can take a LoRA again
        pass


def test_a_second_lora_is_refused_and_works_with_apply(net):
    images = torch.rand(2, 3, 56, 56)
    with inject_lora(net) as handle:
        with pytest.raises(AlreadyAppliedError):
            inject_lora(net)
        _randomise(handle.weights)
        with rt.apply(net, fisheye(56, 56)):
            assert bool(torch.isfinite(_depth(net, images)).all())


def test_the_gradient_reaches_only_the_lora_factors(net):
    with inject_lora(net) as handle:
        _randomise(handle.weights)
        for parameter in net.parameters():
            parameter.requires_grad_(False)
        depth = rt.predict(net, torch.rand(2, 3, 56, 56)).depth
        depth.mean().backward()
        assert all(
            p.grad is not None and bool(p.grad.abs().sum() > 0) for p in handle.weights.lora_A
        )
        assert all(p.grad is None for p in net.parameters())


def test_save_writes_peft_layout_and_load_gives_the_same_outputs(net, tmp_path):
    images = torch.rand(2, 3, 56, 56)
    with inject_lora(net) as handle:
        _randomise(handle.weights)
        handle.weights.camera = fisheye(56, 56)
        expected = _depth(net, images)
        folder = handle.weights.save(tmp_path / "lora")
    config = json.loads((folder / "adapter_config.json").read_text())
    assert config["peft_type"] == "LORA" and config["r"] == 8 and config["lora_alpha"] == 16.0
    assert config["target_modules"] == sorted(lora_targets(net))
    from safetensors.torch import load_file

    keys = set(load_file(str(folder / "adapter_model.safetensors")))
    assert "base_model.model.backbone.pretrained.blocks.0.attn.qkv.lora_A.weight" in keys
    assert len(keys) == 2 * len(lora_targets(net))
    loaded = LoraWeights.load(folder)
    assert loaded.camera == fisheye(56, 56)
    with inject_lora(net, loaded):
        assert torch.equal(_depth(net, images), expected)


def test_weights_for_other_layers_are_refused(net):
    other = build_tiny_network(seed=0, embed_dim=32)
    with inject_lora(other) as handle:
        weights = handle.weights
    with pytest.raises(AdapterError, match="other layers or sizes"):
        inject_lora(net, weights)


def test_a_dropped_model_is_not_kept_alive_and_a_copy_carries_no_lora(net):
    images = torch.rand(1, 3, 56, 56)
    reference = _depth(net, images)
    handle = inject_lora(net)
    _randomise(handle.weights)
    twin = copy.deepcopy(net)
    assert torch.equal(_depth(twin, images), reference), "the copy runs without the LoRA"
    assert not torch.equal(_depth(net, images), reference)
    handle.remove()
    model = build_tiny_network(seed=0)
    inject_lora(model)
    ref = weakref.ref(model)
    del model
    gc.collect()
    assert ref() is None


@pytest.mark.skipif(importlib.util.find_spec("peft") is None, reason="peft is not installed")
def test_peft_gives_identical_outputs(net, tmp_path):
    from peft import LoraConfig, inject_adapter_in_model, set_peft_model_state_dict

    images = torch.rand(2, 3, 56, 56)
    with inject_lora(net) as handle:
        _randomise(handle.weights)
        ours = _depth(net, images)
        state = handle.weights.peft_state_dict()
        targets = lora_targets(net)
    twin = build_tiny_network(seed=0)
    config = LoraConfig(r=8, lora_alpha=16, target_modules=targets, lora_dropout=0.0)
    twin = inject_adapter_in_model(config, twin)
    set_peft_model_state_dict(
        twin, {k.removeprefix("base_model.model."): v for k, v in state.items()}
    )
    assert torch.allclose(_depth(twin.eval(), images), ours, atol=1e-5)


def test_adapt_fits_the_lora_factors_with_the_same_objective(net, tmp_path):
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.train import adapt
    from tests.test_losses import room_sequence

    camera = fisheye(84, 70, 190.0)
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    config = AdaptConfig.from_recipe(
        "matches",
        steps=3,
        input_size=84,
        n_windows=3,
        cache_dir=str(tmp_path / "cache"),
        matcher_options={"border_px": 2},
        seed=0,
        components=[],
        lr=1e-2,
    )
    with inject_lora(net) as handle:
        adapter = adapt(
            net,
            camera,
            images,
            config,
            tune=handle.weights,
            out_path=tmp_path / "lora.safetensors",
            progress=False,
        )
        moved = max(float(b.detach().abs().max()) for b in handle.weights.lora_B)
    assert moved > 0, "the LoRA factors were fitted"
    assert adapter.is_zero(), "the adapter's tables stay at zero"
    assert adapter.training_info["tuned"] == {
        "module": "LoraWeights",
        "parameters": handle.weights.num_parameters(),
    }
    assert adapter.training_info["verdict"]["status"] in ("ok", "diverged")
    assert not (tmp_path / "lora.safetensors").exists(), "the caller saves the LoRA, not adapt"
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())


@pytest.mark.parametrize("family", ["da3", "vggt", "pi3", "pi3x", "vggt_omega"])
def test_lora_contract_on_every_backbone_that_declares_its_blocks(family):
    import importlib.util

    from tests.backbones import CASE, make

    case = CASE[family]
    if importlib.util.find_spec(case.package) is None:
        pytest.skip(f"{case.package} is not importable")
    model = make(family)
    images = case.images()
    reference = _depth(model, images)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    handle = inject_lora(model)
    assert len(handle.weights.paths) >= 2
    assert torch.equal(_depth(model, images), reference)
    _randomise(handle.weights)
    assert not torch.allclose(_depth(model, images), reference)
    handle.remove()
    assert torch.equal(_depth(model, images), reference)
    assert all(torch.equal(state[k], v) for k, v in model.state_dict().items())


def test_tune_mode_has_the_collapse_guard(net, tmp_path, monkeypatch):
    """A LoRA fit whose depth the guard judges collapsed gets its starting factors back."""
    from raytun3r_plugin.adaptation import AdaptConfig, adapt, train
    from tests.test_losses import room_sequence

    monkeypatch.setattr(train, "GUARD_MIN_CORRELATION", 1.01)  # no fit can pass: it must trip
    camera = fisheye(84, 70, 190.0)
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    config = AdaptConfig.from_recipe(
        "matches",
        steps=6,
        guard_every=3,
        input_size=84,
        n_windows=3,
        cache_dir=str(tmp_path / "cache"),
        matcher_options={"border_px": 2},
        components=[],
        lr=1e-2,
        min_parallax_px=0.0,
    )
    with inject_lora(net) as handle:
        adapter = adapt(net, camera, images, config, tune=handle.weights, progress=False)
        factors = [float(b.detach().abs().max()) for b in handle.weights.lora_B]
    guard = adapter.training_info["guard"]
    assert guard["tripped"]["step"] == 3 and guard["tripped"]["restored_step"] == 0
    assert adapter.training_info["steps"] == 3
    assert max(factors) == 0.0  # LoRA's B factors start at zero: restored
    assert adapter.training_info["verdict"]["status"] == "collapsed"
