"""apply()/remove() on the real Depth Anything 3 code (docs/conventions.md section 9, invariants 1-4, 6)."""

from __future__ import annotations

import inspect

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.errors import (
    AdapterError,
    AlreadyAppliedError,
    CameraError,
    InputError,
    NotAppliedError,
    Raytun3rError,
    UnsupportedUpstreamError,
)
from tests.helpers import (
    assert_same_snapshot,
    fail_install_at,
    fisheye,
    max_relative_difference,
    outputs,
    outputs_from_threads,
    pinhole,
    randomise_,
    snapshot,
)

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3 import build_tiny_network  # noqa: E402

H, W = 70, 84


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(1))


@pytest.fixture
def net():
    return build_tiny_network(seed=0)




def test_pinhole_zero_adapter_reproduces_upstream(net, images):
    """Invariant 1: pinhole camera + zero adapter with every correction on = upstream."""
    reference = outputs(net, images)
    adapter = rt.Adapter.for_model(net, pinhole(W, H))
    with rt.apply(net, pinhole(W, H), adapter) as handle:
        assert all(handle.components.values())
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_pinhole_zero_adapter_with_three_views(net):
    """DA3 reorders views for S >= 3; positions must still line up."""
    images = torch.rand(1, 3, 3, H, W, generator=torch.Generator().manual_seed(5))
    reference = outputs(net, images)
    with rt.apply(net, pinhole(W, H), rt.Adapter.for_model(net)):
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_fisheye_and_nonzero_adapter_change_outputs(net, images):
    reference = outputs(net, images)
    camera = fisheye(W, H)
    with rt.apply(net, camera):
        parameter_free = outputs(net, images)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(net, camera, adapter):
        adapted = outputs(net, images)
    assert max_relative_difference(reference, parameter_free) > 1e-3
    assert max_relative_difference(parameter_free, adapted) > 1e-3


@pytest.mark.parametrize("component", ["pe", "rope", "patch_resample", "border_tokens", "grid"])
def test_each_component_has_an_effect(net, images, component):
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(net, camera, adapter, components={component: True} | {c: False for c in rt.adapter.COMPONENTS if c != component}) as handle:
        assert [k for k, v in handle.components.items() if v] == [component]
        one = outputs(net, images)
    assert max_relative_difference(outputs(net, images), one) > 1e-4


def test_gradients_reach_only_adapter_tables(net, images):
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    net.requires_grad_(False)
    with rt.apply(net, camera, adapter):
        prediction = rt.predict(net, images)
        (prediction.depth.mean() + prediction.cam_from_world[..., :3, 3].square().sum()).backward()
    for name, parameter in adapter.named_parameters():
        assert parameter.grad is not None and float(parameter.grad.abs().sum()) > 0, name
    assert all(p.grad is None for p in net.parameters())


def test_remove_restores_everything(net, images):
    """Invariant 2: same outputs, same state_dict, no leftover attributes, same signature."""
    reference = outputs(net, images)
    snap = snapshot(net)
    signature = inspect.signature(net.forward)
    handle = rt.apply(net, fisheye(W, H), randomise_(rt.Adapter.for_model(net)), strict=False)
    assert max_relative_difference(reference, outputs(net, images)) > 1e-4
    # The replaced methods (not net.forward, which is never patched) keep their signatures.
    for owner, attribute in handle.wrapped():
        assert inspect.signature(vars(owner)[attribute]) == inspect.signature(getattr(type(owner), attribute).__get__(owner)), attribute
    handle.remove()
    handle.remove()  # idempotent
    assert_same_snapshot(net, snap)
    assert inspect.signature(net.forward) == signature
    assert max_relative_difference(reference, outputs(net, images)) == 0.0
    assert rt.handle_of(net) is None


def test_remove_without_handle_and_not_applied(net):
    rt.apply(net, fisheye(W, H))
    rt.remove(net)
    assert rt.handle_of(net) is None
    with pytest.raises(NotAppliedError):
        rt.remove(net)


def test_disabled_gives_upstream_behaviour(net, images):
    reference = outputs(net, images)
    with rt.apply(net, fisheye(W, H), randomise_(rt.Adapter.for_model(net))) as handle:
        patched = outputs(net, images)
        with handle.disabled():
            plain = outputs(net, images)
        again = outputs(net, images)
    assert max_relative_difference(reference, plain) == 0.0
    assert max_relative_difference(patched, again) == 0.0


