"""VGGT-Omega specifics: the normalised-coordinate RoPE hook, the unflattened patch embedding,
no PE table, the structural refusals, ``predict`` and the builders.

The contract every backbone meets is ``tests/test_backbone_contract.py`` (row ``vggt_omega`` of
``tests/backbones.py``). Runs on the stub in ``tests/stubs/vggt_omega`` and unchanged on the
real package when ``vggt_omega`` is importable (with the small network of
:func:`tests.backbones.tiny_real`).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.analysis import pe_field
from raytun3r_plugin.errors import InputError, UnsupportedUpstreamError, WeightsError
from raytun3r_plugin.registry import spec_for
from tests.backbones import CASE, make
from tests.helpers import assert_same_snapshot, fisheye, outputs, pinhole, randomise_, snapshot

pytest.importorskip("vggt_omega")
from raytun3r_plugin.patches import vggt_omega as omega_patch  # noqa: E402

HEIGHT, WIDTH = CASE["vggt_omega"].size
ROPE_PATHS = ("aggregator.rope_embed", "aggregator.patch_embed.rope_embed")


@pytest.fixture
def net():
    return make("vggt_omega")


@pytest.fixture
def images():
    return CASE["vggt_omega"].images()


def _rope(net, path):
    owner = net
    for part in path.split("."):
        owner = getattr(owner, part)
    return owner


def _fake_state(displacement: torch.Tensor, patch: int = 16, requires_grad: bool = False):
    """The few PatchState members the RoPE behaviour reads, with a fixed displacement."""
    table = torch.zeros(3, requires_grad=requires_grad)
    return SimpleNamespace(
        uses=lambda component: component == "rope",
        info=SimpleNamespace(patch_size=patch),
        adapter=SimpleNamespace(rope={"radial": table}),
        geometry=lambda height, width: (height, width),
        rope_displacement=lambda geometry, device, dtype: displacement + 0 * table.sum(),
    )


def test_describe_says_there_is_no_pe_table(net):
    spec, root = spec_for(net)
    info = spec.describe(root)
    assert spec.family == "vggt_omega" and info.pos_embed is None
    assert (info.patch_size, info.has_rope, info.has_grid) == (16, True, True)
    assert info.name == f"vggt_omega-custom-e{info.embed_dim}-d{len(net.aggregator.frame_blocks)}"
    adapter = rt.Adapter.for_model(net, fisheye(WIDTH, HEIGHT))
    assert adapter.pe_fingerprint == "" and adapter.n_r_rope == 20
    # strict apply has no PE fingerprint to compare and still checks the rest
    with rt.apply(net, fisheye(WIDTH, HEIGHT), adapter, strict=True):
        pass
    with pytest.raises(UnsupportedUpstreamError, match="has no absolute PE table"):
        pe_field(net, WIDTH, HEIGHT)


@pytest.mark.parametrize("path", ROPE_PATHS)
@pytest.mark.parametrize("mode", ["max", "min", "separate"])
def test_zero_displacement_is_bit_identical(net, path, mode):
    rope = _rope(net, path)
    rope.normalize_coords = mode
    behaviour = omega_patch._normalised_rope(rope, _fake_state(torch.zeros(12, 2)))
    upstream = rope(H=3, W=4)
    patched = behaviour(rope.forward, H=3, W=4)
    assert all(torch.equal(a, b) for a, b in zip(upstream, patched, strict=True))


def test_displacement_is_in_token_units(net):
    """A displacement of d tokens moves a patch's angles to those of centre + d."""
    rope = net.aggregator.rope_embed
    displacement = torch.zeros(12, 2)
    displacement[5] = torch.tensor([0.5, -0.25])  # row 1, column 1 of a 3 x 4 grid
    sin, cos = omega_patch._normalised_rope(rope, _fake_state(displacement))(rope.forward, H=3, W=4)
    upstream_sin, _ = rope(H=3, W=4)
    moved = [i for i in range(12) if not torch.equal(sin[i], upstream_sin[i])]
    assert moved == [5]
    # normalize_coords="max": one token is 2 / max(3, 4) in the [-1, 1] coordinates
    y = 2 * (1 + 0.5 + 0.5) / 4 - 1
    x = 2 * (1 + 0.5 - 0.25) / 4 - 1
    angles = 2 * math.pi * torch.cat([y / rope.periods, x / rope.periods]).tile(2)
    assert torch.allclose(sin[5], angles.sin(), atol=1e-6)
    assert torch.allclose(cos[5], angles.cos(), atol=1e-6)


