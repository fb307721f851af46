"""apply()/remove() on VGGT, Pi3 and Pi3X (docs/conventions.md section 9, invariants 1, 2, 3, 4, 6).

Runs on the stub packages in ``tests/stubs`` (the documented tiny recipes), and unchanged on the
real upstream code when ``vggt`` / ``pi3`` are importable: the official models are 1-1.4 B
parameters, so there the same tests use small networks assembled from the upstream classes
(:func:`tiny_real`), exactly as the real ``__init__`` wires them but with small widths.
"""

from __future__ import annotations

import copy
import gc
import importlib
import inspect
import sys
from functools import partial

import pytest
import torch
from torch import nn

import raytun3r_plugin as rt
from raytun3r_plugin import hooks
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.errors import MissingDependencyError, UnsupportedUpstreamError, WeightsError
from raytun3r_plugin.registry import HOOK_KINDS, resolve_targets, spec_for
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

pytest.importorskip("vggt")
pytest.importorskip("pi3")
from raytun3r_plugin.patches import pi3 as pi3_patch  # noqa: E402
from raytun3r_plugin.patches import vggt as vggt_patch  # noqa: E402

H, W = 42, 56  # 3 x 4 patches of 14 px
KINDS = ("vggt", "pi3", "pi3x")
_PACKAGE = {"vggt": "vggt", "pi3": "pi3", "pi3x": "pi3"}


def is_stub(kind: str) -> bool:
    return bool(getattr(importlib.import_module(_PACKAGE[kind]), "__raytun3r_stub__", False))


# ---------------------------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------------------------


def _seeded(seed):
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    return generator_state


def tiny_real(kind: str, seed: int = 0) -> nn.Module:
    """A small network made of the real upstream classes, wired as upstream's ``__init__`` does."""
    state = _seeded(seed)
    try:
        return {"vggt": _tiny_real_vggt, "pi3": _tiny_real_pi3, "pi3x": _tiny_real_pi3x}[kind]().eval()
    finally:
        torch.random.set_rng_state(state)


def _tiny_real_vggt():
    from vggt.heads.camera_head import CameraHead
    from vggt.heads.dpt_head import DPTHead
    from vggt.models.aggregator import Aggregator
    from vggt.models.vggt import VGGT

    model = VGGT.__new__(VGGT)
    nn.Module.__init__(model)
    model.aggregator = Aggregator(img_size=70, patch_size=14, embed_dim=384, depth=2, num_heads=6, patch_embed="dinov2_vits14_reg")
    model.camera_head = CameraHead(dim_in=768, trunk_depth=1, num_heads=6)
    dpt = dict(dim_in=768, features=32, out_channels=[16, 32, 64, 64], intermediate_layer_idx=[0, 1, 0, 1])
    model.point_head = DPTHead(output_dim=4, activation="inv_log", conf_activation="expp1", **dpt)
    model.depth_head = DPTHead(output_dim=2, activation="exp", conf_activation="expp1", **dpt)
    model.track_head = None
    return model


def _pi3_trunk(model, module):
    """Encoder, RoPE, decoder and register tokens as in ``Pi3.__init__`` / ``Pi3X.__init__``."""
    from pi3.models.dinov2.hub.backbones import dinov2_vits14_reg
    from pi3.models.dinov2.layers import Mlp
    from pi3.models.layers.attention import FlashAttentionRope
    from pi3.models.layers.block import BlockRope
    from pi3.models.layers.pos_embed import PositionGetter

    model.encoder = dinov2_vits14_reg(pretrained=False)
    del model.encoder.mask_token
    model.patch_size = 14
    dim = model.encoder.embed_dim
    model.rope = module.RoPE2D(freq=100.0)  # the name the upstream module imported (cuRoPE2D or RoPE2D)
    model.position_getter = PositionGetter()
    norm = partial(nn.LayerNorm, eps=1e-6)
    model.decoder = nn.ModuleList(
        BlockRope(dim=dim, num_heads=6, mlp_ratio=4, qkv_bias=True, proj_bias=True, ffn_bias=True, drop_path=0.0, norm_layer=norm,
                  act_layer=nn.GELU, ffn_layer=Mlp, init_values=0.01, qk_norm=True, attn_class=FlashAttentionRope, rope=model.rope)
        for _ in range(2)
    )
    model.dec_embed_dim = dim
    model.patch_start_idx = 5
    model.register_token = nn.Parameter(torch.randn(1, 1, 5, dim) * 1e-6)
    model.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
    model.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
    return dim


