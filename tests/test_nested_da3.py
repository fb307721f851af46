"""The nested DA3 model (issue 14): both networks patched by one ``apply``, loaded, predicted.

The model is upstream's real ``NestedDepthAnything3Net``, built from DictConfigs at the
smallest DINOv2 size upstream offers (vits, 384 wide) for both branches: the any-view branch is
upstream's own ``da3-small`` config, the metric branch a ``da3metric-large`` config shrunk to
vits (no RoPE, DPT head). Full size (a 1.1 B-parameter giant plus a large) is not built here.
"""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("depth_anything_3")

from raytun3r_plugin.patches import da3 as da3_patch  # noqa: E402
from raytun3r_plugin.patches import da3_networks  # noqa: E402
from safetensors.torch import save_model  # noqa: E402

import raytun3r_plugin as rt  # noqa: E402
from raytun3r_plugin import registry  # noqa: E402
from raytun3r_plugin.apps.cli import main  # noqa: E402
from raytun3r_plugin.errors import AdapterError, InputError, UnsupportedUpstreamError  # noqa: E402
from raytun3r_plugin.patch_wrapper import WRAPPER_MARK  # noqa: E402
from raytun3r_plugin.patching import handle_of  # noqa: E402
from raytun3r_plugin.registry import spec_for  # noqa: E402
from raytun3r_plugin.weights import describe_checkpoint  # noqa: E402
from tests.helpers import (  # noqa: E402
    assert_same_snapshot,
    fisheye,
    max_relative_difference,
    outputs,
    pinhole,
    randomise_,
    snapshot,
)

torch.set_num_threads(1)

_OBJECT = {"args": "as_params"}


def _metric_config():
    """``da3metric-large`` at the vits size: no RoPE / alternating attention, a DPT head."""
    from omegaconf import OmegaConf

    return OmegaConf.create(
        {
            "__object__": {"path": "depth_anything_3.model.da3", "name": "DepthAnything3Net"}
            | _OBJECT,
            "net": {
                "__object__": {"path": "depth_anything_3.model.dinov2.dinov2", "name": "DinoV2"}
                | _OBJECT,
                "name": "vits",
                "out_layers": [2, 5, 8, 11],
                "alt_start": -1,
                "qknorm_start": -1,
                "rope_start": -1,
                "cat_token": False,
            },
            "head": {
                "__object__": {"path": "depth_anything_3.model.dpt", "name": "DPT"} | _OBJECT,
                "dim_in": 384,
                "output_dim": 1,
                "features": 32,
                "out_channels": [48, 96, 192, 384],
            },
        }
    )


def build_tiny_nested(seed: int = 0) -> torch.nn.Module:
    """A real ``NestedDepthAnything3Net`` with small random weights and a sky-free metric head.

    Upstream's constructor leaves the PE tables at zero; random weights exercise the PE hook.
    The metric sky head's last bias is negative, so (ReLU) no pixel is sky and upstream's
    alignment has pixels to fit.
    """
    from depth_anything_3.cfg import load_config
    from depth_anything_3.model.da3 import NestedDepthAnything3Net
    from depth_anything_3.registry import MODEL_REGISTRY

    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        net = NestedDepthAnything3Net(load_config(MODEL_REGISTRY["da3-small"]), _metric_config())
        with torch.no_grad():
            for parameter in net.parameters():
                parameter.normal_(0, 0.02)
            net.da3_metric.head.scratch.sky_output_conv2[-1].bias.fill_(-1.0)
    finally:
        torch.random.set_rng_state(generator_state)
    return net.eval()


@pytest.fixture(scope="module")
def net():
    return build_tiny_nested()


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, 70, 84, generator=torch.Generator().manual_seed(1))


@pytest.fixture(scope="module")
def reference(net, images):
    """The unpatched nested model's own forward (upstream's metric alignment included)."""
    return outputs(net, images)


def _wrapped(module, attribute: str) -> bool:
    return getattr(vars(module).get(attribute), WRAPPER_MARK, False)


def _metric_depth(net, images) -> torch.Tensor:
    from raytun3r_plugin.prediction import imagenet_normalise

    with torch.no_grad():
        return net.da3_metric(imagenet_normalise(images)).depth


