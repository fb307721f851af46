"""Tests of the VGGT-Omega stub package in tests/stubs (see docs/stubs.md): its signatures
against the ones recorded from the real code, structure and outputs, RoPE numerics, the by-name
imported dense head, deterministic initialisation. Skipped where the real package is installed."""

from __future__ import annotations

import ast
import importlib
import inspect
import math

import pytest
import torch

from tests.stub_imports import GRID, stub

#: Signatures of the real code at facebookresearch/vggt-omega 39a0cb8 (docs/stubs.md), read from
#: its source with ``ast``: "module:qualified name" -> (parameter, kind, default source), kind P
#: (positional or keyword), K (keyword only), * / ** (variadic); ``self`` left out.
VGGT_OMEGA_SIGNATURES = {
    "vggt_omega.models.vggt_omega:VGGTOmega.__init__": (
        ("patch_size", "P", "16"),
        ("embed_dim", "P", "1024"),
        ("enable_camera", "P", "True"),
        ("enable_depth", "P", "True"),
        ("enable_alignment", "P", "False"),
    ),
    "vggt_omega.models.vggt_omega:VGGTOmega.forward": (("images", "P", None),),
    "vggt_omega.models.aggregator:Aggregator.__init__": (
        ("patch_size", "P", "16"),
        ("embed_dim", "P", "1024"),
        ("depth", "P", "24"),
        ("num_heads", "P", "16"),
        ("mlp_ratio", "P", "4.0"),
        ("num_register_tokens", "P", "16"),
        ("register_attention_block_indices", "P", "[2, 6, 9, 14, 20]"),
        ("cached_layer_indices", "P", "(4, 11, 17, 23)"),
    ),
    "vggt_omega.models.aggregator:Aggregator.forward": (("images", "P", None),),
    "vggt_omega.models.aggregator:Aggregator._run_frame_block": (
        ("tokens", "P", None),
        ("batch_size", "P", None),
        ("num_frames", "P", None),
        ("num_tokens", "P", None),
        ("embed_dim", "P", None),
        ("block_idx", "P", None),
        ("rope_sincos", "P", None),
    ),
    "vggt_omega.models.aggregator:Aggregator._run_inter_frame_attention_block": (
        ("tokens", "P", None),
        ("batch_size", "P", None),
        ("num_frames", "P", None),
        ("num_tokens", "P", None),
        ("embed_dim", "P", None),
        ("block_idx", "P", None),
        ("attention_type", "P", None),
    ),
    "vggt_omega.models.aggregator:_build_patch_embed": (
        ("patch_size", "P", None),
        ("embed_dim", "P", None),
    ),
    "vggt_omega.models.aggregator:slice_expand_and_flatten": (
        ("token_tensor", "P", None),
        ("batch_size", "P", None),
        ("num_frames", "P", None),
    ),
    "vggt_omega.models.layers.rope_position_encoding:RopePositionEmbedding.__init__": (
        ("embed_dim", "P", None),
        ("num_heads", "K", None),
        ("base", "K", "100.0"),
        ("min_period", "K", "None"),
        ("max_period", "K", "None"),
        ("normalize_coords", "K", "'separate'"),
        ("shift_coords", "K", "None"),
        ("jitter_coords", "K", "None"),
        ("rescale_coords", "K", "None"),
        ("dtype", "K", "None"),
        ("device", "K", "None"),
    ),
    "vggt_omega.models.layers.rope_position_encoding:RopePositionEmbedding.forward": (
        ("H", "K", None),
        ("W", "K", None),
    ),
    "vggt_omega.models.layers.rope_position_encoding:RopePositionEmbedding._init_weights": (),
    "vggt_omega.models.layers.patch_embed:PatchEmbed.__init__": (
        ("img_size", "P", "224"),
        ("patch_size", "P", "16"),
        ("in_chans", "P", "3"),
        ("embed_dim", "P", "768"),
        ("norm_layer", "P", "None"),
        ("flatten_embedding", "P", "True"),
    ),
    "vggt_omega.models.layers.patch_embed:PatchEmbed.forward": (("x", "P", None),),
    "vggt_omega.models.layers.patch_embed:make_2tuple": (("x", "P", None),),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.__init__": (
        ("img_size", "K", "224"),
        ("patch_size", "K", "16"),
        ("in_chans", "K", "3"),
        ("pos_embed_rope_base", "K", "100.0"),
        ("pos_embed_rope_min_period", "K", "None"),
        ("pos_embed_rope_max_period", "K", "None"),
        ("pos_embed_rope_normalize_coords", "K", "'separate'"),
        ("pos_embed_rope_shift_coords", "K", "None"),
        ("pos_embed_rope_jitter_coords", "K", "None"),
        ("pos_embed_rope_rescale_coords", "K", "None"),
        ("pos_embed_rope_dtype", "K", "'bf16'"),
        ("embed_dim", "K", "768"),
        ("depth", "K", "12"),
        ("num_heads", "K", "12"),
        ("ffn_ratio", "K", "4.0"),
        ("qkv_bias", "K", "True"),
        ("drop_path_rate", "K", "0.0"),
        ("layerscale_init", "K", "None"),
        ("norm_layer", "K", "'layernorm'"),
        ("ffn_layer", "K", "'mlp'"),
        ("ffn_bias", "K", "True"),
        ("proj_bias", "K", "True"),
        ("n_storage_tokens", "K", "0"),
        ("mask_k_bias", "K", "False"),
        ("untie_cls_and_patch_norms", "K", "False"),
        ("untie_global_and_local_cls_norm", "K", "False"),
        ("device", "K", "None"),
        ("ignored_kwargs", "**", None),
    ),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.init_weights": (),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.prepare_tokens_with_masks": (
        ("x", "P", None),
        ("masks", "P", "None"),
    ),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.forward_features": (
        ("x", "P", None),
        ("masks", "P", "None"),
    ),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.forward_features_list": (
        ("x_list", "P", None),
        ("masks_list", "P", None),
    ),
    "vggt_omega.models.layers.vision_transformer:DinoVisionTransformer.forward": (
        ("args", "*", None),
        ("is_training", "K", "True"),
        ("kwargs", "**", None),
    ),
    "vggt_omega.models.layers.attention:SelfAttention.__init__": (
        ("dim", "P", None),
        ("num_heads", "P", "8"),
        ("qkv_bias", "P", "False"),
        ("proj_bias", "P", "True"),
        ("attn_drop", "P", "0.0"),
        ("proj_drop", "P", "0.0"),
        ("mask_k_bias", "P", "False"),
        ("use_qk_norm", "P", "False"),
        ("device", "P", "None"),
    ),
    "vggt_omega.models.layers.attention:SelfAttention.apply_rope": (
        ("q", "P", None),
        ("k", "P", None),
        ("rope", "P", None),
    ),
    "vggt_omega.models.layers.attention:SelfAttention.forward": (
        ("x", "P", None),
        ("attn_bias", "P", "None"),
        ("rope", "P", "None"),
    ),
    "vggt_omega.models.layers.attention:SelfAttention.compute_attention": (
        ("qkv", "P", None),
        ("attn_bias", "P", "None"),
        ("rope", "P", "None"),
    ),
    "vggt_omega.models.layers.attention:LinearKMaskedBias.forward": (("input", "P", None),),
    "vggt_omega.models.layers.attention:rope_apply": (
        ("x", "P", None),
        ("sin", "P", None),
        ("cos", "P", None),
    ),
    "vggt_omega.models.layers.attention:rope_rotate_half": (("x", "P", None),),
    "vggt_omega.models.layers.block:SelfAttentionBlock.__init__": (
        ("dim", "P", None),
        ("num_heads", "P", None),
        ("ffn_ratio", "P", "4.0"),
        ("qkv_bias", "P", "False"),
        ("proj_bias", "P", "True"),
        ("ffn_bias", "P", "True"),
        ("drop", "P", "0.0"),
        ("attn_drop", "P", "0.0"),
        ("init_values", "P", "None"),
        ("drop_path", "P", "0.0"),
        ("act_layer", "P", "nn.GELU"),
        ("norm_layer", "P", "nn.LayerNorm"),
        ("attn_class", "P", "SelfAttention"),
        ("ffn_layer", "P", "Mlp"),
        ("mask_k_bias", "P", "False"),
        ("use_qk_norm", "P", "False"),
        ("device", "P", "None"),
    ),
    "vggt_omega.models.layers.block:SelfAttentionBlock.forward": (
        ("x_or_x_list", "P", None),
        ("rope_or_rope_list", "P", "None"),
    ),
    "vggt_omega.models.layers.ffn_layers:Mlp.__init__": (
        ("in_features", "P", None),
        ("hidden_features", "P", "None"),
        ("out_features", "P", "None"),
        ("act_layer", "P", "nn.GELU"),
        ("drop", "P", "0.0"),
        ("bias", "P", "True"),
        ("device", "P", "None"),
    ),
    "vggt_omega.models.layers.ffn_layers:Mlp.forward": (("x", "P", None),),
    "vggt_omega.models.heads.dense_head:DenseHead.__init__": (
        ("dim_in", "P", "2048"),
        ("patch_size", "P", "16"),
        ("features", "P", "256"),
        ("out_channels", "P", "[256, 512, 1024, 1024]"),
        ("intermediate_layer_idx", "P", "[4, 11, 17, 23]"),
    ),
    "vggt_omega.models.heads.dense_head:DenseHead.forward": (
        ("aggregated_tokens_list", "P", None),
        ("images", "P", None),
        ("patch_token_start", "P", None),
        ("frames_chunk_size", "P", "8"),
    ),
    "vggt_omega.models.heads.dense_head:DenseHead._forward_impl": (
        ("aggregated_tokens_list", "P", None),
        ("images", "P", None),
        ("patch_token_start", "P", None),
        ("frames_start_idx", "P", "None"),
        ("frames_end_idx", "P", "None"),
    ),
    "vggt_omega.models.heads.dense_head:DenseHead._apply_pos_embed": (
        ("x", "P", None),
        ("width", "P", None),
        ("height", "P", None),
        ("ratio", "P", "0.1"),
    ),
    "vggt_omega.models.heads.dense_head:DenseHead.scratch_forward": (("features", "P", None),),
    "vggt_omega.models.heads.dense_head:custom_interpolate": (
        ("x", "P", None),
        ("size", "P", "None"),
        ("scale_factor", "P", "None"),
        ("mode", "P", "'bilinear'"),
        ("align_corners", "P", "True"),
    ),
    "vggt_omega.models.heads.camera_head:CameraHead.__init__": (("dim_in", "P", "2048"),),
    "vggt_omega.models.heads.camera_head:CameraHead.forward": (
        ("aggregated_tokens_list", "P", None),
        ("patch_token_start", "P", None),
    ),
    "vggt_omega.models.heads.text_alignment_head:TextAlignmentHead.__init__": (
        ("dim_in", "P", "2048"),
    ),
    "vggt_omega.models.heads.text_alignment_head:TextAlignmentHead.forward": (
        ("aggregated_tokens_list", "P", None),
        ("patch_token_start", "P", None),
    ),
    "vggt_omega.models.heads.utils:position_grid_to_embed": (
        ("pos_grid", "P", None),
        ("embed_dim", "P", None),
        ("omega_0", "P", "100"),
    ),
    "vggt_omega.models.heads.utils:make_sincos_pos_embed": (
        ("embed_dim", "P", None),
        ("pos", "P", None),
        ("omega_0", "P", "100"),
    ),
    "vggt_omega.models.heads.utils:create_uv_grid": (
        ("width", "P", None),
        ("height", "P", None),
        ("aspect_ratio", "P", "None"),
        ("dtype", "P", "None"),
        ("device", "P", "None"),
    ),
    "vggt_omega.utils.pose_enc:encoding_to_camera": (
        ("pose_encoding", "P", None),
        ("image_size_hw", "P", None),
        ("build_intrinsics", "P", "True"),
    ),
    "vggt_omega.utils.rotation:quat_to_mat": (("quaternions", "P", None),),
}
_KIND = {
    inspect.Parameter.POSITIONAL_OR_KEYWORD: "P",
    inspect.Parameter.POSITIONAL_ONLY: "P",
    inspect.Parameter.KEYWORD_ONLY: "K",
    inspect.Parameter.VAR_POSITIONAL: "*",
    inspect.Parameter.VAR_KEYWORD: "**",
}


