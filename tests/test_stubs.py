"""Tests of the VGGT and Pi3/Pi3X stub packages in tests/stubs (see docs/stubs.md; VGGT-Omega's:
tests/test_stubs_vggt_omega.py).

These check the parts of the stubs raytun3r's patches rely on: module paths and hook
methods, token layout and RoPE positions, integer RoPE lookups, caches, the by-name imported
grid functions, the pose encoding, output keys and shapes. They are skipped when the real
upstream packages are the ones importable (the stubs are only put on sys.path otherwise).
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import sys
import time
import types

import pytest
import torch
import torch.nn.functional as F

from tests.stub_imports import GRID, stub

H, W = 28, 42  # 2 x 3 patches of 14 px


@pytest.fixture(scope="module")
def vggt_pkg():
    return stub("vggt")


@pytest.fixture(scope="module")
def pi3_pkg():
    return stub("pi3")


@pytest.fixture
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(1))


def tiny_vggt(**kwargs):
    from vggt.models.vggt import VGGT

    kwargs.setdefault("enable_track", False)
    return VGGT(img_size=70, patch_size=14, embed_dim=64, **kwargs).eval()


def rope_positions(rope_module):
    """Record the positions every call of a RoPE module receives."""
    seen = []
    handle = rope_module.register_forward_pre_hook(lambda mod, args: seen.append(args[1].clone()))
    return seen, handle


# ----------------------------------------------------------------------------------------
# VGGT
# ----------------------------------------------------------------------------------------


def test_vggt_outputs(vggt_pkg, images):
    model = tiny_vggt()
    with torch.no_grad():
        out = model(images)
    assert set(out) == {
        "pose_enc",
        "pose_enc_list",
        "depth",
        "depth_conf",
        "world_points",
        "world_points_conf",
        "images",
    }
    assert out["pose_enc"].shape == (1, 2, 9)
    assert len(out["pose_enc_list"]) == 4
    assert out["depth"].shape == (1, 2, H, W, 1)
    assert out["depth_conf"].shape == (1, 2, H, W)
    assert out["world_points"].shape == (1, 2, H, W, 3)
    assert out["world_points_conf"].shape == (1, 2, H, W)
    assert out["images"] is not None and out["images"].shape == images.shape
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert torch.isfinite(out[key]).all(), key
    assert (out["depth"] > 0).all() and (out["depth_conf"] > 1).all()

    # (S, 3, H, W) input gets a batch dimension, as upstream
    with torch.no_grad():
        out4 = model(images[0])
    torch.testing.assert_close(out4["depth"], out["depth"])

    from vggt.utils.pose_enc import pose_encoding_to_extri_intri

    extrinsics, intrinsics = pose_encoding_to_extri_intri(out["pose_enc"], images.shape[-2:])
    assert extrinsics.shape == (1, 2, 3, 4) and intrinsics.shape == (1, 2, 3, 3)
    assert torch.isfinite(intrinsics).all() and (intrinsics[..., 0, 0] > 0).all()


def test_vggt_structure_and_hook_points(vggt_pkg):
    from vggt.heads.dpt_head import DPTHead
    from vggt.layers.patch_embed import PatchEmbed
    from vggt.layers.rope import PositionGetter, RotaryPositionEmbedding2D
    from vggt.layers.vision_transformer import DinoVisionTransformer

    model = tiny_vggt()
    agg = model.aggregator
    vit = agg.patch_embed
    assert isinstance(vit, DinoVisionTransformer)
    assert isinstance(vit.patch_embed, PatchEmbed)
    assert vit.num_register_tokens == 4
    assert vit.interpolate_offset == 0.0 and vit.interpolate_antialias is True
    assert vit.pos_embed.shape == (1, 1 + 5 * 5, 64)  # img_size 70 -> 5 x 5 table
    assert isinstance(agg.rope, RotaryPositionEmbedding2D) and agg.rope.base_frequency == 100
    assert isinstance(agg.position_getter, PositionGetter)
    assert agg.patch_start_idx == 5
    assert agg.camera_token.shape == (1, 2, 1, 64)
    assert agg.register_token.shape == (1, 2, 4, 64)
    assert all(b.attn.rope is agg.rope for b in list(agg.frame_blocks) + list(agg.global_blocks))
    assert isinstance(model.depth_head, DPTHead) and isinstance(model.point_head, DPTHead)
    assert model.track_head is None
    assert {k.split(".")[0] for k in model.state_dict()} == {
        "aggregator",
        "camera_head",
        "point_head",
        "depth_head",
    }
    with pytest.raises(AssertionError):
        vit.patch_embed(torch.rand(1, 3, 30, 42))


def test_vggt_token_layout_and_positions(vggt_pkg, images):
    model = tiny_vggt()
    agg = model.aggregator
    seen, handle = rope_positions(agg.rope)
    try:
        with torch.no_grad():
            tokens_list, patch_start_idx = agg(images)
    finally:
        handle.remove()
    P = 5 + 6
    assert patch_start_idx == 5
    assert len(tokens_list) == len(agg.frame_blocks)
    assert all(t.shape == (1, 2, P, 128) for t in tokens_list)
    frame = [p for p in seen if p.shape == (2, P, 2)]
    glob = [p for p in seen if p.shape == (1, 2 * P, 2)]
    # q and k of every frame and every global block
    assert len(frame) == len(glob) == 2 * len(agg.frame_blocks)
    expected = torch.cat([torch.zeros(5, 2, dtype=torch.long), GRID + 1])
    for p in frame:
        assert p.dtype == torch.long
        assert torch.equal(p[0], expected) and torch.equal(p[1], expected)
    for p in glob:
        assert torch.equal(p[0], expected.repeat(2, 1))
    assert list(agg.position_getter.position_cache) == [(2, 3)]
    assert (
        8,
        4,
        torch.device("cpu"),
        torch.float32,
    ) in agg.rope.frequency_cache  # head_dim 16 -> 8


def test_vggt_position_getter_returns_a_copy(vggt_pkg):
    from vggt.layers.rope import PositionGetter

    getter = PositionGetter()
    first = getter(2, 2, 3, torch.device("cpu"))
    first += 100
    again = getter(2, 2, 3, torch.device("cpu"))
    assert torch.equal(again[0], GRID) and again.shape == (2, 6, 2)


def _reference_rope(tokens, positions, base):
    half = tokens.shape[-1] // 2
    inv = 1.0 / base ** (torch.arange(0, half, 2).float() / half)
    out = []
    for axis, part in enumerate(tokens.chunk(2, dim=-1)):
        ang = positions[..., axis].float()[..., None] * inv
        ang = torch.cat([ang, ang], dim=-1)[:, None]
        rotated = torch.cat([-part[..., half // 2 :], part[..., : half // 2]], dim=-1)
        out.append(part * ang.cos() + rotated * ang.sin())
    return torch.cat(out, dim=-1)


@pytest.mark.parametrize("which", ["vggt", "pi3"])
def test_rope_integer_table_lookup(which, vggt_pkg, pi3_pkg):
    if which == "vggt":
        from vggt.layers.rope import RotaryPositionEmbedding2D

        rope = RotaryPositionEmbedding2D(frequency=100.0)
        cache = rope.frequency_cache
    else:
        from pi3.models.layers.pos_embed import RoPE2D

        rope = RoPE2D(freq=100.0)
        cache = rope.cache
    gen = torch.Generator().manual_seed(0)
    tokens = torch.randn(2, 3, 11, 16, generator=gen)
    positions = torch.randint(0, 6, (2, 11, 2), generator=gen)
    torch.testing.assert_close(rope(tokens, positions), _reference_rope(tokens, positions, 100.0))
    assert list(cache) == [(8, int(positions.max()) + 1, torch.device("cpu"), torch.float32)]
    # fractional positions are impossible: the tables are indexed with F.embedding
    with pytest.raises(RuntimeError):
        rope(tokens, positions.float() + 0.5)


def test_interpolate_pos_encoding(vggt_pkg, pi3_pkg):
    model = tiny_vggt()
    vit = model.aggregator.patch_embed
    tokens = torch.zeros(1, 1 + 25, 64)
    assert vit.interpolate_pos_encoding(tokens, 70, 70) is vit.pos_embed  # native size: unchanged
    # other size: size-based bicubic with antialias; w receives the height, h the width
    pe = vit.interpolate_pos_encoding(torch.zeros(1, 1 + 6, 64), H, W)
    grid = vit.pos_embed[:, 1:].reshape(1, 5, 5, 64).permute(0, 3, 1, 2)
    want = (
        F.interpolate(grid, size=(2, 3), mode="bicubic", antialias=True)
        .permute(0, 2, 3, 1)
        .reshape(1, 6, 64)
    )
    assert pe.shape == (1, 7, 64)
    torch.testing.assert_close(pe[:, 1:], want)
    torch.testing.assert_close(pe[:, :1], vit.pos_embed[:, :1])

    from pi3.models.pi3 import Pi3

    enc = Pi3().encoder
    assert enc.pos_embed.shape[1] == 1 + 37 * 37  # img_size 518 kept
    assert enc.interpolate_offset == 0.0 and enc.interpolate_antialias is True
    assert (
        enc.interpolate_pos_encoding(torch.zeros(1, 1370, enc.embed_dim), 518, 518) is enc.pos_embed
    )


def test_dpt_pos_embed_uses_the_by_name_import(vggt_pkg, images, monkeypatch):
    import vggt.heads.dpt_head as dpt_head
    import vggt.heads.utils as head_utils

    model = tiny_vggt()
    calls = []
    original = head_utils.create_uv_grid

    def spy(width, height, aspect_ratio=None, dtype=None, device=None):
        calls.append((width, height, aspect_ratio))
        return original(width, height, aspect_ratio=aspect_ratio, dtype=dtype, device=device)

    monkeypatch.setattr(head_utils, "create_uv_grid", spy)  # the defining module only: not seen
    with torch.no_grad():
        model(images)
    assert calls == []

    monkeypatch.setattr(dpt_head, "create_uv_grid", spy)
    with torch.no_grad():
        model(images)
    # per head: 4 patch-grid stages + once at full resolution; depth head then point head
    per_head = [(3, 2, W / H)] * 4 + [(W, H, W / H)]
    assert calls == per_head * 2

    grid = original(3, 2)
    assert grid.shape == (2, 3, 2)  # (height, width, (u, v))
    assert math.hypot(*grid[-1, -1].tolist()) < 1.0 and grid[0, 0, 0] < 0 < grid[0, -1, 0]


def test_pose_encoding_round_trip(vggt_pkg):
    from vggt.utils.pose_enc import extri_intri_to_pose_encoding, pose_encoding_to_extri_intri
    from vggt.utils.rotation import mat_to_quat, quat_to_mat

    gen = torch.Generator().manual_seed(0)
    quat = F.normalize(torch.randn(2, 3, 4, generator=gen), dim=-1)
    quat = torch.where(quat[..., 3:] < 0, -quat, quat)
    extrinsics = torch.cat([quat_to_mat(quat), torch.randn(2, 3, 3, 1, generator=gen)], dim=-1)
    size_hw = (28, 42)
    intrinsics = torch.zeros(2, 3, 3, 3)
    intrinsics[..., 0, 0] = 20 + 30 * torch.rand(2, 3, generator=gen)
    intrinsics[..., 1, 1] = 20 + 30 * torch.rand(2, 3, generator=gen)
    intrinsics[..., 0, 2], intrinsics[..., 1, 2], intrinsics[..., 2, 2] = 21.0, 14.0, 1.0

    enc = extri_intri_to_pose_encoding(extrinsics, intrinsics, image_size_hw=size_hw)
    assert enc.shape == (2, 3, 9)
    torch.testing.assert_close(enc[..., 3:7], quat)
    ext2, intr2 = pose_encoding_to_extri_intri(enc, image_size_hw=size_hw)
    torch.testing.assert_close(ext2, extrinsics)
    torch.testing.assert_close(intr2, intrinsics)
    ext3, none = pose_encoding_to_extri_intri(enc, build_intrinsics=False)
    assert none is None
    torch.testing.assert_close(ext3, extrinsics)

    # conventions: xyzw (scalar last), w >= 0; 90 degrees about z; 180 degrees about x
    rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s = math.sqrt(0.5)
    torch.testing.assert_close(mat_to_quat(rz), torch.tensor([0.0, 0.0, s, s]))
    torch.testing.assert_close(
        mat_to_quat(torch.diag(torch.tensor([1.0, -1.0, -1.0]))), torch.tensor([1.0, 0, 0, 0])
    )
    rotations = quat_to_mat(quat)
    torch.testing.assert_close(quat_to_mat(mat_to_quat(rotations)), rotations)


def test_vggt_training_mode_gradients(vggt_pkg, images):
    model = tiny_vggt().train()
    out = model(images)  # aggregator and DINO blocks run under torch.utils.checkpoint
    assert "images" not in out
    (out["depth"].mean() + out["world_points"].mean() + out["pose_enc"].mean()).backward()
    grad = model.aggregator.patch_embed.pos_embed.grad
    assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_vggt_deterministic_init_and_sizes(vggt_pkg):
    from vggt import _stub_config

    state = torch.random.get_rng_state()
    a, b = tiny_vggt(), tiny_vggt()
    assert torch.equal(state, torch.random.get_rng_state())  # global RNG untouched
    sa, sb = a.state_dict(), b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    with _stub_config.stub_sizes(aggregator_depth=2, dpt_intermediate_layer_idx=(0, 0, 1, 1)):
        small = tiny_vggt(enable_track=True)
    assert len(small.aggregator.frame_blocks) == 2 and small.track_head is not None
    assert len(tiny_vggt().aggregator.frame_blocks) == _stub_config.SIZES.aggregator_depth


# ----------------------------------------------------------------------------------------
# Pi3 / Pi3X
# ----------------------------------------------------------------------------------------


def _check_pi3_outputs(out, B=1, N=2):
    assert out["points"].shape == (B, N, H, W, 3)
    assert out["local_points"].shape == (B, N, H, W, 3)
    assert out["conf"].shape == (B, N, H, W, 1)
    assert out["camera_poses"].shape == (B, N, 4, 4)
    for key, value in out.items():
        assert torch.isfinite(value).all(), key
    assert (out["local_points"][..., 2] > 0).all()
    poses = out["camera_poses"]
    rot = poses[..., :3, :3]
    torch.testing.assert_close(
        rot @ rot.transpose(-1, -2), torch.eye(3).expand_as(rot), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(B, N), atol=1e-5, rtol=0)
    torch.testing.assert_close(poses[..., 3, :], torch.tensor([0.0, 0, 0, 1]).expand(B, N, 4))
    world = (
        torch.einsum("bnij,bnhwj->bnhwi", rot, out["local_points"]) + poses[..., None, None, :3, 3]
    )
    torch.testing.assert_close(world, out["points"], atol=1e-5, rtol=1e-5)


def test_pi3_outputs_and_structure(pi3_pkg, images):
    from pi3.models.dinov2.layers.patch_embed import PatchEmbed
    from pi3.models.dinov2.models.vision_transformer import DinoVisionTransformer
    from pi3.models.layers.attention import FlashAttentionRope
    from pi3.models.layers.block import BlockRope
    from pi3.models.layers.pos_embed import PositionGetter, RoPE2D
    from pi3.models.layers.transformer_head import LinearPts3d, TransformerDecoder
    from pi3.models.pi3 import Pi3

    model = Pi3().eval()
    with torch.no_grad():
        out = model(images)
    assert set(out) == {"points", "local_points", "conf", "camera_poses"}
    _check_pi3_outputs(out)

    assert isinstance(model.encoder, DinoVisionTransformer) and isinstance(
        model.encoder.patch_embed, PatchEmbed
    )
    assert not hasattr(model.encoder, "mask_token")
    assert model.encoder.num_register_tokens == 4
    assert isinstance(model.rope, RoPE2D) and model.rope.base == 100.0
    assert isinstance(model.position_getter, PositionGetter)
    assert model.patch_start_idx == 5 and model.register_token.shape == (
        1,
        1,
        5,
        model.dec_embed_dim,
    )
    assert all(
        isinstance(b, BlockRope) and isinstance(b.attn, FlashAttentionRope) for b in model.decoder
    )
    assert all(b.attn.rope is model.rope for b in model.decoder)
    assert isinstance(model.point_decoder, TransformerDecoder) and isinstance(
        model.point_head, LinearPts3d
    )
    assert all(b.attn.rope is model.rope for b in model.point_decoder.blocks)
    assert all(b.attn.rope is model.rope for b in model.camera_decoder.blocks)
    conf_rope = model.conf_decoder.blocks[0].attn.rope
    assert isinstance(conf_rope, RoPE2D) and conf_rope is not model.rope  # deepcopy
    assert set(model.rope.cache) and set(conf_rope.cache)  # each instance has its own cache
    assert {k.split(".")[0] for k in model.state_dict()} == {
        "encoder",
        "decoder",
        "register_token",
        "point_decoder",
        "point_head",
        "conf_decoder",
        "conf_head",
        "camera_decoder",
        "camera_head",
        "image_mean",
        "image_std",
    }
    # encoder call as in Pi3.forward: a feature dict only with is_training=True
    feats = model.encoder(torch.rand(2, 3, H, W), is_training=True)
    assert feats["x_norm_patchtokens"].shape == (2, 6, model.encoder.embed_dim)


def test_pi3_token_layout_and_positions(pi3_pkg, images):
    from pi3.models.pi3 import Pi3

    model = Pi3().eval()
    seen, handle = rope_positions(model.rope)
    try:
        with torch.no_grad():
            model(images)
    finally:
        handle.remove()
    P = 5 + 6
    expected = torch.cat([torch.zeros(5, 2, dtype=torch.long), GRID + 1])
    frame = [p for p in seen if p.shape == (2, P, 2)]
    glob = [p for p in seen if p.shape == (1, 2 * P, 2)]
    n_dec = len(model.decoder)
    assert len(glob) == 2 * (n_dec // 2)
    # decoder frame blocks + point and camera decoders (the conf decoder has its own RoPE)
    n_head = len(model.point_decoder.blocks) + len(model.camera_decoder.blocks)
    assert len(frame) == 2 * (n_dec // 2 + n_head)
    for p in frame:
        assert p.dtype == torch.long and torch.equal(p[0], expected) and torch.equal(p[1], expected)
    for p in glob:
        assert torch.equal(p[0], expected.repeat(2, 1))
    assert list(model.position_getter.cache_positions) == [(2, 3)]


def test_pi3_curope_is_used_when_importable(pi3_pkg, monkeypatch):
    """Upstream structure: pos_embed tries ``from models.curope import cuRoPE2D`` first."""
    import pi3.models.layers.pos_embed as pos_embed

    class cuRoPE2D(torch.nn.Module):  # noqa: N801 (upstream name)
        def __init__(self, freq=100.0, F0=1.0):
            super().__init__()

    models_pkg = types.ModuleType("models")
    models_pkg.__path__ = []
    curope = types.ModuleType("models.curope")
    curope.cuRoPE2D = cuRoPE2D
    models_pkg.curope = curope
    monkeypatch.setitem(sys.modules, "models", models_pkg)
    monkeypatch.setitem(sys.modules, "models.curope", curope)
    # load a private copy so the imported pi3 modules keep their classes
    spec = importlib.util.spec_from_file_location("_pi3_pos_embed_with_curope", pos_embed.__file__)
    copy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(copy)
    assert copy.RoPE2D is cuRoPE2D
    assert pos_embed.RoPE2D is not cuRoPE2D and hasattr(pos_embed.RoPE2D, "apply_rope1d")


def test_pi3x_outputs_structure_and_conditioning(pi3_pkg, images, monkeypatch):
    import pi3.models.layers.conv_head as conv_head
    from pi3.models.dinov2.layers.patch_embed import PatchEmbed
    from pi3.models.layers.conv_head import ConvHead
    from pi3.models.pi3x import Pi3X

    assert pi3_pkg.Pi3X is Pi3X
    model = Pi3X().eval()
    assert isinstance(model.point_head, ConvHead) and isinstance(model.conf_head, ConvHead)
    assert type(model.ray_embed) is PatchEmbed and model.ray_embed.proj.in_channels == 2
    assert (
        type(model.depth_encoder.patch_embed) is PatchEmbed
        and model.depth_encoder.patch_embed.proj.in_channels == 2
    )
    assert (
        type(model.encoder.patch_embed) is PatchEmbed
        and model.encoder.patch_embed.proj.in_channels == 3
    )
    assert model.depth_encoder.pos_embed is not model.encoder.pos_embed
    assert (
        model.conf_decoder.blocks[0].attn.rope is model.rope
    )  # Pi3X: built separately, shared RoPE
    assert model.metric_decoder.blocks[0].cross_attn.rope is model.rope
    assert model.patch_start_idx == 5 and model.register_token.shape == (
        1,
        1,
        5,
        model.dec_embed_dim,
    )

    calls = []
    original = conv_head.normalized_view_plane_uv

    def spy(width, height, aspect_ratio=None, dtype=None, device=None):
        calls.append((height, width, aspect_ratio))
        return original(width, height, aspect_ratio=aspect_ratio, dtype=dtype, device=device)

    monkeypatch.setattr(conv_head, "normalized_view_plane_uv", spy)
    seen, handle = rope_positions(model.rope)
    try:
        with torch.no_grad():
            base = model(images)
    finally:
        handle.remove()
    assert set(base) == {"points", "local_points", "rays", "conf", "camera_poses", "metric"}
    assert base["rays"].shape == (1, 2, H, W, 3) and base["metric"].shape == (1,)
    metric = base["metric"].view(1, 1, 1, 1, 1)
    _check_pi3_outputs(  # outputs are metric-scaled; undo the scale for the geometric checks
        {
            "points": base["points"] / metric,
            "local_points": base["local_points"] / metric,
            "conf": base["conf"],
            "camera_poses": _unscale_poses(base["camera_poses"], base["metric"]),
        }
    )
    torch.testing.assert_close(base["rays"].norm(dim=-1), torch.ones(1, 2, H, W))
    # uv channels: 3 upsample stages (patch grid, x2, x4) + full resolution, point and conf heads
    per_head = [(2, 3, W / H), (4, 6, W / H), (8, 12, W / H), (H, W, W / H)]
    assert calls == per_head * 2
    # metric decoder: the query token sits at (0, 0), keys carry every position
    cross = [p for p in seen if p.shape == (1, 1, 2)]
    assert cross and all(torch.equal(p, torch.zeros(1, 1, 2, dtype=torch.long)) for p in cross)

    K = torch.tensor([[30.0, 0, 21], [0, 30, 14], [0, 0, 1]]).expand(1, 2, 3, 3)
    with torch.no_grad():
        with_k = model(images, intrinsics=K)
        with_depth = model(images, depths=torch.rand(1, 2, H, W) + 1.0)
        poses = torch.eye(4).repeat(1, 2, 1, 1)
        poses[0, 1, 0, 3] = 1.0
        with_pose = model(images, intrinsics=K, poses=poses)
        no_prior = model(images, intrinsics=K, with_prior=False)
    assert not torch.allclose(with_k["local_points"], base["local_points"])
    assert not torch.allclose(with_depth["local_points"], base["local_points"])
    assert not torch.allclose(with_pose["local_points"], with_k["local_points"])
    torch.testing.assert_close(no_prior["local_points"], base["local_points"])
    for out in (with_k, with_depth, with_pose):
        assert all(torch.isfinite(v).all() for v in out.values())

    model.disable_multimodal()
    for attr in ("depth_encoder", "depth_emb", "ray_embed", "pose_inject_blk"):
        assert not hasattr(model, attr)
    with torch.no_grad():
        assert model(images)["points"].shape == (1, 2, H, W, 3)


def _unscale_poses(poses, metric):
    out = poses.clone()
    out[..., :3, 3] = out[..., :3, 3] / metric.view(-1, 1, 1)
    return out


def test_pi3x_state_dict_prefixes(pi3_pkg):
    from pi3.models.pi3x import Pi3X

    prefixes = {k.split(".")[0] for k in Pi3X().state_dict()}
    assert prefixes == {
        "encoder",
        "decoder",
        "register_token",
        "point_decoder",
        "point_head",
        "conf_decoder",
        "conf_head",
        "camera_decoder",
        "camera_head",
        "image_mean",
        "image_std",
        "depth_encoder",
        "depth_emb",
        "ray_embed",
        "pose_inject_blk",
        "metric_token",
        "metric_decoder",
        "metric_head",
    }


def test_tiny_forward_time(vggt_pkg, pi3_pkg, images):
    from pi3.models.pi3 import Pi3
    from pi3.models.pi3x import Pi3X

    for model in (tiny_vggt(), Pi3().eval(), Pi3X().eval()):
        with torch.no_grad():
            model(images)  # first call pays one-off library warm-up
            start = time.perf_counter()
            model(images)
            assert time.perf_counter() - start < 1.0, type(model).__name__
