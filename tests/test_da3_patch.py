"""Depth Anything 3 specifics on the real ``depth_anything_3`` code: view reordering, the
``DepthAnything3`` wrapper, masks and adapter refusals.

The contract every backbone meets (docs/conventions.md section 9, invariants 1-4 and 6) is
``tests/test_backbone_contract.py``.
"""

from __future__ import annotations

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.errors import (
    AdapterError,
    AlreadyAppliedError,
    CameraError,
)
from tests.backbones import make
from tests.helpers import (
    assert_same_snapshot,
    fisheye,
    max_relative_difference,
    outputs,
    pinhole,
    randomise_,
    snapshot,
)

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_tiny_network  # noqa: E402

H, W = 70, 84


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(1))


@pytest.fixture
def net():
    return make("da3")


def test_pinhole_zero_adapter_with_three_views(net):
    """DA3 reorders views for S >= 3; positions must still line up."""
    images = torch.rand(1, 3, 3, H, W, generator=torch.Generator().manual_seed(5))
    reference = outputs(net, images)
    with rt.apply(net, pinhole(W, H), rt.Adapter.for_model(net)):
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


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
    assert (
        max_relative_difference(at_size, doubled) == 0.0
        and max_relative_difference(at_size, unmasked) > 1e-3
    )


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


def test_da3_wrapper_is_unwrapped_to_its_network(net, images):
    """The ``depth_anything_3.api.DepthAnything3`` wrapper keeps the network at ``.model``."""
    wrapper_class = type(
        "DepthAnything3", (torch.nn.Module,), {"__module__": "depth_anything_3.api"}
    )
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
    api = pytest.importorskip(
        "depth_anything_3.api",
        reason="depth_anything_3.api needs moviepy, not installed here",
        exc_type=ImportError,
    )
    wrapper = api.DepthAnything3(model_name="da3-small")
    with rt.apply(wrapper, fisheye(W, H)) as handle:
        assert handle.root is wrapper.model
