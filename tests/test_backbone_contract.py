"""The backbone contract, run on every row of ``tests/backbones.CASES`` (docs/conventions.md
section 9, invariants 1-4 and 6; PEFT's ``TEST_CASES x PeftCommonTester``).

Each test is written once and parametrised over the table of tiny builders (DA3's real tiny
network, the VGGT / Pi3 / Pi3X stubs or tiny real networks), so a backbone added later runs all
of them by adding one row; :func:`test_every_registered_backbone_has_a_case` fails until it
does. Backbone-specific checks stay in ``test_da3_patch.py`` and ``test_vggt_pi3_patch.py``.
"""

from __future__ import annotations

import copy
import dataclasses
import gc
import importlib.util
import re
import sys

import pytest
import torch
from torch import nn

import raytun3r_plugin as rt
from raytun3r_plugin import registry
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.errors import (
    AlreadyAppliedError,
    BackboneRegistrationError,
    DuplicateBackboneError,
    InputError,
    NotAppliedError,
    Raytun3rError,
    UnsupportedUpstreamError,
)
from raytun3r_plugin.registry import HOOK_KINDS, resolve_path, resolve_targets, spec_for
from tests.backbones import CASES, make
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


@pytest.fixture(scope="module", autouse=True)
def _upstream_globals():
    """The upstream module globals at the start, with every importable model built once; no
    test of this module may leave one changed (the Pi3X uv trampoline is the one global patch)."""
    start = {}
    for case in CASES:
        if importlib.util.find_spec(case.package) is not None:
            make(case.family)
            start[case.package] = _module_globals(case.package)
    yield start
    for package, before in start.items():
        _assert_same_globals(package, before)


@pytest.fixture(params=CASES, ids=lambda case: case.family)
def case(request):
    pytest.importorskip(request.param.package)
    return request.param


@pytest.fixture
def net(case):
    return make(case.family)


@pytest.fixture
def images(case):
    return case.images()


@pytest.fixture
def reference(net, images):
    """Unpatched outputs of ``net`` itself (exact comparisons stay within one instance: CPU
    kernels may round differently for weights at other addresses)."""
    return outputs(net, images)


def _cameras(case):
    height, width = case.size
    return pinhole(width, height), fisheye(width, height)


def _rope_instances(net) -> list[nn.Module]:
    spec, _ = spec_for(net)
    return [
        module
        for module in net.modules()
        if set(registry._class_names(module)) & set(spec.rope_classes)
    ]


def _deep_snapshot(net) -> dict:
    """Every instance attribute of every module, by identity (``helpers.snapshot`` has the names)."""
    return {
        (name, key): value
        for name, module in net.named_modules()
        for key, value in vars(module).items()
    }


def _assert_same_objects(net, before: dict) -> None:
    after = _deep_snapshot(net)
    assert after.keys() == before.keys()
    changed = [key for key, value in before.items() if after[key] is not value]
    assert not changed, f"attributes replaced and not restored: {changed}"


def _module_globals(package: str) -> dict:
    return {
        (name, key): value
        for name, module in list(sys.modules.items())
        if module is not None and (name == package or name.startswith(package + "."))
        for key, value in vars(module).items()
        if not key.startswith("__")
    }


def _assert_same_globals(package: str, before: dict) -> None:
    def changed() -> list:
        after = _module_globals(package)
        return [key for key, value in before.items() if after.get(key) is not value]

    if changed():
        gc.collect()  # a global trampoline (Pi3X uv) goes with the last wrapper using it; only slow if needed
    assert not changed(), f"upstream module globals changed: {changed()}"


# ---------------------------------------------------------------------------------------------
# The table and the registry
# ---------------------------------------------------------------------------------------------


def test_every_registered_backbone_has_a_case():
    """A backbone registered without a row in tests/backbones.CASES would skip every contract."""
    registered = set(registry.specs())
    rows = [case.family for case in CASES]
    assert len(rows) == len(set(rows)), f"duplicate rows: {rows}"
    assert not registered - set(rows), (
        f"registered backbones without a row in tests/backbones.CASES: {sorted(registered - set(rows))}"
    )
    assert not set(rows) - registered, (
        f"rows for backbones that are not registered: {sorted(set(rows) - registered)}"
    )