def test_rope_gradient_passes_the_aggregators_no_grad(net):
    """Upstream computes the frame RoPE under no_grad; a fitting adapter still gets a gradient."""
    rope = net.aggregator.rope_embed
    behaviour = omega_patch._normalised_rope(
        rope, _fake_state(torch.full((12, 2), 0.1), requires_grad=True)
    )
    with torch.no_grad():
        sin, _ = behaviour(rope.forward, H=3, W=4)
    assert sin.requires_grad
    frozen = omega_patch._normalised_rope(rope, _fake_state(torch.full((12, 2), 0.1)))
    with torch.no_grad():
        assert not frozen(rope.forward, H=3, W=4)[0].requires_grad


def test_both_rope_instances_are_patched_and_matter(net, images, monkeypatch):
    camera = fisheye(WIDTH, HEIGHT)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    calls = {path: [] for path in ROPE_PATHS}
    with rt.apply(net, camera, adapter, components=["rope"]):
        for path in ROPE_PATHS:
            rope = _rope(net, path)
            assert "forward" in vars(rope)  # a per-instance wrapper
            wrapper = vars(rope)["forward"]
            monkeypatch.setattr(
                rope,
                "forward",
                lambda *a, _w=wrapper, _c=calls[path], **k: _c.append(k) or _w(*a, **k),
            )
        rt.predict(net, images)
    depth = len(net.aggregator.patch_embed.blocks)
    assert calls["aggregator.rope_embed"] == [{"H": 3, "W": 4}]  # once per forward
    assert len(calls["aggregator.patch_embed.rope_embed"]) == depth  # once per ViT block
    assert "forward" not in vars(net.aggregator.rope_embed)


def test_patch_embedding_keeps_the_unflattened_layout(net):
    camera = fisheye(WIDTH, HEIGHT)
    embed = net.aggregator.patch_embed.patch_embed
    x = torch.rand(2, 3, HEIGHT, WIDTH)
    upstream = embed(x)
    with rt.apply(net, camera, components=["patch_resample", "border_tokens"]):
        patched = embed(x)
    assert upstream.shape == patched.shape == (2, 3, 4, embed.embed_dim)
    assert not torch.equal(upstream, patched)
    with rt.apply(net, pinhole(WIDTH, HEIGHT), components=["patch_resample", "border_tokens"]):
        assert torch.equal(embed(x), upstream)


def test_pe_component_is_inert_and_its_tables_get_no_gradient(net, images):
    camera = fisheye(WIDTH, HEIGHT)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    reference = outputs(net, images)
    with rt.apply(net, camera, adapter, components={c: c == "pe" for c in COMPONENTS}):
        assert outputs(net, images)["depth"].equal(reference["depth"])
    net.requires_grad_(False)
    with rt.apply(net, camera, adapter):
        rt.predict(net, images).depth.mean().backward()
    assert adapter.pe["radial"].grad is None and adapter.pe["angular"].grad is None
    assert float(adapter.rope["radial"].grad.abs().sum()) > 0


def test_absolute_pe_table_is_refused(net):
    net.aggregator.patch_embed.pos_embed = torch.nn.Parameter(torch.zeros(1, 5, 8))
    snap = snapshot(net)
    with pytest.raises(UnsupportedUpstreamError, match="expected no absolute PE table"):
        rt.apply(net, fisheye(WIDTH, HEIGHT))
    assert_same_snapshot(net, snap)


@pytest.mark.parametrize("path", ROPE_PATHS)
def test_rope_coordinate_augmentation_is_refused(net, path):
    _rope(net, path).jitter_coords = 2.0
    with pytest.raises(
        UnsupportedUpstreamError, match=rf"augmentation at '{path}'.*jitter_coords=2\.0"
    ):
        rt.apply(net, fisheye(WIDTH, HEIGHT))
    assert rt.handle_of(net) is None