def test_recognised_as_two_da3_branches(net):
    spec, root = spec_for(net)
    assert spec.family == "da3nested" and root is net
    assert spec.branches == (("da3", "da3"), ("da3_metric", "da3"))
    info = spec.describe(root)  # exactly the main branch
    assert info == da3_patch.describe(net.da3) and info.name == "da3-small"
    assert info.pos_embed is net.da3.backbone.pretrained.pos_embed and info.has_rope
    assert "da3nested" not in registry.specs()  # a composite of da3, not a family of its own
    # Each inner network alone is still a plain DA3 net.
    assert spec_for(net.da3_metric)[0].family == "da3"


def test_one_apply_patches_both_branches(net, images):
    with rt.apply(net, fisheye()) as handle:
        for branch in (net.da3, net.da3_metric):
            vit = branch.backbone.pretrained
            assert _wrapped(vit, "interpolate_pos_encoding")
            assert _wrapped(vit.patch_embed, "forward") and _wrapped(branch.head, "_add_pos_embed")
        assert _wrapped(net.da3.backbone.pretrained.rope, "forward")  # only the main has RoPE
        assert handle.patched.count("DinoVisionTransformer.interpolate_pos_encoding") == 2
        assert handle_of(net) is handle and handle_of(net.da3) is None
        # The parameter-free corrections act on the metric branch too.
        patched = _metric_depth(net, images)
        with handle.disabled():
            plain = _metric_depth(net, images)
        assert not torch.equal(patched, plain)
        # Applying again to an inner network is refused: its methods are wrapped already.
        with pytest.raises(rt.AlreadyAppliedError):
            rt.apply(net.da3_metric, fisheye())


def test_pe_hook_runs_in_the_metric_branch(net, images):
    plain = _metric_depth(net, images)
    with rt.apply(net, fisheye(), components=["pe_naive_remap"]):
        remapped = _metric_depth(net, images)  # only the PE hook is installed
    assert not torch.equal(remapped, plain)


def test_adapter_goes_to_the_main_branch_only(net, images):
    adapter = randomise_(rt.Adapter.for_model(net, fisheye()), scale=0.5)
    plain = _metric_depth(net, images)
    before = outputs(net, images)
    with rt.apply(net, fisheye(), adapter, components=["pe"]) as handle:
        assert handle._states[0].adapter is adapter and handle._states[1].adapter is None
        assert torch.equal(_metric_depth(net, images), plain)  # zero learned tables there
        assert max_relative_difference(outputs(net, images), before) > 1e-4


def test_pinhole_zero_adapter_is_the_identity(net, images, reference):
    adapter = rt.Adapter.for_model(net, pinhole())
    with rt.apply(net, pinhole(), adapter):
        patched = outputs(net, images)
    assert max_relative_difference(patched, reference) < 1e-5


def test_remove_is_exact_and_apply_idempotent(net, images, reference):
    before = snapshot(net)
    handle = rt.apply(net, fisheye())
    assert rt.apply(net, fisheye()) is handle
    assert max_relative_difference(outputs(net, images), reference) > 1e-6
    handle.remove()
    handle.remove()
    assert_same_snapshot(net, before)
    assert all(not _wrapped(module, name) for module in net.modules() for name in vars(module))
    assert max_relative_difference(outputs(net, images), reference) == 0.0


def test_wrong_width_adapter_leaves_the_model_untouched(net):
    before = snapshot(net)
    adapter = rt.Adapter(backbone="da3-small", embed_dim=1024, camera=fisheye())
    with pytest.raises(AdapterError, match=r"matches none of its branches.*main branch 'da3'"):
        rt.apply(net, fisheye(), adapter)
    assert handle_of(net) is None
    assert_same_snapshot(net, before)


def test_adapter_of_the_metric_width_is_refused_naming_the_branch():
    """Branches of other widths (64 and 48, as the giant's 1536 and the large's 1024)."""
    nested = da3_networks.build_tiny_nested_network(embed_dim=64, metric_embed_dim=48)
    metric_sized = rt.Adapter.for_model(nested.da3_metric, fisheye())
    assert metric_sized.embed_dim == 48
    before = snapshot(nested)
    with pytest.raises(
        AdapterError, match=r"width of the branch 'da3_metric'.*applied to its main branch 'da3'"
    ):
        rt.apply(nested, fisheye(), metric_sized, strict=False)
    assert handle_of(nested) is None
    assert_same_snapshot(nested, before)
    assert rt.Adapter.for_model(nested, fisheye()).embed_dim == 64  # the main branch's