def test_register_refuses_duplicates_and_inconsistent_specs(monkeypatch):
    monkeypatch.setattr(registry, "_SPECS", dict(registry.specs()))  # register into a copy
    da3 = registry.specs()["da3"]
    assert registry.register(da3) is da3  # the same object again: a no-op
    with pytest.raises(
        DuplicateBackboneError, match="family 'da3' is already registered.*overwrite=True"
    ) as error:
        registry.register(dataclasses.replace(da3))
    assert isinstance(error.value, Raytun3rError)
    with pytest.raises(
        DuplicateBackboneError,
        match=r"load_backbone name\(s\) \['da3-small'\] are already provided by 'da3'",
    ):
        registry.register(
            dataclasses.replace(
                da3, family="da3-twin", builders={"da3-small": da3.builders["da3-small"]}
            )
        )
    replacement = dataclasses.replace(da3, builders={})
    assert (
        registry.register(replacement, overwrite=True) is replacement
        and registry._SPECS["da3"] is replacement
    )

    twin = dataclasses.replace(da3, family="da3-twin", builders={})
    typo = dataclasses.replace(twin.targets[0], hook="positional")
    with pytest.raises(
        BackboneRegistrationError,
        match="hook 'positional'; expected one of pe, rope, patch_embed, grid",
    ):
        registry.register(dataclasses.replace(twin, targets=(typo, *twin.targets[1:])))
    with pytest.raises(
        BackboneRegistrationError, match="must declare rope_classes and rope_base_attribute"
    ):
        registry.register(dataclasses.replace(twin, rope_base_attribute=None))
    with pytest.raises(BackboneRegistrationError, match="two PatchTargets"):
        registry.register(dataclasses.replace(twin, targets=(*twin.targets, twin.targets[0])))
    with pytest.raises(BackboneRegistrationError, match="upstream must be an UpstreamVersion"):
        registry.register(dataclasses.replace(twin, upstream="depth-anything-3 0.1.1"))
    assert "da3-twin" not in registry._SPECS


def test_every_spec_declares_its_tested_upstream():
    for family, spec in registry.specs().items():
        upstream = spec.upstream
        assert upstream.source and upstream.version and upstream.module, family
        if upstream.is_commit:  # a GitHub checkout is pinned by its full SHA
            assert re.fullmatch(r"[0-9a-f]{40}", upstream.version), family
        assert upstream.version[:7] in str(upstream)


def test_recognised_and_every_declared_owner_resolves(case, net):
    """The tiny model carries every owner of every target, so every hook is exercised."""
    spec, root = spec_for(net)
    assert spec.family == case.family and root is net
    resolved = {
        (target.name, path) for target, path, _ in resolve_targets(spec, root, set(HOOK_KINDS))
    }
    declared = {(target.name, path) for target in spec.targets for path in target.owners}
    assert resolved == declared
    info = spec.describe(root)
    assert (
        info.patch_size > 0
        and case.size[0] % info.patch_size == 0 == case.size[1] % info.patch_size
    )
    assert info.has_rope == ("rope" not in case.inert) and info.has_grid == (
        "grid" not in case.inert
    )
    assert _rope_instances(net)


def test_input_size_and_fit_recipes_are_declared_as_data(case, net):
    """Every family says at what size a fit and inference run by default (its upstream's own
    preprocessing), and its recipe changes, if any, name real recipes and fields."""
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.recipes import recipe_names

    spec, root = spec_for(net)
    size = registry.native_input_size(net)
    info = spec.describe(root)
    assert size == spec.input_size and size % info.patch_size == 0
    assert size == {"vggt": 518, "vggt_omega": 512}.get(case.family, 504)
    assert set(spec.recipe_changes) <= set(recipe_names())
    for name in recipe_names():
        config = AdaptConfig.from_recipe(name, model=net)
        assert config.recipe == name
        assert config.recipe_record(net)["changes"] == {}


# ---------------------------------------------------------------------------------------------
# Invariant 1 (pinhole identity), corrections, gradients
# ---------------------------------------------------------------------------------------------