@pytest.fixture(scope="module")
def vggt_omega_pkg():
    return stub("vggt_omega")


def _stub_signature(where: str) -> tuple:
    module_name, qualified = where.split(":")
    module = importlib.import_module(module_name)
    function = module
    for part in qualified.split("."):
        function = getattr(function, part)
    parameters = list(inspect.signature(function).parameters.values())
    if parameters and parameters[0].name == "self":
        parameters = parameters[1:]
    return module, parameters


@pytest.mark.parametrize("where", sorted(VGGT_OMEGA_SIGNATURES))
def test_vggt_omega_signatures_match_upstream(vggt_omega_pkg, where):
    """Names, kinds and defaults of every mirrored function equal the recorded upstream ones."""
    module, parameters = _stub_signature(where)
    recorded = VGGT_OMEGA_SIGNATURES[where]
    assert [(p.name, _KIND[p.kind]) for p in parameters] == [(n, k) for n, k, _ in recorded]
    for parameter, (name, _, default) in zip(parameters, recorded, strict=True):
        if default is None:
            assert parameter.default is inspect.Parameter.empty, name
            continue
        try:
            expected = ast.literal_eval(default)
        except ValueError:  # a name such as nn.GELU, resolved in the stub module
            expected = eval(default, vars(module))  # noqa: S307 - recorded test data
        assert parameter.default == expected, name