def _tiny_real_pi3():
    import pi3.models.pi3 as module
    from pi3.models.layers.camera_head import CameraHead
    from pi3.models.layers.transformer_head import LinearPts3d, TransformerDecoder

    model = module.Pi3.__new__(module.Pi3)
    nn.Module.__init__(model)
    model.pos_type = "rope100"
    dim = _pi3_trunk(model, module)
    head = dict(in_dim=2 * dim, dec_embed_dim=64, dec_num_heads=4, depth=1, rope=model.rope)
    model.point_decoder = TransformerDecoder(out_dim=64, **head)
    model.point_head = LinearPts3d(patch_size=14, dec_embed_dim=64, output_dim=3)
    model.conf_decoder = copy.deepcopy(model.point_decoder)
    model.conf_head = LinearPts3d(patch_size=14, dec_embed_dim=64, output_dim=1)
    model.camera_decoder = TransformerDecoder(out_dim=32, use_checkpoint=False, **head)
    model.camera_head = CameraHead(dim=32)
    return model


def _tiny_real_pi3x():
    import pi3.models.pi3x as module
    from pi3.models.dinov2.layers import PatchEmbed
    from pi3.models.layers.camera_head import CameraHead
    from pi3.models.layers.conv_head import ConvHead
    from pi3.models.layers.transformer_head import ContextOnlyTransformerDecoder, TransformerDecoder

    model = module.Pi3X.__new__(module.Pi3X)
    nn.Module.__init__(model)
    model.use_multimodal = True
    dim = _pi3_trunk(model, module)
    model.depth_encoder = copy.deepcopy(model.encoder)
    del model.depth_encoder.patch_embed
    model.depth_encoder.patch_embed = PatchEmbed(img_size=224, patch_size=14, in_chans=2, embed_dim=dim)
    model.depth_emb = nn.Parameter(torch.zeros(1, 1, dim))
    model.ray_embed = PatchEmbed(img_size=224, patch_size=14, in_chans=2, embed_dim=dim)
    nn.init.normal_(model.ray_embed.proj.weight, std=0.02)  # upstream zero-initialises; nonzero so it matters
    model.pose_inject_blk = nn.ModuleList()  # pose conditioning is not exercised on the tiny real model
    head = dict(in_dim=2 * dim, dec_embed_dim=64, dec_num_heads=4, depth=1, rope=model.rope)
    conv = dict(num_features=4, dim_in=dim, projects=nn.Identity(), dim_proj=64, dim_upsample=[32, 32, 16], dim_times_res_block_hidden=2,
                num_res_blocks=1, res_block_norm="group_norm", last_res_blocks=0, last_conv_channels=8, last_conv_size=1, using_uv=True)
    model.point_decoder = TransformerDecoder(out_dim=64, **head)
    model.point_head = ConvHead(dim_out=[2, 1], **conv)
    model.camera_decoder = TransformerDecoder(out_dim=32, **head)
    model.camera_head = CameraHead(dim=32)
    model.metric_token = nn.Parameter(torch.randn(1, 1, 2 * dim) * 1e-6)
    model.metric_decoder = ContextOnlyTransformerDecoder(in_dim=2 * dim, out_dim=32, dec_embed_dim=32, depth=1, dec_num_heads=2, rope=model.rope)
    model.metric_head = nn.Linear(32, 1)
    model.conf_decoder = TransformerDecoder(out_dim=64, **head)  # shares model.rope, as upstream
    model.conf_head = ConvHead(dim_out=[1], **conv)
    return model