def test_pinhole_zero_adapter_reproduces_upstream(case, net, images, reference):
    """Invariant 1: pinhole camera + zero adapter with every correction on = upstream."""
    camera, _ = _cameras(case)
    with rt.apply(net, camera, rt.Adapter.for_model(net, camera)) as handle:
        assert all(handle.components.values())
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_pinhole_identity_holds_at_another_rope_frequency(case, net, images):
    """The continuous angles use the frequency upstream uses (``rope_base_attribute``), not a guess."""
    spec, _ = spec_for(net)
    for rope in _rope_instances(net):
        setattr(rope, spec.rope_base_attribute, 37.0)
    reference = outputs(net, images)
    camera, _ = _cameras(case)
    with rt.apply(net, camera, rt.Adapter.for_model(net, camera)):
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_fisheye_and_adapter_change_outputs(case, net, images, reference):
    _, camera = _cameras(case)
    with rt.apply(net, camera):
        parameter_free = outputs(net, images)
    with rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera))):
        adapted = outputs(net, images)
    assert max_relative_difference(reference, parameter_free) > 1e-3
    assert max_relative_difference(parameter_free, adapted) > 1e-3


@pytest.mark.parametrize("component", COMPONENTS)
def test_each_component_has_an_effect(case, net, images, reference, component):
    _, camera = _cameras(case)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(
        net, camera, adapter, components={c: c == component for c in COMPONENTS}
    ) as handle:
        assert [c for c, on in handle.components.items() if on] == [component]
        one = outputs(net, images)
    difference = max_relative_difference(reference, one)
    if component in case.inert:
        assert difference == 0.0
    else:
        assert difference > 1e-4


def test_gradients_reach_only_adapter_tables(case, net, images):
    _, camera = _cameras(case)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    net.requires_grad_(False)
    with rt.apply(net, camera, adapter):
        prediction = rt.predict(net, images)
        (prediction.depth.mean() + prediction.cam_from_world[..., :3, 3].square().sum()).backward()
    assert {name for name, _ in adapter.named_parameters()} == {
        "pe.radial",
        "pe.angular",
        "rope.radial",
    }
    for name, parameter in adapter.named_parameters():
        if name.split(".")[0] in case.inert:  # e.g. no PE table (VGGT-Omega): nothing to reach
            assert parameter.grad is None or not bool(parameter.grad.any()), name
            continue
        assert parameter.grad is not None and float(parameter.grad.abs().sum()) > 0, name
    assert all(p.grad is None for p in net.parameters())


# ---------------------------------------------------------------------------------------------
# Invariants 2 (remove restores), 3 (all or nothing)
# ---------------------------------------------------------------------------------------------


def test_remove_restores_everything(case, net, images, reference, _upstream_globals):
    """Invariant 2: the same outputs, state_dict, attribute objects and upstream module globals."""
    snap, objects = snapshot(net), _deep_snapshot(net)
    globals_before = _module_globals(case.package) | _upstream_globals[case.package]
    handle = rt.apply(net, _cameras(case)[1], randomise_(rt.Adapter.for_model(net)), strict=False)
    assert max_relative_difference(reference, outputs(net, images)) > 1e-4
    assert handle.wrapped()
    handle.remove()
    handle.remove()  # idempotent
    assert_same_snapshot(net, snap)
    _assert_same_objects(net, objects)
    _assert_same_globals(case.package, globals_before)
    assert max_relative_difference(reference, outputs(net, images)) == 0.0
    assert rt.handle_of(net) is None


def test_remove_by_model_and_of_an_unpatched_model(case, net):
    rt.apply(net, _cameras(case)[1])
    rt.remove(net)
    assert rt.handle_of(net) is None
    with pytest.raises(NotAppliedError):
        rt.remove(net)


def test_disabled_gives_upstream_behaviour(case, net, images, reference):
    with rt.apply(net, _cameras(case)[1], randomise_(rt.Adapter.for_model(net))) as handle:
        patched = outputs(net, images)
        with handle.disabled():
            plain = outputs(net, images)
        again = outputs(net, images)
    assert max_relative_difference(reference, plain) == 0.0
    assert max_relative_difference(patched, again) == 0.0


