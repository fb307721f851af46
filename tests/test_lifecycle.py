"""Lifecycle of a patched model: garbage collection, ``copy.deepcopy`` and the wrapped methods.

The semantics are accelerate's (``add_hook_to_module``): wrappers look up the original method
and the patch state at call time, so a deep copy of a patched model is a patched copy that runs
its own weights, with its own handle.
"""

from __future__ import annotations

import copy
import gc
import inspect
import weakref

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin import patching
from raytun3r_plugin.errors import NotAppliedError, PatchedCopyError, Raytun3rError
from raytun3r_plugin.patch_wrapper import WRAPPER_MARK
from raytun3r_plugin.registry import resolve_targets, spec_for
from tests.backbones import CASE, CASES, make
from tests.helpers import fisheye, outputs, randomise_


def _make(kind: str):
    """A fresh small model of ``kind`` (a row of tests/backbones.CASES) and its input (height, width)."""
    case = CASE[kind]
    pytest.importorskip(case.package)
    return make(kind), case.size


def _images(size, seed: int = 1) -> torch.Tensor:
    return torch.rand(1, 2, 3, *size, generator=torch.Generator().manual_seed(seed))


def _patch_embed(model) -> torch.nn.Module:
    """The patch embedding of the image path (the first thing every frame meets), from the spec."""
    spec, root = spec_for(model)
    (owner,) = (owner for target, _, owner in resolve_targets(spec, root, {"patch_embed"}))
    return owner


@pytest.fixture(params=[case.family for case in CASES])
def kind(request):
    return request.param


def _is_freed(model_ref: weakref.ref) -> bool:
    gc.collect()
    return model_ref() is None


def test_unpatched_model_is_freed(kind):
    """The control: without a patch the model dies with its last reference."""
    model, _ = _make(kind)
    ref = weakref.ref(model)
    del model
    assert _is_freed(ref)


def test_patched_model_is_freed(kind):
    model, size = _make(kind)
    handle = rt.apply(
        model, fisheye(size[1], size[0]), randomise_(rt.Adapter.for_model(model)), strict=False
    )
    outputs(model, _images(size))  # fill the caches and, for Pi3X, install the uv trampoline
    ref = weakref.ref(model)
    del model
    assert _is_freed(ref)
    assert not handle.is_active  # a handle outliving its model says so ...
    handle.remove()  # ... and removing it is a no-op
    with pytest.raises(NotAppliedError):
        _ = handle.model


def test_patched_model_is_freed_with_its_handle_kept_and_without_remove(kind):
    model, size = _make(kind)
    handle = rt.apply(model, fisheye(size[1], size[0]))
    ref = weakref.ref(model)
    del model
    assert _is_freed(ref)
    assert handle.patched == []  # nothing of the dead model is reachable through the handle


def test_deepcopy_is_a_patched_copy_running_its_own_weights(kind):
    model, size = _make(kind)
    images = _images(size)
    camera = fisheye(size[1], size[0])
    handle = rt.apply(model, camera, randomise_(rt.Adapter.for_model(model)), strict=False)
    source = outputs(model, images)
    twin = copy.deepcopy(model)
    twin_handle = rt.handle_of(twin)
    assert twin_handle is not None and twin_handle is not handle and twin_handle.model is twin
    assert rt.handle_of(model) is handle
    assert twin_handle.patched == handle.patched
    assert torch.equal(outputs(twin, images)["depth"], source["depth"])  # same weights, same patch
    with torch.no_grad():
        for parameter in _patch_embed(twin).parameters():
            parameter.zero_()
    assert not torch.equal(outputs(twin, images)["depth"], source["depth"])
    assert torch.equal(outputs(model, images)["depth"], source["depth"])  # the source is untouched

    # Removing the source leaves the copy patched and working.
    handle.remove()
    assert (
        rt.handle_of(model) is None and rt.handle_of(twin) is twin_handle and twin_handle.is_active
    )
    zeroed_patched = outputs(twin, images)
    with twin_handle.disabled():
        zeroed_plain = outputs(twin, images)
    assert not torch.equal(zeroed_patched["depth"], zeroed_plain["depth"])
    twin_handle.remove()
    assert rt.handle_of(twin) is None
    assert torch.equal(outputs(twin, images)["depth"], zeroed_plain["depth"])


def test_removing_a_deepcopy_restores_it_exactly(kind):
    model, size = _make(kind)
    images = _images(size)
    plain_twin = copy.deepcopy(model)
    rt.apply(
        model, fisheye(size[1], size[0]), randomise_(rt.Adapter.for_model(model)), strict=False
    )
    twin = copy.deepcopy(model)
    rt.remove(twin)
    assert rt.handle_of(twin) is None and rt.handle_of(model) is not None
    assert not any(name in vars(twin) for name in patching.ADDED_ATTRIBUTES)
    for module in twin.modules():
        assert not any(getattr(value, WRAPPER_MARK, False) for value in vars(module).values())
    expected, found = outputs(plain_twin, images), outputs(twin, images)
    for key in expected:
        assert torch.equal(expected[key], found[key]), key
    rt.remove(model)


def test_handle_remove_after_deepcopy_of_the_source(kind):
    model, size = _make(kind)
    images = _images(size)
    reference = outputs(model, images)
    handle = rt.apply(model, fisheye(size[1], size[0]))
    twin = copy.deepcopy(model)
    handle.remove()
    assert rt.handle_of(model) is None and rt.handle_of(twin) is not None
    assert torch.equal(outputs(model, images)["depth"], reference["depth"])
    twin_handle = rt.handle_of(twin)
    del twin
    gc.collect()
    assert not twin_handle.is_active  # the copy is freed like any patched model


def test_wrapped_methods_keep_name_and_signature_while_patched(kind):
    model, size = _make(kind)
    with rt.apply(
        model, fisheye(size[1], size[0]), randomise_(rt.Adapter.for_model(model)), strict=False
    ) as handle:
        assert handle.patched
        for owner, attribute in handle.wrapped():
            wrapped = vars(owner)[attribute]
            upstream = getattr(type(owner), attribute).__get__(owner, type(owner))
            assert getattr(wrapped, WRAPPER_MARK, False), attribute
            assert wrapped.__name__ == upstream.__name__ == attribute
            assert inspect.signature(wrapped) == inspect.signature(upstream), attribute
            assert wrapped.__wrapped__ == upstream


def test_adapter_of_a_copy_is_its_own(kind):
    model, size = _make(kind)
    adapter = randomise_(rt.Adapter.for_model(model))
    handle = rt.apply(model, fisheye(size[1], size[0]), adapter, strict=False)
    twin_handle = rt.handle_of(copy.deepcopy(model))
    assert handle.adapter is adapter and twin_handle.adapter is not adapter
    assert twin_handle.adapter.same_as(adapter)
    handle.remove()


def test_deepcopy_of_a_patched_submodule_is_refused():
    """Copying part of a patched model would leave wrappers that no handle can remove."""
    model, size = _make("da3")
    with rt.apply(model, fisheye(size[1], size[0])):
        with pytest.raises(PatchedCopyError, match="copy the whole model") as error:
            copy.deepcopy(model.backbone)
        assert isinstance(error.value, Raytun3rError)
        assert (
            copy.deepcopy(model.backbone.pretrained.blocks[0]) is not None
        )  # unpatched parts copy freely
