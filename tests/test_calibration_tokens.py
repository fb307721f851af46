"""Calibration-token baseline: parameter count, the tokens reach the output, disabled() and
remove() give the vanilla model bit for bit, gradients reach only the tokens, adapt fits them.

DA3 (its tiny network), and VGGT / Pi3 / Pi3X (the stub packages' tiny recipes of
``tests/backbones.py``, or tiny real networks when the upstream packages are importable)."""

from __future__ import annotations

import copy
import importlib
import json

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.baselines import CalibrationTokens, inject_calibration_tokens
from raytun3r_plugin.errors import (
    AdapterError,
    AlreadyAppliedError,
    InputError,
    UnsupportedUpstreamError,
)
from raytun3r_plugin.registry import spec_for
from tests.helpers import (
    assert_same_snapshot,
    fisheye,
    max_relative_difference,
    outputs,
    snapshot,
)


@pytest.fixture
def net():
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    return build_tiny_network(seed=0)


def _depth(model, images):
    with torch.no_grad():
        return rt.predict(model, images).depth


def test_da3_small_has_the_papers_parameter_count():
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_network

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
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.train import adapt
    from tests.test_losses import room_sequence

    camera = fisheye(84, 70, 190.0)
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    config = AdaptConfig.from_recipe(
        "matches",
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


# ---------------------------------------------------------------------------------------------
# VGGT (aggregator: frame then global blocks), Pi3 and Pi3X (decoder BlockRope layers)
# ---------------------------------------------------------------------------------------------

KINDS = ("vggt", "pi3", "pi3x")
#: What each family's tokens cover, in token order, at the tiny sizes (stub: VGGT aggregator
#: depth 4, Pi3 decoder depth 4; the tiny real networks: 2 and 2).
T = 4


@pytest.fixture(params=KINDS)
def kind(request):
    pytest.importorskip("vggt" if request.param == "vggt" else "pi3")
    return request.param


@pytest.fixture
def model(kind):
    from tests.backbones import make

    return make(kind)


@pytest.fixture(scope="module")
def views():
    from tests.backbones import H, W

    return torch.rand(1, 3, 3, H, W, generator=torch.Generator().manual_seed(1))  # 3 views


def _block_lists(model):
    if hasattr(model, "aggregator"):
        depth = len(model.aggregator.frame_blocks)
        return (("aggregator.frame_blocks", depth), ("aggregator.global_blocks", depth))
    return (("decoder", len(model.decoder)),)


def _attention_blocks(model):
    """(block, layout) of every covered block, in token order."""
    if hasattr(model, "aggregator"):
        frame = [(block, "frame") for block in model.aggregator.frame_blocks]
        return frame + [(block, "global") for block in model.aggregator.global_blocks]
    return [(block, "frame" if i % 2 == 0 else "global") for i, block in enumerate(model.decoder)]


def _randomise(tokens, seed=0):
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        tokens.tokens.copy_(torch.randn(tokens.tokens.shape, generator=generator))


def test_parameter_count_is_blocks_x_t_x_c(model, kind):
    info = spec_for(model)[0].describe(model)
    lists = _block_lists(model)
    blocks = sum(length for _, length in lists)
    parameters = sum(p.numel() for p in model.parameters())
    with inject_calibration_tokens(model) as handle:
        assert handle.tokens.tokens.shape == (blocks, T, info.embed_dim)
        assert handle.tokens.num_parameters() == blocks * T * info.embed_dim
        assert handle.tokens.block_lists == lists
        assert sum(p.numel() for p in model.parameters()) == parameters, "not model parameters"
    from tests.backbones import is_stub

    if is_stub(kind):  # the documented tiny recipes: VGGT 2 x 4 blocks, C = 64; Pi3 4, C = 32
        assert handle.tokens.num_parameters() == {"vggt": 2048, "pi3": 512, "pi3x": 512}[kind]


@pytest.mark.parametrize("family", ["vggt", "pi3"])
def test_full_size_block_counts(family):
    """Upstream depths (VGGT aggregator 24 + 24, Pi3 decoder 36) at a small width: the token
    count is blocks x t x C, 196,608 / 147,456 at C = 1024."""
    from tests.backbones import is_stub

    pytest.importorskip(family)
    if not is_stub(family):
        pytest.skip("sizes of the stub packages")
    stub = importlib.import_module(f"{family}._stub_config")
    if family == "vggt":
        from vggt.models.vggt import VGGT

        with stub.stub_sizes(aggregator_depth=24, dpt_intermediate_layer_idx=(4, 11, 17, 23)):
            model = VGGT(img_size=70, patch_size=14, embed_dim=64, enable_track=False)
        blocks, full = 48, 196_608
    else:
        from pi3.models.pi3 import Pi3

        with stub.stub_sizes(decoder_depth=36):
            model = Pi3()
        blocks, full = 36, 147_456
    width = spec_for(model)[0].describe(model).embed_dim
    with inject_calibration_tokens(model) as handle:
        assert handle.tokens.tokens.shape[0] == blocks
        assert handle.tokens.num_parameters() == blocks * T * width
    assert blocks * T * 1024 == full


def test_vggt_pi3_tokens_change_the_output_and_removal_is_exact(model, views):
    before = snapshot(model)
    reference = outputs(model, views)
    handle = inject_calibration_tokens(model)
    changed = outputs(model, views)
    assert all(changed[k].shape == reference[k].shape for k in reference)
    # far above float noise (~1e-7); the stubs' LayerScale 0.01 keeps every block's effect small
    assert max_relative_difference(changed, reference) > 1e-4, "the tokens take part"
    with handle.disabled():
        assert all(torch.equal(outputs(model, views)[k], reference[k]) for k in reference)
    with pytest.raises(AlreadyAppliedError):
        inject_calibration_tokens(model)
    handle.remove()
    handle.remove()
    assert not handle.active
    now = outputs(model, views)
    assert all(torch.equal(now[k], reference[k]) for k in reference)
    assert_same_snapshot(model, before)  # state dict and every module's attributes
    with inject_calibration_tokens(model):  # a second injection after removal works
        pass


def test_every_block_sees_the_tokens_after_the_special_tokens(model, views):
    """Inside each covered block's attention the sequence is t longer per frame, the tokens sit
    at patch_start_idx with the special tokens' position; the blocks' outputs and what the heads
    read (VGGT: the aggregator's list, Pi3: decode's output) keep upstream's token count."""
    blocks = _attention_blocks(model)
    start = model.aggregator.patch_start_idx if hasattr(model, "aggregator") else 5
    assert start == 5

    order = {id(block.attn): i for i, (block, _) in enumerate(blocks)}

    def record(store):
        def hook(module, args, kwargs):
            pos = kwargs.get("pos", kwargs.get("xpos"))
            store.append((order[id(module)], args[0].shape, pos.clone()))

        return hook

    def run():
        attention, heads = [], []
        handles = [
            block.attn.register_forward_pre_hook(record(attention), with_kwargs=True)
            for block, _ in blocks
        ]
        if hasattr(model, "aggregator"):
            handles.append(
                model.aggregator.register_forward_hook(
                    lambda m, a, out: heads.append([tuple(x.shape) for x in out[0]])
                )
            )
        else:
            handles.append(
                model.point_decoder.register_forward_pre_hook(
                    lambda m, a, kw: heads.append((tuple(a[0].shape), tuple(kw["xpos"].shape))),
                    with_kwargs=True,
                )
            )
        try:
            outputs(model, views)
        finally:
            for hook in handles:
                hook.remove()
        return attention, heads

    vanilla, vanilla_heads = run()
    with inject_calibration_tokens(model):
        tokened, tokened_heads = run()
    assert tokened_heads == vanilla_heads
    frames = views.shape[1]
    vanilla, tokened = sorted(vanilla, key=lambda r: r[0]), sorted(tokened, key=lambda r: r[0])
    assert [r[0] for r in vanilla] == [r[0] for r in tokened] == list(range(len(blocks)))
    for (_, shape, pos), (_, wide, wide_pos), (_, layout) in zip(
        vanilla, tokened, blocks, strict=True
    ):
        per_frame = 1 if layout == "frame" else frames
        assert wide[-2] == shape[-2] + T * per_frame
        n = shape[-2] // per_frame
        grid = wide_pos.reshape(wide_pos.shape[0], per_frame, n + T, 2)
        assert torch.equal(grid[:, :, start : start + T], grid[:, :, :1].expand(-1, -1, T, -1))
        assert bool((grid[:, :, start : start + T] == 0).all()), "the special tokens' (0, 0)"
        kept = torch.cat([grid[:, :, :start], grid[:, :, start + T :]], dim=2)
        assert torch.equal(kept.reshape(pos.shape), pos)


def test_vggt_pi3_gradient_reaches_only_the_tokens(model, views):
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    with inject_calibration_tokens(model) as handle:
        _randomise(handle.tokens)
        prediction = rt.predict(model, views)
        (prediction.depth.mean() + prediction.cam_from_world.sum()).backward()
        grad = handle.tokens.tokens.grad
        assert grad is not None and bool((grad.abs().sum(dim=(1, 2)) > 0).all()), "every block"
    assert all(p.grad is None for p in model.parameters())


def test_a_copy_runs_without_the_tokens_and_apply_works_with_them(model, views):
    from tests.backbones import H, W

    reference = outputs(model, views)
    with inject_calibration_tokens(model) as handle:
        _randomise(handle.tokens)
        tokened = outputs(model, views)
        twin = copy.deepcopy(model)
        assert all(torch.equal(outputs(twin, views)[k], reference[k]) for k in reference)
        assert all(torch.equal(outputs(model, views)[k], tokened[k]) for k in tokened)
        with inject_calibration_tokens(twin, handle.tokens):  # the copy takes tokens of its own
            assert all(torch.equal(outputs(twin, views)[k], tokened[k]) for k in tokened)
        assert all(torch.equal(outputs(twin, views)[k], reference[k]) for k in reference)
        with rt.apply(model, fisheye(W, H)):
            assert all(bool(torch.isfinite(v).all()) for v in outputs(model, views).values())
    assert all(torch.equal(outputs(model, views)[k], reference[k]) for k in reference)


def test_save_and_load_record_the_backbone_and_blocks(model, views, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import save_file

    info = spec_for(model)[0].describe(model)
    lists = _block_lists(model)
    with inject_calibration_tokens(model) as handle:
        _randomise(handle.tokens)
        expected = outputs(model, views)
        path = handle.tokens.save(tmp_path / "tokens.safetensors")
    with safe_open(str(path), "pt") as file:
        metadata = file.metadata()
    assert metadata["backbone"] == info.name
    assert json.loads(metadata["blocks"]) == [list(entry) for entry in lists]
    loaded = CalibrationTokens.load(path)
    assert loaded.backbone == info.name and loaded.block_lists == lists
    with inject_calibration_tokens(model, loaded):
        now = outputs(model, views)
    assert all(torch.equal(now[k], expected[k]) for k in expected)
    blocks = sum(length for _, length in lists)
    other = CalibrationTokens(blocks, T, info.embed_dim, block_lists=(("elsewhere", blocks),))
    with pytest.raises(AdapterError, match="made for the blocks"):
        inject_calibration_tokens(model, other)
    with pytest.raises(AdapterError, match="do not fit"):
        inject_calibration_tokens(model, CalibrationTokens(blocks + 1, T, info.embed_dim))
    bad = dict(metadata, blocks=json.dumps([[lists[0][0], blocks + 1]]))
    save_file({"tokens": loaded.tokens.detach()}, str(tmp_path / "bad.safetensors"), bad)
    with pytest.raises(AdapterError, match="add up"):
        CalibrationTokens.load(tmp_path / "bad.safetensors")


def test_vggt_refuses_several_blocks_per_runner_call():
    pytest.importorskip("vggt")
    from tests.backbones import make

    model = make("vggt")
    model.aggregator.aa_block_size = 2
    with pytest.raises(UnsupportedUpstreamError, match="aa_block_size"):
        inject_calibration_tokens(model)
    assert "_process_frame_attention" not in vars(model.aggregator)


@pytest.mark.parametrize("family", ["pi3", "pi3x"])
def test_pi3_global_blocks_need_decode_for_the_frame_count(family):
    """Outside ``decode`` a global-attention block cannot tell frames apart: it refuses; a frame
    block (one frame per row) runs with its tokens."""
    pytest.importorskip("pi3")
    from tests.backbones import make

    model = make(family)
    width = model.dec_embed_dim
    x, pos = torch.rand(2, 5 + 12, width), torch.zeros(2, 5 + 12, 2, dtype=torch.long)
    with inject_calibration_tokens(model):
        assert model.decoder[0](x, xpos=pos).shape == x.shape
        with pytest.raises(InputError, match="outside decode"):
            model.decoder[1](x.reshape(1, 34, width), xpos=pos.reshape(1, 34, 2))
    assert torch.equal(
        model.decoder[1](x.reshape(1, 34, width), xpos=pos.reshape(1, 34, 2)),
        model.decoder[1].forward(x.reshape(1, 34, width), xpos=pos.reshape(1, 34, 2)),
    )


@pytest.mark.parametrize("family", ["vggt", "pi3"])
def test_adapt_fits_vggt_and_pi3_tokens(family, tmp_path):
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.train import adapt
    from tests.backbones import make
    from tests.test_losses import room_sequence

    pytest.importorskip(family)
    model = make(family)
    camera = fisheye(84, 70, 190.0)
    images, _, _ = room_sequence(camera, 5, step=0.35, yaw=0.06)
    config = AdaptConfig.from_recipe(
        "matches",
        steps=2,
        input_size=84,
        n_windows=3,
        cache_dir=str(tmp_path / "cache"),
        matcher_options={"border_px": 2},
        seed=0,
        components=[],
        lr=1e-2,
    )
    with inject_calibration_tokens(model) as handle:
        start = handle.tokens.tokens.detach().clone()
        adapter = adapt(model, camera, images, config, tune=handle.tokens, progress=False)
        moved = (handle.tokens.tokens.detach() - start).abs().sum(dim=(1, 2))
        assert bool((moved > 0).all()), "every block's tokens are fitted"
    assert adapter.is_zero()


def test_a_family_without_a_prompt_target_refuses():
    pytest.importorskip("vggt_omega")
    from tests.backbones import make

    model = make("vggt_omega")
    with pytest.raises(UnsupportedUpstreamError, match="declares no place"):
        inject_calibration_tokens(model)