def test_adapter_tables_train_through_the_main_branch(net, images):
    """Upstream's nested forward scales in place (no gradient through it); the adapter is fitted
    on ``model.da3`` while the nested handle is on, and is then the nested model's adapter."""
    adapter = randomise_(rt.Adapter.for_model(net, fisheye()), scale=0.05)
    with rt.apply(net, fisheye(), adapter):
        prediction = rt.predict(net.da3, images)
        prediction.depth.mean().backward()
    net.zero_grad(set_to_none=True)  # the (module-scoped) weights are not what is tested
    grads = [p.grad for p in adapter.parameters() if p.grad is not None]
    assert grads and any(float(g.abs().sum()) > 0 for g in grads)


def test_a_failing_branch_leaves_the_other_untouched(net):
    """All or nothing: the metric branch refuses (its PE owner moved), the main one stays bare."""
    before = snapshot(net)
    vit = net.da3_metric.backbone.pretrained
    patch_embed = vit.patch_embed
    try:
        # An upstream change: the tokeniser is no longer a PatchEmbed.
        object.__setattr__(vit, "_modules", dict(vit._modules, patch_embed=torch.nn.Identity()))
        with pytest.raises(UnsupportedUpstreamError, match="PatchEmbed"):
            rt.apply(net, fisheye())
    finally:
        object.__setattr__(vit, "_modules", dict(vit._modules, patch_embed=patch_embed))
    assert handle_of(net) is None
    assert_same_snapshot(net, before)


def test_a_missing_branch_is_refused(net):
    metric = net.da3_metric
    try:
        object.__setattr__(
            net, "_modules", {k: v for k, v in net._modules.items() if k != "da3_metric"}
        )
        with pytest.raises(
            UnsupportedUpstreamError, match="expected a da3 network at 'da3_metric'"
        ):
            rt.apply(net, fisheye())
    finally:
        object.__setattr__(net, "_modules", dict(net._modules, da3_metric=metric))
    assert handle_of(net) is None


def test_predict_keeps_the_metric_scale(net, images, reference):
    with rt.apply(net, fisheye()):
        with torch.no_grad():
            nested = rt.predict(net, images)
            main_alone = rt.predict(net.da3, images)  # the patched main branch, unscaled
    scale = nested.extras["metric_scale"]
    assert scale.ndim == 0 and not torch.isclose(scale, torch.tensor(1.0))
    # No sky in this model: the nested depth is the main branch's, scaled by upstream's fit.
    torch.testing.assert_close(nested.depth, main_alone.depth * scale, rtol=1e-5, atol=0)
    translation = nested.cam_from_world[..., :3, 3]
    torch.testing.assert_close(
        translation, main_alone.cam_from_world[..., :3, 3] * scale, rtol=1e-4, atol=1e-6
    )
    assert nested.depth.shape == reference["depth"].shape


def test_deepcopy_of_a_patched_nested_model_runs_its_own_branches(net, images):
    import copy

    with rt.apply(net, fisheye()):
        expected = outputs(net, images)
        twin = copy.deepcopy(net)
    handle = handle_of(twin)
    assert handle is not None and len(handle._states) == 2
    assert max_relative_difference(outputs(twin, images), expected) == 0.0
    handle.remove()
    assert not _wrapped(twin.da3_metric.backbone.pretrained, "interpolate_pos_encoding")


# ---------------------------------------------------------------------------------------------
# Loading: the official layout, strict keys, the recorded name, ``raytun3r weights``
# ---------------------------------------------------------------------------------------------


class _Wrapper(torch.nn.Module):
    """The ``depth_anything_3.api.DepthAnything3`` layout: keys ``model.da3.*``."""

    def __init__(self, inner: torch.nn.Module) -> None:
        super().__init__()
        self.model = inner


@pytest.fixture(scope="module")
def folder(net, tmp_path_factory):
    path = tmp_path_factory.mktemp("DA3NESTED-GIANT-LARGE")
    save_model(_Wrapper(net), str(path / "model.safetensors"))
    config = {"model_name": "da3nested-giant-large", "config": {"anyview": {}, "metric": {}}}
    (path / "config.json").write_text(json.dumps(config))
    return path