def test_failure_part_way_rolls_back(net, images, monkeypatch):
    """Invariant 3: a failure while installing leaves the model untouched."""
    reference = outputs(net, images)
    snap = snapshot(net)
    calls = fail_install_at(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="injected"):
        rt.apply(net, fisheye(W, H), randomise_(rt.Adapter.for_model(net)))
    assert calls["n"] == 3
    assert_same_snapshot(net, snap)
    assert rt.handle_of(net) is None
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


def test_structural_mismatch_is_reported_before_any_change(net, monkeypatch):
    from depth_anything_3.model.dinov2.vision_transformer import DinoVisionTransformer

    snap = snapshot(net)

    def moved(self, batch, views, height, width, device):  # a renamed upstream signature
        raise AssertionError("never called")

    monkeypatch.setattr(DinoVisionTransformer, "_prepare_rope", moved)
    with pytest.raises(UnsupportedUpstreamError) as error:
        rt.apply(net, fisheye(W, H))
    message = str(error.value)
    assert "expected signature _prepare_rope(B, S, H, W, device)" in message
    assert "found _prepare_rope(batch, views, height, width, device)" in message
    assert_same_snapshot(net, snap)
    assert isinstance(error.value, Raytun3rError)


def test_missing_submodule_is_reported(net, monkeypatch):
    monkeypatch.setattr(net.backbone.pretrained, "patch_embed", torch.nn.Identity())
    with pytest.raises(UnsupportedUpstreamError, match="expected a PatchEmbed at 'backbone.pretrained.patch_embed', found torch.nn.modules.linear.Identity"):
        rt.apply(net, fisheye(W, H))


def test_idempotent_and_already_applied(net):
    camera = fisheye(W, H)
    adapter = rt.Adapter.for_model(net, camera)
    first = rt.apply(net, camera, adapter)
    try:
        assert rt.apply(net, camera, adapter) is first
        with pytest.raises(AlreadyAppliedError):
            rt.apply(net, fisheye(W, H, fov_deg=170.0), adapter, strict=False)
        with pytest.raises(AlreadyAppliedError):
            rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))
    finally:
        first.remove()


def test_two_models_different_cameras_side_by_side(images):
    """Invariant 4 (also from two threads): each patched model equals itself alone."""
    net_a, net_b = build_tiny_network(seed=0), build_tiny_network(seed=0)
    camera_a, camera_b = fisheye(W, H, 190.0), fisheye(W, H, 150.0)
    adapter = randomise_(rt.Adapter.for_model(net_a))
    with rt.apply(net_a, camera_a, adapter, strict=False):
        alone_a = outputs(net_a, images)
    with rt.apply(net_b, camera_b, adapter, strict=False):
        alone_b = outputs(net_b, images)
    assert max_relative_difference(alone_a, alone_b) > 1e-4
    other = build_tiny_network(seed=0)
    plain = outputs(other, images)
    with rt.apply(net_a, camera_a, adapter, strict=False), rt.apply(net_b, camera_b, adapter, strict=False):
        assert max_relative_difference(alone_a, outputs(net_a, images)) == 0.0
        assert max_relative_difference(alone_b, outputs(net_b, images)) == 0.0
        assert max_relative_difference(plain, outputs(other, images)) == 0.0  # untouched instance
        results = outputs_from_threads({"a": net_a, "b": net_b}, images, repeats=3)
    assert max_relative_difference(alone_a, results["a"]) == 0.0
    assert max_relative_difference(alone_b, results["b"]) == 0.0


