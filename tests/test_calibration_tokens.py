"""Calibration-token baseline: parameter count, the tokens reach the output, disabled() and
remove() give the vanilla model bit for bit, gradients reach only the tokens, adapt fits them."""

from __future__ import annotations

import copy

import pytest
import torch

pytest.importorskip("depth_anything_3")

from raytun3r_plugin.patches.da3 import build_network, build_tiny_network  # noqa: E402

import raytun3r_plugin as rt  # noqa: E402
from raytun3r_plugin.baselines import CalibrationTokens, inject_calibration_tokens  # noqa: E402
from raytun3r_plugin.errors import AdapterError, AlreadyAppliedError  # noqa: E402
from tests.helpers import fisheye  # noqa: E402


@pytest.fixture
def net():
    return build_tiny_network(seed=0)


def _depth(model, images):
    with torch.no_grad():
        return rt.predict(model, images).depth


def test_da3_small_has_the_papers_parameter_count():
    with inject_calibration_tokens(build_network("da3-small")) as handle:
        assert handle.tokens.num_parameters() == 12 * 4 * 384 == 18_432


def test_tokens_change_the_output_and_removal_is_exact(net):
    images = torch.rand(3, 3, 56, 56)  # 3 views: DA3's reference-view reordering runs too
    state = {k: v.clone() for k, v in net.state_dict().items()}
    reference = _depth(net, images)
    handle = inject_calibration_tokens(net)
    changed = _depth(net, images)
    assert changed.shape == reference.shape
    assert not torch.allclose(changed, reference), "the tokens take part in attention"
    with handle.disabled():
        assert torch.equal(_depth(net, images), reference)
    with pytest.raises(AlreadyAppliedError):
        inject_calibration_tokens(net)
    handle.remove()
    handle.remove()
    assert torch.equal(_depth(net, images), reference)
    assert "process_attention" not in vars(net.backbone.pretrained)
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())


def test_tokens_work_with_apply_and_a_copy_runs_without_them(net):
    images = torch.rand(2, 3, 56, 56)
    reference = _depth(net, images)
    with inject_calibration_tokens(net):
        twin = copy.deepcopy(net)
        assert torch.equal(_depth(twin, images), reference)
        with rt.apply(net, fisheye(56, 56)):
            assert bool(torch.isfinite(_depth(net, images)).all())


def test_the_gradient_reaches_only_the_tokens(net):
    for parameter in net.parameters():
        parameter.requires_grad_(False)
    with inject_calibration_tokens(net) as handle:
        rt.predict(net, torch.rand(2, 3, 56, 56)).depth.mean().backward()
        grad = handle.tokens.tokens.grad
        assert grad is not None and bool((grad.abs().sum(dim=(1, 2)) > 0).all()), "every block"
    assert all(p.grad is None for p in net.parameters())


def test_save_and_load_round_trip_and_refuse_other_sizes(net, tmp_path):
    images = torch.rand(2, 3, 56, 56)
    with inject_calibration_tokens(net) as handle:
        handle.tokens.camera = fisheye(56, 56)
        expected = _depth(net, images)
        path = handle.tokens.save(tmp_path / "tokens.safetensors")
    loaded = CalibrationTokens.load(path)
    assert loaded.camera == fisheye(56, 56)
    with inject_calibration_tokens(net, loaded):
        assert torch.equal(_depth(net, images), expected)
    with pytest.raises(AdapterError, match="do not fit"):
        inject_calibration_tokens(net, CalibrationTokens(3, 4, 64))
    path.write_bytes(path.read_bytes()[:-8])
    with pytest.raises(AdapterError):
        CalibrationTokens.load(path)


def test_adapt_fits_the_tokens(net, tmp_path):
    from raytun3r_plugin.adaptation.train import AdaptConfig, adapt
    from tests.test_losses import room_sequence

    camera = fisheye(84, 70, 190.0)
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    config = AdaptConfig(
        steps=3,
        input_size=84,
        n_windows=3,
        cache_dir=str(tmp_path / "cache"),
        matcher_options={"border_px": 2},
        seed=0,
        components=[],
        lr=1e-2,
    )
    with inject_calibration_tokens(net) as handle:
        start = handle.tokens.tokens.detach().clone()
        adapter = adapt(net, camera, images, config, tune=handle.tokens, progress=False)
        assert not torch.equal(handle.tokens.tokens.detach(), start)
    assert adapter.is_zero()
    assert adapter.training_info["tuned"]["module"] == "CalibrationTokens"