def test_vggt_omega_structure_and_outputs(vggt_omega_pkg):
    from vggt_omega.models.layers.rope_position_encoding import RopePositionEmbedding
    from vggt_omega.models.vggt_omega import VGGTOmega

    model = VGGTOmega(embed_dim=64).eval()
    aggregator = model.aggregator
    assert type(aggregator.patch_embed).__name__ == "DinoVisionTransformer"
    assert not hasattr(aggregator.patch_embed, "pos_embed")  # RoPE only, as upstream
    ropes = [name for name, m in model.named_modules() if isinstance(m, RopePositionEmbedding)]
    assert ropes == ["aggregator.patch_embed.rope_embed", "aggregator.rope_embed"]
    assert aggregator.patch_embed.patch_embed.flatten_embedding is False
    assert aggregator.patch_token_start == 1 + aggregator.register_token.shape[2]
    assert {"aggregator.rope_embed.periods", "aggregator.patch_embed.rope_embed.periods"} <= set(
        model.state_dict()
    )
    images = torch.rand(1, 2, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        output = model(images)
    assert output["pose_enc"].shape == (1, 2, 9)
    assert output["depth"].shape == (1, 2, 32, 48, 1) and bool((output["depth"] > 0).all())
    assert output["depth_conf"].shape == (1, 2, 32, 48) and bool((output["depth_conf"] > 1).all())
    start = aggregator.patch_token_start
    assert output["camera_and_register_tokens"].shape == (1, 2, start, 128)
    assert torch.equal(model(images[0])["depth"], output["depth"])  # (S, 3, H, W) input


@pytest.mark.parametrize("mode", ["max", "min", "separate"])
def test_vggt_omega_rope_numerics(vggt_omega_pkg, mode):
    """(sin, cos) follow upstream's formula: centre coordinates in [-1, 1], y then x, tiled."""
    from vggt_omega.models.layers.rope_position_encoding import RopePositionEmbedding

    rope = RopePositionEmbedding(64, num_heads=4, base=100, normalize_coords=mode)
    sin, cos = rope(H=2, W=3)
    assert sin.shape == cos.shape == (6, 16)
    norm = {"max": (3, 3), "min": (2, 2), "separate": (2, 3)}[mode]
    periods = 100.0 ** (2 * torch.arange(4) / 8)
    assert torch.allclose(rope.periods, periods)
    y = (2 * (GRID[:, 0] + 0.5) / norm[0] - 1)[:, None] / periods
    x = (2 * (GRID[:, 1] + 0.5) / norm[1] - 1)[:, None] / periods
    angles = (2 * math.pi * torch.cat([y, x], dim=1)).tile(2)
    assert torch.allclose(sin, angles.sin(), atol=1e-6) and torch.allclose(
        cos, angles.cos(), atol=1e-6
    )


def test_vggt_omega_dense_head_uses_the_by_name_import(vggt_omega_pkg, monkeypatch):
    import vggt_omega.models.heads.dense_head as dense_head
    from vggt_omega.models.vggt_omega import VGGTOmega

    model = VGGTOmega(embed_dim=64).eval()
    calls = []
    original = dense_head.position_grid_to_embed
    monkeypatch.setattr(
        dense_head,
        "position_grid_to_embed",
        lambda grid, dim: calls.append((tuple(grid.shape), dim)) or original(grid, dim),
    )
    with torch.no_grad():
        model(torch.rand(1, 1, 3, 32, 48))
    # four projections at the 2 x 3 patch grid, then the fused feature at 1/4 scale
    assert [shape[:2] for shape, _ in calls] == [(2, 3)] * 4 + [(8, 12)]


def test_vggt_omega_deterministic_init_and_sizes(vggt_omega_pkg):
    from vggt_omega import _stub_config
    from vggt_omega.models.vggt_omega import VGGTOmega

    state = torch.random.get_rng_state()
    first, second = VGGTOmega(embed_dim=64).state_dict(), VGGTOmega(embed_dim=64).state_dict()
    assert torch.equal(torch.random.get_rng_state(), state)
    assert all(torch.equal(first[k], second[k]) for k in first)
    with _stub_config.stub_sizes(aggregator_depth=3, cached_layer_indices=(0, 2)):
        model = VGGTOmega(embed_dim=32, enable_camera=False)
    assert len(model.aggregator.frame_blocks) == 3 and model.camera_head is None