def build(kind: str, seed: int = 0) -> nn.Module:
    """A fresh model: the stub's documented tiny recipe, or a tiny real network."""
    if not is_stub(kind):
        return tiny_real(kind, seed)
    stub_config = importlib.import_module(f"{_PACKAGE[kind]}._stub_config")
    with stub_config.stub_sizes(seed=seed):
        if kind == "vggt":
            from vggt.models.vggt import VGGT

            return VGGT(img_size=70, patch_size=14, embed_dim=64, enable_track=False).eval()
        if kind == "pi3":
            from pi3.models.pi3 import Pi3

            return Pi3().eval()
        from pi3.models.pi3x import Pi3X

        return Pi3X().eval()


_PRISTINE: dict[tuple[str, int], nn.Module] = {}


def make(kind: str, seed: int = 0) -> nn.Module:
    """A private copy of a cached pristine model (building the real tiny ones takes seconds)."""
    if (kind, seed) not in _PRISTINE:
        _PRISTINE[kind, seed] = build(kind, seed)
    return copy.deepcopy(_PRISTINE[kind, seed])


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """The models are tiny: intra-op threads only spin on a shared 2-core machine (~10x CPU time)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(1))


@pytest.fixture(params=KINDS)
def kind(request):
    return request.param


@pytest.fixture
def net(kind):
    return make(kind)


@pytest.fixture
def reference(net, images):
    """Unpatched outputs of ``net`` itself (exact comparisons stay within one instance: CPU
    kernels may round differently for weights at other addresses)."""
    return outputs(net, images)




def conv_head_module():
    return importlib.import_module("pi3.models.layers.conv_head")


# ---------------------------------------------------------------------------------------------
# Structure
# ---------------------------------------------------------------------------------------------


def test_recognised_and_every_hook_resolves(net, kind):
    spec, root = spec_for(net)
    assert spec.family == kind and root is net
    resolved = {(target.name, path) for target, path, _ in resolve_targets(spec, root, set(HOOK_KINDS))}
    expected = {
        "vggt": {("pe_interpolation", "aggregator.patch_embed"), ("rope", "aggregator.rope"),
                 ("patch_embedding", "aggregator.patch_embed.patch_embed"), ("prediction_grid", "depth_head"),
                 ("prediction_grid", "point_head")},
        "pi3": {("pe_interpolation", "encoder"), ("rope", "rope"), ("rope", "conf_decoder.blocks.0.attn.rope"),
                ("patch_embedding", "encoder.patch_embed")},
        "pi3x": {("pe_interpolation", "encoder"), ("rope", "rope"), ("patch_embedding", "encoder.patch_embed"),
                 ("prediction_grid", "point_head"), ("prediction_grid", "conf_head")},
    }[kind]
    assert resolved == expected
    info = spec.describe(root)
    assert info.has_rope and info.patch_size == 14 and info.has_grid == (kind != "pi3")


def test_adapter_is_28_c_plus_20(net):
    info = spec_for(net)[0].describe(net)
    counts = rt.Adapter.for_model(net).num_parameters()
    assert counts == {"pe": 28 * info.embed_dim, "rope": 20, "total": 28 * info.embed_dim + 20}
    if info.name in ("vggt-1b", "pi3", "pi3x"):  # the official models: C = 1024
        assert counts["total"] == 28 * 1024 + 20


# ---------------------------------------------------------------------------------------------
# Invariants 1 (pinhole identity), corrections, gradients
# ---------------------------------------------------------------------------------------------


def test_pinhole_zero_adapter_reproduces_upstream(net, images, reference):
    """Invariant 1: pinhole camera + zero adapter with every correction on = upstream."""
    adapter = rt.Adapter.for_model(net, pinhole(W, H))
    with rt.apply(net, pinhole(W, H), adapter) as handle:
        assert all(handle.components.values())
        patched = outputs(net, images)
    assert max_relative_difference(reference, patched) < 1e-5


def test_fisheye_and_adapter_change_outputs_and_gradients_reach_every_table(net, images, reference):
    camera = fisheye(W, H)
    with rt.apply(net, camera):
        parameter_free = outputs(net, images)
    assert max_relative_difference(reference, parameter_free) > 1e-3
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    net.requires_grad_(False)
    with rt.apply(net, camera, adapter):
        prediction = rt.predict(net, images)
        adapted = {"depth": prediction.depth.detach(), "conf": prediction.confidence.detach(), "pose": prediction.cam_from_world.detach()}
        (prediction.depth.mean() + prediction.cam_from_world[..., :3, 3].square().sum()).backward()
    assert max_relative_difference(parameter_free, adapted) > 1e-3
    names = {name for name, _ in adapter.named_parameters()}
    assert names == {"pe.radial", "pe.angular", "rope.radial"}
    for name, parameter in adapter.named_parameters():
        assert parameter.grad is not None and float(parameter.grad.abs().sum()) > 0, name
    assert all(p.grad is None for p in net.parameters())


@pytest.mark.parametrize("component", COMPONENTS)
def test_each_component_has_an_effect(net, kind, images, reference, component):
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    only = {c: c == component for c in COMPONENTS}
    with rt.apply(net, camera, adapter, components=only):
        one = outputs(net, images)
    difference = max_relative_difference(reference, one)
    if kind == "pi3" and component == "grid":
        assert difference == 0.0  # Pi3 has no prediction grid
    else:
        assert difference > 1e-4


def test_rope_sees_float_displaced_positions_with_special_tokens_at_zero(net, images, monkeypatch):
    """Every RoPE call gets the upstream (y+1, x+1) grid plus the radial displacement, specials at 0."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    seen = []
    real = hooks.apply_rope_2d
    monkeypatch.setattr(hooks, "apply_rope_2d", lambda tokens, positions, base: seen.append(positions.detach().clone()) or real(tokens, positions, base))
    with rt.apply(net, camera, adapter, components=["rope"]) as handle:
        outputs(net, images)
        geometry = handle._state.geometry(H, W)
        displacement = handle._state.rope_displacement(geometry, torch.device("cpu"), torch.float32).detach()
    h, w = H // 14, W // 14
    grid = torch.cartesian_prod(torch.arange(h), torch.arange(w)).float() + 1
    expected_frame = torch.cat((torch.zeros(5, 2), grid + displacement))  # (5 + hw, 2)
    assert float(displacement.abs().max()) > 0.05
    layouts = set()
    for positions in seen:  # (Pi3X's metric query token, alone at (0, 0), keeps the upstream path)
        assert positions.dtype == torch.float32
        frames = positions.reshape(-1, 5 + h * w, 2)
        layouts.add(positions.shape[1] // (5 + h * w))
        assert torch.equal(frames, expected_frame.expand_as(frames))
    assert layouts == {1, 2}  # frame blocks / head decoders (one view per row), global blocks (both views)


def test_displacement_matches_the_layout_based_core_helper(net):
    """``displace_grid_positions`` equals ``hooks.displaced_rope_positions`` on a frame layout."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(net, camera, adapter) as handle:
        state = handle._state
        grid = torch.cartesian_prod(torch.arange(H // 14), torch.arange(W // 14))[None].expand(4, -1, -1) + 1
        frame = torch.cat((torch.zeros(4, 5, 2, dtype=torch.long), grid), dim=1)
        ours = hooks.displace_grid_positions(frame, state, 14)
        core = hooks.displaced_rope_positions(frame, 5, state, H, W)
        assert torch.equal(ours, core)
        global_layout = frame.reshape(2, -1, 2)
        assert torch.equal(hooks.displace_grid_positions(global_layout, state, 14), core.reshape(2, -1, 2))
        specials_only = torch.zeros(2, 1, 2, dtype=torch.long)
        assert hooks.displace_grid_positions(specials_only, state, 14) is specials_only


# ---------------------------------------------------------------------------------------------
# Invariants 2, 3, 4, 6
# ---------------------------------------------------------------------------------------------


def test_remove_restores_everything(net, kind, images, reference):
    """Invariant 2: same outputs, same state_dict, no leftover attributes, same signature."""
    snap = snapshot(net)
    signature = inspect.signature(net.forward)
    uv_function = conv_head_module().normalized_view_plane_uv
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
    gc.collect()
    assert conv_head_module().normalized_view_plane_uv is uv_function


def test_failure_part_way_rolls_back(net, images, reference, monkeypatch):
    """Invariant 3: a failure while installing leaves the model untouched."""
    snap = snapshot(net)
    uv_function = conv_head_module().normalized_view_plane_uv
    calls = fail_install_at(monkeypatch, 3)
    with pytest.raises(RuntimeError, match="injected"):
        rt.apply(net, fisheye(W, H), randomise_(rt.Adapter.for_model(net)))
    assert calls["n"] == 3
    assert_same_snapshot(net, snap)
    assert rt.handle_of(net) is None
    assert conv_head_module().normalized_view_plane_uv is uv_function  # apply installs no global
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


def test_two_models_different_cameras_side_by_side(kind, images):
    """Invariant 4 (also from two threads): each patched model equals itself alone."""
    net_a, net_b, bystander = make(kind), make(kind), make(kind)
    plain = outputs(bystander, images)
    camera_a, camera_b = fisheye(W, H, 190.0), fisheye(W, H, 150.0)
    adapter = randomise_(rt.Adapter.for_model(net_a))
    with rt.apply(net_a, camera_a, adapter, strict=False):
        alone_a = outputs(net_a, images)
    with rt.apply(net_b, camera_b, adapter, strict=False):
        alone_b = outputs(net_b, images)
    assert max_relative_difference(alone_a, alone_b) > 1e-4
    with rt.apply(net_a, camera_a, adapter, strict=False), rt.apply(net_b, camera_b, adapter, strict=False):
        assert max_relative_difference(alone_a, outputs(net_a, images)) == 0.0
        assert max_relative_difference(alone_b, outputs(net_b, images)) == 0.0
        assert max_relative_difference(plain, outputs(bystander, images)) == 0.0  # untouched instance
        assert not any(attribute in vars(module) for module in bystander.modules() for attribute in ("forward", "interpolate_pos_encoding", "_apply_pos_embed"))
        results = outputs_from_threads({"a": net_a, "b": net_b}, images, repeats=1)
    assert max_relative_difference(alone_a, results["a"]) == 0.0
    assert max_relative_difference(alone_b, results["b"]) == 0.0


def test_saved_and_loaded_adapter_is_bit_identical(net, images, tmp_path):
    """Invariant 6."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    loaded = rt.Adapter.load(adapter.save(tmp_path / "cam.safetensors"))
    with rt.apply(net, camera, adapter):
        before = outputs(net, images)
    with rt.apply(net, None, loaded):  # the camera comes from the file
        after = outputs(net, images)
    assert max_relative_difference(before, after) == 0.0


def test_disabled_gives_upstream_behaviour(net, images, reference):
    with rt.apply(net, fisheye(W, H), randomise_(rt.Adapter.for_model(net))) as handle:
        patched = outputs(net, images)
        with handle.disabled():
            plain = outputs(net, images)
        again = outputs(net, images)
    assert max_relative_difference(reference, plain) == 0.0
    assert max_relative_difference(patched, again) == 0.0


# ---------------------------------------------------------------------------------------------
# Refusals
# ---------------------------------------------------------------------------------------------


def _fake_curope_class():
    class cuRoPE2D(nn.Module):  # noqa: N801 (the compiled class's name)
        def __init__(self, freq=100.0, F0=1.0):
            super().__init__()

        def forward(self, tokens, positions):
            return tokens

    cuRoPE2D.__module__, cuRoPE2D.__qualname__ = "models.curope", "cuRoPE2D"
    return cuRoPE2D


@pytest.mark.parametrize("which", ["pi3", "pi3x"])
def test_compiled_curope_is_refused_before_any_change(which, monkeypatch):
    """pi3.models.layers.pos_embed binds RoPE2D = cuRoPE2D when ``models.curope`` imports."""
    module = importlib.import_module(f"pi3.models.{which}")
    monkeypatch.setattr(module, "RoPE2D", _fake_curope_class())
    model = build(which)
    assert type(model.rope).__name__ == "cuRoPE2D"
    snap = snapshot(model)
    with pytest.raises(UnsupportedUpstreamError, match=r"compiled RoPE models\.curope\.cuRoPE2D at 'rope'.*PyTorch RoPE2D"):
        rt.apply(model, fisheye(W, H))
    assert_same_snapshot(model, snap)
    assert rt.handle_of(model) is None


def test_uncovered_rope_instance_is_refused(net, kind):
    """An upstream change that adds a RoPE copy must not leave part of the model unpatched."""
    if kind == "vggt":
        attention = net.aggregator.global_blocks[0].attn
        attention.rope, where = copy.deepcopy(attention.rope), "aggregator.global_blocks.0.attn.rope"
    elif kind == "pi3":
        attention = net.camera_decoder.blocks[0].attn
        attention.rope, where = copy.deepcopy(attention.rope), "camera_decoder.blocks.0.attn.rope"
    else:
        net.conf_decoder, where = copy.deepcopy(net.conf_decoder), "conf_decoder.blocks.0.attn.rope"
    snap = snapshot(net)
    with pytest.raises(UnsupportedUpstreamError, match=f"at '{where}' that is not one of the patched RoPE instances"):
        rt.apply(net, fisheye(W, H))
    assert_same_snapshot(net, snap)


def test_structural_mismatch_is_reported_before_any_change(net, kind, monkeypatch):
    owner = net.aggregator.rope if kind == "vggt" else net.rope if kind == "pi3" else net.point_head

    def renamed(self, features, coordinates=None):  # a changed upstream signature
        raise AssertionError("never called")

    monkeypatch.setattr(type(owner), "forward", renamed)
    snap = snapshot(net)
    with pytest.raises(UnsupportedUpstreamError, match=r"expected signature forward\(.*\), found forward\(features, coordinates\)"):
        rt.apply(net, fisheye(W, H))
    assert_same_snapshot(net, snap)


# ---------------------------------------------------------------------------------------------
# Pi3X: conditioning paths and the uv trampoline
# ---------------------------------------------------------------------------------------------


def _conditions():
    generator = torch.Generator().manual_seed(7)
    focal = 30.0
    intrinsics = torch.tensor([[focal, 0.0, W / 2], [0.0, focal, H / 2], [0.0, 0.0, 1.0]]).expand(1, 2, 3, 3).clone()
    depths = 1.0 + torch.rand(1, 2, H, W, generator=generator)
    return {"intrinsics": intrinsics, "depths": depths}


def test_pi3x_conditioning_paths_are_untouched(images):
    """Only the image path is patched: ray_embed and depth_encoder see and give the same."""
    net = make("pi3x")
    conditions = _conditions()
    recorded = {}

    def recorder(name):
        return lambda module, args, output: recorded.setdefault(name, []).append(output["x_norm_patchtokens"] if isinstance(output, dict) else output)

    handles = [net.ray_embed.register_forward_hook(recorder("ray")), net.depth_encoder.register_forward_hook(recorder("depth"))]
    try:
        with torch.no_grad():
            plain = net(images, **conditions)
        camera = fisheye(W, H)
        with rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera))):
            for module in (net.ray_embed, net.depth_encoder, net.depth_encoder.patch_embed):
                assert not {"forward", "interpolate_pos_encoding"} & set(vars(module))
            with torch.no_grad():
                patched = net(images, **conditions)
    finally:
        for handle in handles:
            handle.remove()
    assert len(recorded["ray"]) == len(recorded["depth"]) == 2
    assert torch.equal(recorded["ray"][0], recorded["ray"][1])
    assert torch.equal(recorded["depth"][0], recorded["depth"][1])
    assert not torch.allclose(plain["local_points"], patched["local_points"])  # the image path did change