@pytest.fixture
def tiny_builds(monkeypatch):
    """Build the tiny nested net (other random weights) where the full-size one would be built."""
    built = []

    def build(name):
        model = build_tiny_nested(seed=7)
        model.raytun3r_name = name
        built.append(name)
        return model

    monkeypatch.setattr(da3_networks, "build_network", build)
    monkeypatch.setitem(da3_networks._NEEDS, "da3nested-giant-large", ())  # evo: giant's GS head
    return built


@pytest.mark.parametrize("name", [None, "da3nested-giant-large", "da3nested-giant-large-1.1"])
def test_load_backbone_builds_and_loads_the_nested_model(name, net, folder, tiny_builds):
    loaded = rt.load_backbone(name, folder)
    assert tiny_builds == [name or "da3nested-giant-large"]
    assert loaded.raytun3r_name == (name or "da3nested-giant-large")
    reference = net.state_dict()
    state = loaded.state_dict()
    assert state.keys() == reference.keys()
    assert all(torch.equal(state[k], reference[k]) for k in reference)
    spec, root = spec_for(loaded)
    assert spec.family == "da3nested" and root is loaded


def test_missing_branch_keys_are_a_strict_load_error(net, tmp_path, tiny_builds):
    state = {
        "model." + k: v.clone()
        for k, v in net.state_dict().items()
        if not k.startswith("da3_metric.head.")
    }
    torch.save(state, tmp_path / "model.pt")
    with pytest.raises(rt.WeightsError, match="da3_metric.head"):
        rt.load_backbone("da3nested-giant-large", tmp_path)


def test_weights_command_says_what_the_file_is_and_how_to_load_it(folder, capsys):
    record = describe_checkpoint(folder)
    assert record["family"] == "da3" and record["name"] == "da3nested-giant-large"
    assert record["load"] == f"raytun3r_plugin.load_backbone('da3nested-giant-large', '{folder}')"
    assert main(["weights", str(folder)]) == 0
    text = capsys.readouterr().out
    assert "da3nested-giant-large" in text and "load_backbone('da3nested-giant-large'" in text


# ---------------------------------------------------------------------------------------------
# Registration of branched specs, and what the nested model does not offer
# ---------------------------------------------------------------------------------------------


def test_register_refuses_inconsistent_branched_specs(monkeypatch):
    import dataclasses

    from raytun3r_plugin.errors import BackboneRegistrationError

    monkeypatch.setattr(registry, "_SPECS", dict(registry.specs()))  # register into a copy
    da3 = registry.specs()["da3"]
    nested = da3_patch.NESTED_SPEC
    bad = {
        "declares branches and targets": dataclasses.replace(nested, targets=da3.targets),
        "branch paths must be distinct": dataclasses.replace(
            nested, branches=(("da3", "da3"), ("da3", "da3"))
        ),
        "names family 'nope'": dataclasses.replace(nested, branches=(("da3", "nope"),)),
    }
    for message, spec in bad.items():
        with pytest.raises(BackboneRegistrationError, match=message):
            registry.register(dataclasses.replace(spec, family="other"))
    with pytest.raises(BackboneRegistrationError, match="reuses a registered family name"):
        registry.register(
            dataclasses.replace(da3, composites=(dataclasses.replace(nested, family="vggt"),)),
            overwrite=True,
        )
    with pytest.raises(BackboneRegistrationError, match="must declare branches"):
        registry.register(
            dataclasses.replace(da3, composites=(dataclasses.replace(nested, branches=()),)),
            overwrite=True,
        )


def test_single_network_baselines_are_refused_on_the_nested_model(net):
    from raytun3r_plugin.baselines.lora import lora_targets

    with pytest.raises(UnsupportedUpstreamError, match="da3nested: declares no transformer blocks"):
        lora_targets(net)
    assert lora_targets(net.da3)  # the branch alone is a plain DA3 net