def test_failure_at_the_last_install_rolls_back(
    case, net, images, reference, monkeypatch, _upstream_globals
):
    """Invariant 3: a failure while installing the last replacement leaves the model untouched."""
    spec, root = spec_for(net)
    count = len(resolve_targets(spec, root, set(HOOK_KINDS)))
    snap, objects = snapshot(net), _deep_snapshot(net)
    globals_before = _module_globals(case.package) | _upstream_globals[case.package]
    calls = fail_install_at(monkeypatch, count)
    with pytest.raises(RuntimeError, match="injected"):
        rt.apply(net, _cameras(case)[1], randomise_(rt.Adapter.for_model(net)))
    assert calls["n"] == count
    assert_same_snapshot(net, snap)
    _assert_same_objects(net, objects)
    _assert_same_globals(case.package, globals_before)
    assert rt.handle_of(net) is None
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


# ---------------------------------------------------------------------------------------------
# Refusals: a changed upstream is reported, expected X found Y, before anything changes
# ---------------------------------------------------------------------------------------------


def _renamed(self, *moved_arguments):  # an upstream method whose parameters changed
    raise AssertionError("never called")


def test_changed_upstream_signature_is_refused_before_any_change(case, net, monkeypatch):
    spec, root = spec_for(net)
    snap = snapshot(net)
    for target in spec.targets:
        owner = next(
            owner for path in target.owners if (owner := resolve_path(root, path)) is not None
        )
        with monkeypatch.context() as patch:
            patch.setattr(type(owner), target.attribute, _renamed)
            with pytest.raises(UnsupportedUpstreamError) as error:
                rt.apply(net, _cameras(case)[1])
        message = str(error.value)
        assert f"patch {target.name!r}" in message, message
        assert (
            f"expected signature {target.attribute}({', '.join(target.signature)}), found {target.attribute}(moved_arguments)"
            in message
        )
        assert f"checked against {spec.upstream}" in message
        assert_same_snapshot(net, snap)
        assert rt.handle_of(net) is None


def test_moved_upstream_submodule_is_refused_before_any_change(case, net):
    spec, root = spec_for(net)
    snap = snapshot(net)
    for path in dict.fromkeys(path for target in spec.targets for path in target.owners):
        parent, _, name = path.rpartition(".")
        owner = resolve_path(root, parent) if parent else root
        original = getattr(owner, name)
        # Swapped by hand: pytest's monkeypatch (9.2) deletes, rather than restores, a submodule
        # that nn.Module keeps in _modules instead of the instance __dict__.
        setattr(owner, name, nn.Identity())
        try:
            with pytest.raises(
                UnsupportedUpstreamError,
                match=rf"expected .* at '{re.escape(path)}', found torch\.nn\.modules\.linear\.Identity",
            ):
                rt.apply(net, _cameras(case)[1])
        finally:
            setattr(owner, name, original)
        assert_same_snapshot(net, snap)
        assert rt.handle_of(net) is None


def test_renamed_rope_frequency_attribute_is_refused(case, net, monkeypatch):
    spec, _ = spec_for(net)
    name = spec.rope_base_attribute
    rope = _rope_instances(net)[0]
    monkeypatch.setattr(rope, "renamed_frequency", getattr(rope, name), raising=False)
    monkeypatch.delattr(rope, name)
    snap = snapshot(net)
    with pytest.raises(
        UnsupportedUpstreamError,
        match=rf"expected the RoPE frequency base .* {type(rope).__qualname__}\.{name}, found no attribute '{name}' \(its numeric attributes: .*renamed_frequency=",
    ):
        rt.apply(net, _cameras(case)[1])
    assert_same_snapshot(net, snap)


def test_uncovered_rope_instance_is_refused(case, net, monkeypatch):
    """An upstream change that adds a RoPE copy must not leave part of the model unpatched."""
    monkeypatch.setattr(net, "extra_rope", copy.deepcopy(_rope_instances(net)[0]), raising=False)
    snap = snapshot(net)
    with pytest.raises(
        UnsupportedUpstreamError,
        match="at 'extra_rope' that is not one of the patched RoPE instances",
    ):
        rt.apply(net, _cameras(case)[1])
    assert_same_snapshot(net, snap)


def test_idempotent_and_already_applied(case, net):
    height, width = case.size
    camera = fisheye(width, height)
    adapter = rt.Adapter.for_model(net, camera)
    with rt.apply(net, camera, adapter) as first:
        assert rt.apply(net, camera, adapter) is first
        with pytest.raises(AlreadyAppliedError):
            rt.apply(net, fisheye(width, height, fov_deg=170.0), adapter, strict=False)
        with pytest.raises(AlreadyAppliedError):
            rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))