def test_pi3x_pinhole_identity_with_conditions(images):
    net = make("pi3x")
    conditions = _conditions()
    with torch.no_grad():
        plain = net(images, **conditions)
        with rt.apply(net, pinhole(W, H), rt.Adapter.for_model(net)):
            patched = net(images, **conditions)
    for key in ("local_points", "conf", "camera_poses"):
        assert torch.allclose(plain[key], patched[key], rtol=0, atol=1e-5 * float(plain[key].abs().max()))


def test_pi3x_uv_trampoline_lifecycle(images):
    module = conv_head_module()
    original = module.normalized_view_plane_uv
    net_a, net_b = make("pi3x"), make("pi3x")
    handle_a = rt.apply(net_a, fisheye(W, H, 190.0))
    handle_b = rt.apply(net_b, fisheye(W, H, 150.0))
    assert module.normalized_view_plane_uv is original  # installed lazily, by the first forward
    outputs(net_a, images)
    trampoline = module.normalized_view_plane_uv
    assert isinstance(trampoline, pi3_patch._UvTrampoline) and trampoline.original is original
    # outside a patched head it is the original function
    assert torch.equal(trampoline(width=4, height=3, aspect_ratio=4 / 3, dtype=torch.float32), original(width=4, height=3, aspect_ratio=4 / 3, dtype=torch.float32))
    handle_a.remove()
    gc.collect()
    assert module.normalized_view_plane_uv is trampoline  # net_b still uses it
    outputs(net_b, images)
    handle_b.remove()
    gc.collect()
    assert module.normalized_view_plane_uv is original