@pytest.mark.slow
def test_full_size_nested_model_in_the_hub_layout_loads_patches_and_predicts(
    tmp_path, monkeypatch, images
):
    """The real da3nested-giant-large at full size (a ViT-g and a ViT-L, about 1.4 B parameters,
    5.6 GB in float32), saved as the hub folder holds it, through load_backbone and one apply."""
    import sys
    import types
    from importlib.util import find_spec

    if find_spec("evo") is None:
        # DA3 imports evo.core.trajectory (pose alignment) when its giant config is built and no
        # forward calls it; a stand-in module lets the real network be built where evo is absent.
        trajectory = types.ModuleType("evo.core.trajectory")
        trajectory.PosePath3D = object
        for name, module in (
            ("evo", types.ModuleType("evo")),
            ("evo.core", types.ModuleType("evo.core")),
            ("evo.core.trajectory", trajectory),
        ):
            monkeypatch.setitem(sys.modules, name, module)
        monkeypatch.setitem(da3_networks._NEEDS, "da3nested-giant-large", ())
    folder = tmp_path / "DA3NESTED-GIANT-LARGE"
    folder.mkdir()
    built = da3_networks.build_network("da3nested-giant-large")
    save_model(_Wrapper(built), str(folder / "model.safetensors"))
    config = {"model_name": "da3nested-giant-large", "config": {"anyview": {}, "metric": {}}}
    (folder / "config.json").write_text(json.dumps(config))
    del built
    loaded = rt.load_backbone(None, folder)
    assert loaded.raytun3r_name == "da3nested-giant-large"
    spec, root = spec_for(loaded)
    assert spec.family == "da3nested" and root is loaded
    assert spec.describe(root).embed_dim == 1536  # the adapter's width: the ViT-g branch
    assert loaded.da3_metric.backbone.pretrained.embed_dim == 1024
    with rt.apply(loaded, fisheye()) as handle:
        assert handle.patched.count("DinoVisionTransformer.interpolate_pos_encoding") == 2
        prediction = rt.predict(loaded, images)
    assert torch.isfinite(prediction.depth).all() and (prediction.depth > 0).all()
    assert "metric_scale" in prediction.extras
    assert handle_of(loaded) is None


def test_a_rig_patches_both_branches_per_view(net, images, reference):
    """A rig on the nested model: each branch's hooks give each view its own camera."""
    cameras = [fisheye(84, 70, 190.0), fisheye(84, 70, 150.0, k1=0.04)]
    adapters = [
        randomise_(rt.Adapter.for_model(net, c), seed=s)
        for c, s in zip(cameras, (1, 2), strict=True)
    ]
    before = snapshot(net)
    tokens = torch.zeros(2, 1 + 5 * 6, net.da3_metric.backbone.pretrained.embed_dim)
    pictures = torch.rand(2, 3, 70, 84, generator=torch.Generator().manual_seed(2))

    def per_branch():
        return [
            (
                branch.backbone.pretrained.interpolate_pos_encoding(tokens, 70, 84),
                branch.backbone.pretrained.patch_embed(pictures),
            )
            for branch in (net.da3_metric, net.da3)
        ]

    with torch.no_grad():
        singles = []
        for camera, adapter in zip(cameras, adapters, strict=True):
            with rt.apply(net, camera, adapter):
                singles.append(per_branch())
        with rt.apply(net, cameras, adapters) as handle:
            assert handle.is_rig and all(state.rig for state in handle._states)
            rig = per_branch()
            patched = outputs(net, images)
    (pe, patches), (main_pe, main_patches) = rig
    for view in range(2):
        (single_pe, single_patches), (single_main_pe, single_main_patches) = singles[view]
        # The metric branch has no learned tables: its PE is upstream's; the patches are per view.
        assert torch.equal(pe, single_pe) and pe.shape[0] == 1
        assert torch.equal(patches[view], single_patches[view])
        # The main branch carries each view's adapter.
        assert torch.equal(main_pe[view], single_main_pe[0])
        assert torch.equal(main_patches[view], single_main_patches[view])
    assert not torch.equal(singles[0][0][1], singles[1][0][1])
    assert max_relative_difference(patched, reference) > 1e-4
    assert_same_snapshot(net, before)


def test_an_all_sky_input_is_an_input_error(net, images, monkeypatch):
    """Upstream asserts (in the nested class) when the metric alignment sees no scene; predict says so."""
    import inspect

    source = inspect.getsource(type(net))
    assert da3_patch.NESTED_SKY_ASSERTION in source  # the assertion is still upstream's

    def all_sky(*args, **kwargs):
        assert False, da3_patch.NESTED_SKY_ASSERTION  # noqa: B011, PT015 (what upstream raises)

    monkeypatch.setattr(net, "forward", all_sky)
    with pytest.raises(InputError, match="only sky"):
        rt.predict(net, images)