def test_wrong_image_size_is_a_clear_error(case, net):
    height, width = case.size
    patch = spec_for(net)[0].describe(net).patch_size
    with (
        rt.apply(net, fisheye(width, height)),
        pytest.raises(InputError, match=f"multiple of the patch size {patch}"),
    ):
        rt.predict(net, torch.rand(1, 2, 3, height + 3, width))


# ---------------------------------------------------------------------------------------------
# Invariants 4 (side by side), 6 (save / load); the camera follows the input size
# ---------------------------------------------------------------------------------------------


def test_two_models_different_cameras_side_by_side(case, images):
    """Invariant 4 (also from two threads): each patched model equals itself alone; others untouched."""
    net_a, net_b, bystander = make(case.family), make(case.family), make(case.family)
    plain = outputs(bystander, images)
    height, width = case.size
    camera_a, camera_b = fisheye(width, height, 190.0), fisheye(width, height, 150.0)
    adapter = randomise_(rt.Adapter.for_model(net_a))
    with rt.apply(net_a, camera_a, adapter, strict=False):
        alone_a = outputs(net_a, images)
    with rt.apply(net_b, camera_b, adapter, strict=False):
        alone_b = outputs(net_b, images)
    assert max_relative_difference(alone_a, alone_b) > 1e-4
    attributes = {target.attribute for target in spec_for(net_a)[0].targets}
    with (
        rt.apply(net_a, camera_a, adapter, strict=False),
        rt.apply(net_b, camera_b, adapter, strict=False),
    ):
        assert max_relative_difference(alone_a, outputs(net_a, images)) == 0.0
        assert max_relative_difference(alone_b, outputs(net_b, images)) == 0.0
        assert max_relative_difference(plain, outputs(bystander, images)) == 0.0
        assert not any(
            attribute in vars(module) for module in bystander.modules() for attribute in attributes
        )
        results = outputs_from_threads({"a": net_a, "b": net_b}, images, repeats=1)
    assert max_relative_difference(alone_a, results["a"]) == 0.0
    assert max_relative_difference(alone_b, results["b"]) == 0.0


def test_saved_and_loaded_adapter_is_bit_identical(case, net, images, tmp_path):
    """Invariant 6."""
    _, camera = _cameras(case)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    loaded = rt.Adapter.load(adapter.save(tmp_path / "cam.safetensors"))
    with rt.apply(net, camera, adapter):
        before = outputs(net, images)
    with rt.apply(net, None, loaded):  # the camera comes from the file
        after = outputs(net, images)
    assert max_relative_difference(before, after) == 0.0


def test_camera_follows_input_size(case, net, images):
    """A camera for the native image at twice the input size is rescaled to the input."""
    height, width = case.size
    adapter = randomise_(rt.Adapter.for_model(net))
    with rt.apply(net, fisheye(2 * width, 2 * height), adapter, strict=False):
        from_native = outputs(net, images)
    with rt.apply(net, fisheye(width, height), adapter, strict=False):
        from_direct = outputs(net, images)
    assert max_relative_difference(from_native, from_direct) < 1e-4
    with (
        rt.apply(net, fisheye(width, 2 * height), adapter, strict=False),
        pytest.raises(InputError, match="aspect"),
    ):
        outputs(net, images)


# ---------------------------------------------------------------------------------------------
# torch.compile (docs/deployment.md): slow, each compile traces the model again
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_compiled_patched_model(case):
    """Compiled = eager patched; no recompiles for one camera and size; ``disabled()``,
    ``remove()`` and a new camera behave as in eager, each compiling its variant once."""
    from tests.compile_checks import check_compiled_lifecycle

    check_compiled_lifecycle(case.family, "aot_eager")


@pytest.mark.slow
@pytest.mark.parametrize("component", COMPONENTS)
def test_compiled_patched_model_with_one_component(case, component):
    from tests.compile_checks import check_compiled_lifecycle

    check_compiled_lifecycle(
        case.family, "eager", components={c: c == component for c in COMPONENTS}
    )
