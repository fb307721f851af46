"""Large official configs (random weights): excluded by default, run with ``pytest -m slow``."""

from __future__ import annotations

import pytest
import torch

import raytun3r_plugin as rt
from tests.helpers import fisheye, max_relative_difference, outputs, pinhole, randomise_

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_network  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", ["da3-base", "da3-large"])
def test_invariants_on_large_configs(name):
    torch.manual_seed(0)
    net = build_network(name).eval()
    with torch.no_grad():
        net.backbone.pretrained.pos_embed.normal_(0, 0.02)
    images = torch.rand(1, 3, 3, 280, 280, generator=torch.Generator().manual_seed(0))
    reference = outputs(net, images)
    with rt.apply(net, pinhole(280, 280, focal=200.0), rt.Adapter.for_model(net)):
        assert max_relative_difference(reference, outputs(net, images)) < 1e-5
    camera = fisheye(280, 280, 195.0)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    assert adapter.num_parameters()["pe"] == 28 * net.backbone.pretrained.embed_dim
    with rt.apply(net, camera, adapter):
        assert max_relative_difference(reference, outputs(net, images)) > 1e-3
    assert max_relative_difference(reference, outputs(net, images)) == 0.0
