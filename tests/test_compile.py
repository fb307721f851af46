"""``torch.compile`` of a patched model (docs/deployment.md, "Compiling a patched model").

The default suite compiles one backbone (VGGT-Omega's stub, the quickest to trace) through the
whole lifecycle; the contract matrix runs the same check on every backbone, and on every
component set, under ``-m slow`` (tests/test_backbone_contract.py). Slow too (each compile
traces the model again, 20-50 s on a loaded 2-core machine): a new input size, apply() to a
compiled module, and one inductor compile of the tiny DA3 network (a C++ build).
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

import raytun3r_plugin as rt
from raytun3r_plugin.patch_wrapper import PatchWrapper
from raytun3r_plugin.registry import PatchTarget
from tests.backbones import CASE, make
from tests.compile_checks import check_compiled_lifecycle, counter
from tests.helpers import fisheye, max_relative_difference, outputs, randomise_


@pytest.fixture(autouse=True)
def _fresh_dynamo():
    """No compiled code left for the next test."""
    yield
    torch._dynamo.reset()


class _Doubler(nn.Module):
    def scale(self, x):
        return x * 2

    def forward(self, x):
        return self.scale(x) + 1


def _breaking(owner, state):
    """A behaviour with a graph break between its own code and upstream's method."""

    def scale(original, x):
        x = x + 10
        torch._dynamo.graph_break()
        return original(x)

    return scale


def test_a_graph_break_inside_a_wrapper_does_not_recurse():
    """The cause of the RecursionError: after a graph break torch.compile rebuilt the bound
    upstream method as ``owner.scale``, i.e. the wrapper itself. The wrapper now passes the
    class method as a partial, which compiles and runs once."""
    model = _Doubler()
    target = PatchTarget(
        name="scale",
        hook="pe",
        owners=("",),
        attribute="scale",
        signature=("x",),
        owner_classes=("_Doubler",),
        build=_breaking,
    )
    wrapper = PatchWrapper(model, target, state=None)
    object.__setattr__(model, "scale", wrapper)
    count = counter("eager")
    x = torch.arange(3.0)
    result = torch.compile(model, backend=count)(x)
    assert torch.equal(result, (x + 10) * 2 + 1)
    assert count.frame_count >= 2  # the break split the forward


def test_compiled_patched_model_lifecycle():
    counts = check_compiled_lifecycle("vggt_omega", "eager")
    assert counts["new_camera"] <= counts["first"]


@pytest.mark.slow
def test_compiled_model_recompiles_once_for_a_new_input_size():
    case = CASE["vggt_omega"]
    net = make("vggt_omega")
    height, width = case.size
    camera = fisheye(width, height)
    rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))
    count = counter("eager")
    compiled = torch.compile(net, backend=count)
    outputs(compiled, case.images())
    first = count.frame_count
    larger = torch.rand(1, 2, 3, 2 * height, 2 * width, generator=torch.Generator().manual_seed(4))
    expected = outputs(net, larger)  # the camera follows the input size
    assert max_relative_difference(expected, outputs(compiled, larger)) == 0.0
    grown = count.frame_count - first
    assert 0 < grown <= first
    assert max_relative_difference(expected, outputs(compiled, larger)) == 0.0
    assert count.frame_count == first + grown


@pytest.mark.slow
def test_apply_to_a_compiled_module_patches_the_network_inside():
    case = CASE["vggt_omega"]
    net = make("vggt_omega")
    images = case.images()
    compiled = torch.compile(net, backend=counter("eager"))
    height, width = case.size
    camera = fisheye(width, height)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(compiled, camera, adapter) as handle:
        assert rt.handle_of(compiled) is handle
        patched = outputs(compiled, images)
    with rt.apply(net, camera, adapter):
        assert max_relative_difference(patched, outputs(net, images)) == 0.0


@pytest.mark.slow
def test_inductor_compile_of_the_patched_tiny_da3():
    """One real code-generating compile (C++ on CPU): within float tolerance of eager."""
    pytest.importorskip("depth_anything_3")
    check_compiled_lifecycle("da3", "inductor")


@pytest.mark.slow
def test_compiled_nested_da3_matches_eager_without_recompiles():
    """The nested model (two DA3 networks, one apply) compiles like a single one.

    Upstream's nested model fills its own position and RoPE caches during its first call, so
    even unpatched it recompiles once on the second call (measured: 3 graphs unpatched, 1
    patched); from then on nothing compiles again."""
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_tiny_nested_network

    net = build_tiny_nested_network()
    images = torch.rand(1, 2, 3, 70, 84, generator=torch.Generator().manual_seed(2))
    camera = fisheye(84, 70)
    handle = rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))
    patched = outputs(net, images)
    count = counter("eager")
    compiled = torch.compile(net, backend=count)
    for _ in range(2):
        assert max_relative_difference(patched, outputs(compiled, images)) == 0.0
    warm = count.frame_count
    for _ in range(2):
        assert max_relative_difference(patched, outputs(compiled, images)) == 0.0
    assert count.frame_count == warm
    handle.remove()
    plain = outputs(net, images)
    assert max_relative_difference(plain, outputs(compiled, images)) == 0.0
