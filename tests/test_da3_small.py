"""The real da3-small config (34M parameters, random weights) at small inputs."""

from __future__ import annotations

import pytest
import torch

import raytun3r_plugin as rt
from tests.helpers import fisheye, max_relative_difference, outputs, pinhole, randomise_

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_network  # noqa: E402

H, W = 98, 126


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    model = build_network("da3-small").eval()
    with torch.no_grad():  # DA3 leaves pos_embed at zero; a released checkpoint does not
        model.backbone.pretrained.pos_embed.normal_(0, 0.02)
    return model


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(0))


def test_pinhole_identity_on_da3_small(net, images):
    reference = outputs(net, images)
    with rt.apply(net, pinhole(W, H, focal=90.0), rt.Adapter.for_model(net)):
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_fisheye_adapter_on_da3_small(net, images):
    reference = outputs(net, images)
    state = {k: v.clone() for k, v in net.state_dict().items()}
    camera = fisheye(W, H, 195.0)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(net, camera, adapter) as handle:
        assert (
            len(handle.patched) == 6
        )  # PE, RoPE positions, reference view, RoPE angles, patches, grid
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) > 1e-3
    assert max_relative_difference(reference, outputs(net, images)) == 0.0
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())