def test_saved_and_loaded_adapter_is_bit_identical(net, images, tmp_path):
    """Invariant 6."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    path = adapter.save(tmp_path / "cam.safetensors")
    loaded = rt.Adapter.load(path)
    with rt.apply(net, camera, adapter):
        before = outputs(net, images)
    with rt.apply(net, None, loaded):  # the camera comes from the file
        after = outputs(net, images)
    assert max_relative_difference(before, after) == 0.0


def test_camera_follows_input_size(net):
    """A camera for the native 168x140 image is rescaled to a 84x70 input."""
    native, direct = fisheye(2 * W, 2 * H), fisheye(W, H)
    images = torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(3))
    adapter = randomise_(rt.Adapter.for_model(net))
    with rt.apply(net, native, adapter, strict=False):
        from_native = outputs(net, images)
    with rt.apply(net, direct, adapter, strict=False):
        from_direct = outputs(net, images)
    assert max_relative_difference(from_native, from_direct) < 1e-4
    with rt.apply(net, fisheye(W, 2 * H), adapter, strict=False), pytest.raises(InputError, match="aspect"):
        outputs(net, images)


def test_wrong_image_size_is_a_clear_error(net):
    with rt.apply(net, fisheye(W, H)), pytest.raises(InputError, match="multiple of the patch size 14"):
        rt.predict(net, torch.rand(1, 2, 3, H + 3, W))


def test_bad_mask_is_refused_before_the_model_is_touched(net, images):
    camera = fisheye(W, H)
    before = snapshot(net)
    with pytest.raises(CameraError, match="aspect ratios differ"):
        rt.apply(net, camera, mask=torch.ones(H, H, dtype=torch.bool))
    with pytest.raises(CameraError, match="no pixel inside"):
        rt.apply(net, camera, mask=torch.zeros(H, W, dtype=torch.bool))
    with pytest.raises(CameraError, match=r"must be \(H, W\)"):
        rt.apply(net, camera, mask=torch.ones(2, H, W, dtype=torch.bool))
    assert rt.handle_of(net) is None
    assert_same_snapshot(net, before)
    # The same mask at twice the size is accepted (resized with the camera) and acts alike.
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[H // 2 :] = False
    with rt.apply(net, camera, mask=mask):
        at_size = outputs(net, images)
    with rt.apply(net, camera, mask=mask.repeat_interleave(2, 0).repeat_interleave(2, 1)):
        doubled = outputs(net, images)
    with rt.apply(net, camera):
        unmasked = outputs(net, images)
    assert max_relative_difference(at_size, doubled) == 0.0 and max_relative_difference(at_size, unmasked) > 1e-3


def test_adapter_for_other_backbone_or_weights_is_refused(net):
    camera = fisheye(W, H)
    adapter = rt.Adapter.for_model(net, camera)
    other_weights = build_tiny_network(seed=1)
    with pytest.raises(AdapterError, match="fitted on other weights"):
        rt.apply(other_weights, camera, adapter)
    rt.apply(other_weights, camera, adapter, strict=False).remove()  # explicit override
    bigger = build_tiny_network(embed_dim=96, num_heads=2, seed=0)
    with pytest.raises(AdapterError, match="made for backbone"):
        rt.apply(bigger, camera, adapter)
    with pytest.raises(AdapterError, match="fitted on KannalaBrandt4"):
        rt.apply(net, pinhole(W, H), adapter)


def test_other_model_instances_are_untouched(images):
    patched, bystander = build_tiny_network(seed=0), build_tiny_network(seed=0)
    reference = outputs(bystander, images)
    with rt.apply(patched, fisheye(W, H), randomise_(rt.Adapter.for_model(patched))):
        assert max_relative_difference(reference, outputs(bystander, images)) == 0.0
        assert "interpolate_pos_encoding" not in vars(bystander.backbone.pretrained)


def test_da3_wrapper_is_unwrapped_to_its_network(net, images):
    """The ``depth_anything_3.api.DepthAnything3`` wrapper keeps the network at ``.model``."""
    wrapper_class = type("DepthAnything3", (torch.nn.Module,), {"__module__": "depth_anything_3.api"})
    wrapper = wrapper_class()
    wrapper.model = net
    reference = outputs(net, images)
    with rt.apply(wrapper, fisheye(W, H), randomise_(rt.Adapter.for_model(wrapper))) as handle:
        assert handle.root is net and rt.handle_of(wrapper) is handle
        assert max_relative_difference(reference, outputs(net, images)) > 1e-4
        with pytest.raises(AlreadyAppliedError):  # the inner network is already wrapped
            rt.apply(net, fisheye(W, H))
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


def test_real_da3_wrapper_when_it_imports():
    api = pytest.importorskip("depth_anything_3.api", reason="depth_anything_3.api needs moviepy, not installed here", exc_type=ImportError)
    wrapper = api.DepthAnything3(model_name="da3-small")
    with rt.apply(wrapper, fisheye(W, H)) as handle:
        assert handle.root is wrapper.model