def test_rope_without_base_is_refused(net):
    net.aggregator.rope_embed.base = None  # a min_period / max_period configuration
    with pytest.raises(
        UnsupportedUpstreamError, match=r"RopePositionEmbedding\.base, found base=None"
    ):
        rt.apply(net, fisheye(WIDTH, HEIGHT))


def test_predict_conventions(net, images):
    prediction = rt.predict(net, images)
    assert prediction.depth.shape == (1, 2, HEIGHT, WIDTH)
    assert prediction.confidence.shape == (1, 2, HEIGHT, WIDTH)
    assert prediction.cam_from_world.shape == (1, 2, 4, 4)
    assert torch.equal(
        prediction.cam_from_world[..., 3, :], torch.tensor([0.0, 0, 0, 1]).expand(1, 2, 4)
    )
    rotation = prediction.cam_from_world[..., :3, :3]
    assert torch.allclose(
        rotation @ rotation.transpose(-1, -2), torch.eye(3).expand(1, 2, 3, 3), atol=1e-5
    )
    intrinsics = prediction.extras["intrinsics"]
    assert torch.allclose(intrinsics[..., 0, 2], torch.tensor(WIDTH / 2))
    assert torch.allclose(intrinsics[..., 1, 2], torch.tensor(HEIGHT / 2))
    assert "camera_and_register_tokens" in prediction.extras
    net.camera_head = None
    with pytest.raises(InputError, match="no camera head"):
        rt.predict(net, images)


def test_builders_need_a_local_file_and_load_strictly(net, tmp_path, monkeypatch, images):
    assert {"vggt-omega-1b-512", "vggt-omega-1b-256-text"} <= set(rt.available_backbones())
    with pytest.raises(WeightsError, match="needs a local weight file"):
        rt.load_backbone("vggt-omega-1b-512")
    built = []
    monkeypatch.setattr(
        omega_patch,
        "build_network",
        lambda enable_alignment=False: built.append(1) or make("vggt_omega", seed=1),
    )
    with pytest.raises(WeightsError):
        omega_patch.BUILDERS["vggt-omega-1b-512"](tmp_path / "missing.pt")
    assert not built  # the file is read before the network is built
    path = tmp_path / "vggt_omega_1b_512.pt"
    torch.save(net.state_dict(), path)
    loaded = omega_patch.BUILDERS["vggt-omega-1b-512"](path).eval()
    assert all(
        torch.equal(a, b)
        for a, b in zip(loaded.state_dict().values(), net.state_dict().values(), strict=True)
    )
    assert loaded.raytun3r_name == "vggt-omega-1b-512"
    # through load_backbone, with the name and without (then the tensors must say it)
    assert type(rt.load_backbone("vggt-omega-1b-512", path)).__name__ == "VGGTOmega"
    signature = omega_patch.identify(net.state_dict())
    assert signature.family == "vggt_omega" and signature.pe_shape is None
    assert signature.names == () and "no PE table" in signature.detail  # a tiny custom size
    with pytest.raises(WeightsError, match=r"a vggt_omega checkpoint .* no official size"):
        rt.load_backbone(None, path)
    text_state = dict(net.state_dict(), **{"text_alignment_head.language_token": torch.zeros(1)})
    assert "text-alignment head" in omega_patch.identify(text_state).detail
    assert omega_patch.identify({"aggregator.patch_embed.pos_embed": torch.zeros(1)}) is None
    zero = torch.zeros(1)
    official = {  # the key layout of the released 1B checkpoints (shapes only where read)
        "aggregator.rope_embed.periods": zero,
        "aggregator.patch_embed.rope_embed.periods": zero,
        "aggregator.camera_token": torch.zeros(1, 2, 1, 1024),
        **{f"aggregator.frame_blocks.{i}.norm1.weight": zero for i in range(24)},
    }
    assert omega_patch.identify(official).names == ("vggt-omega-1b-512",)
    official["text_alignment_head.language_token"] = zero
    assert omega_patch.identify(official).names == ("vggt-omega-1b-256-text",)
    state = net.state_dict()
    state.pop("aggregator.rope_embed.periods")
    torch.save(state, path)
    with pytest.raises(WeightsError, match="periods"):
        omega_patch.BUILDERS["vggt-omega-1b-512"](path)