# ---------------------------------------------------------------------------------------------
# Builders
# ---------------------------------------------------------------------------------------------


def _save(state: dict, path):
    from safetensors.torch import save_file

    save_file({key: value.detach().clone().contiguous() for key, value in state.items()}, str(path))
    return path


@pytest.mark.parametrize("name", ["vggt-1b", "pi3", "pi3x"])
def test_load_backbone_strict(name, tmp_path, monkeypatch):
    kind = {"vggt-1b": "vggt", "pi3": "pi3", "pi3x": "pi3x"}[name]
    source = make(kind, seed=1)
    if kind == "vggt":
        monkeypatch.setattr(vggt_patch, "build_network", lambda: make(kind))
    else:
        monkeypatch.setattr(pi3_patch, "build_network", lambda which: make(which))
    assert name in rt.available_backbones()
    path = _save(source.state_dict(), tmp_path / "w.safetensors")
    loaded = rt.load_backbone(name, path)
    assert not loaded.training
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in source.state_dict().items())
    with pytest.raises(WeightsError, match="unexpected keys"):
        rt.load_backbone(name, _save(source.state_dict() | {"extra.weight": torch.zeros(1)}, tmp_path / "x.safetensors"))
    with pytest.raises(WeightsError, match="never downloads"):
        rt.load_backbone(name)
    with pytest.raises(WeightsError, match="no such weight file"):
        rt.load_backbone(name, tmp_path / "missing.safetensors")


def test_pi3x_checkpoint_without_conditioning_branches(tmp_path, monkeypatch):
    source = make("pi3x", seed=1)
    source.disable_multimodal(free_cuda_cache=False)
    monkeypatch.setattr(pi3_patch, "build_network", lambda which: make(which))
    loaded = rt.load_backbone("pi3x", _save(source.state_dict(), tmp_path / "w.safetensors"))
    assert not hasattr(loaded, "ray_embed") and not loaded.use_multimodal
    assert loaded.state_dict().keys() == source.state_dict().keys()


@pytest.mark.parametrize("name, module_name, hint", [("vggt-1b", "vggt.models.vggt", "facebookresearch/vggt"), ("pi3", "pi3.models.pi3", "yyfz/Pi3"), ("pi3x", "pi3.models.pi3x", "yyfz/Pi3")])
def test_missing_upstream_package_is_a_clear_error(name, module_name, hint, tmp_path, monkeypatch):
    path = _save({"a": torch.zeros(1)}, tmp_path / "w.safetensors")
    monkeypatch.setitem(sys.modules, module_name, None)  # makes the import fail
    with pytest.raises(MissingDependencyError, match=hint):
        rt.load_backbone(name, path)
