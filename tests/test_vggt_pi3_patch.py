"""VGGT, Pi3 and Pi3X specifics: RoPE position layouts, the compiled-RoPE refusal, Pi3X's
conditioning paths and uv trampoline, the builders.

The contract every backbone meets (pinhole identity, remove, rollback, side by side, save/load,
refusals) is ``tests/test_backbone_contract.py``. Runs on the stub packages in ``tests/stubs``
(the documented tiny recipes), and unchanged on the real upstream code when ``vggt`` / ``pi3``
are importable, with the small networks of ``tests/backbones.py`` (:func:`tests.backbones.tiny_real`).
"""

from __future__ import annotations

import gc
import importlib
import sys

import pytest
import torch
from torch import nn

import raytun3r_plugin as rt
from raytun3r_plugin import hooks
from raytun3r_plugin.errors import MissingDependencyError, UnsupportedUpstreamError, WeightsError
from raytun3r_plugin.registry import spec_for
from tests.backbones import H, W, build, make
from tests.helpers import (
    assert_same_snapshot,
    fisheye,
    outputs,
    pinhole,
    randomise_,
    snapshot,
)

pytest.importorskip("vggt")
pytest.importorskip("pi3")
from raytun3r_plugin.patches import pi3 as pi3_patch  # noqa: E402
from raytun3r_plugin.patches import vggt as vggt_patch  # noqa: E402

KINDS = ("vggt", "pi3", "pi3x")


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(1))


@pytest.fixture(params=KINDS)
def kind(request):
    return request.param


@pytest.fixture
def net(kind):
    return make(kind)


def conv_head_module():
    return importlib.import_module("pi3.models.layers.conv_head")


# ---------------------------------------------------------------------------------------------
# Adapter size
# ---------------------------------------------------------------------------------------------


def test_adapter_is_28_c_plus_20(net):
    info = spec_for(net)[0].describe(net)
    counts = rt.Adapter.for_model(net).num_parameters()
    assert counts == {"pe": 28 * info.embed_dim, "rope": 20, "total": 28 * info.embed_dim + 20}
    if info.name in ("vggt-1b", "pi3", "pi3x"):  # the official models: C = 1024
        assert counts["total"] == 28 * 1024 + 20


# ---------------------------------------------------------------------------------------------
# RoPE positions
# ---------------------------------------------------------------------------------------------


def test_rope_sees_float_displaced_positions_with_special_tokens_at_zero(net, images, monkeypatch):
    """Every RoPE call gets the upstream (y+1, x+1) grid plus the radial displacement, specials at 0."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    seen = []
    real = hooks.apply_rope_2d
    monkeypatch.setattr(
        hooks,
        "apply_rope_2d",
        lambda tokens, positions, base: (
            seen.append(positions.detach().clone()) or real(tokens, positions, base)
        ),
    )
    with rt.apply(net, camera, adapter, components=["rope"]) as handle:
        outputs(net, images)
        geometry = handle._state.geometry(H, W)
        displacement = handle._state.rope_displacement(
            geometry, torch.device("cpu"), torch.float32
        ).detach()
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
    assert layouts == {
        1,
        2,
    }  # frame blocks / head decoders (one view per row), global blocks (both views)


def test_displacement_matches_the_layout_based_core_helper(net):
    """``displace_grid_positions`` equals ``hooks.displaced_rope_positions`` on a frame layout."""
    camera = fisheye(W, H)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    with rt.apply(net, camera, adapter) as handle:
        state = handle._state
        grid = (
            torch.cartesian_prod(torch.arange(H // 14), torch.arange(W // 14))[None].expand(
                4, -1, -1
            )
            + 1
        )
        frame = torch.cat((torch.zeros(4, 5, 2, dtype=torch.long), grid), dim=1)
        ours = hooks.displace_grid_positions(frame, state, 14)
        core = hooks.displaced_rope_positions(frame, 5, state, H, W)
        assert torch.equal(ours, core)
        global_layout = frame.reshape(2, -1, 2)
        assert torch.equal(
            hooks.displace_grid_positions(global_layout, state, 14), core.reshape(2, -1, 2)
        )
        specials_only = torch.zeros(2, 1, 2, dtype=torch.long)
        assert hooks.displace_grid_positions(specials_only, state, 14) is specials_only


# ---------------------------------------------------------------------------------------------
# Pi3 / Pi3X: the compiled RoPE is refused
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
    with pytest.raises(
        UnsupportedUpstreamError,
        match=r"compiled RoPE models\.curope\.cuRoPE2D at 'rope'.*PyTorch RoPE2D",
    ):
        rt.apply(model, fisheye(W, H))
    assert_same_snapshot(model, snap)
    assert rt.handle_of(model) is None


# ---------------------------------------------------------------------------------------------
# Pi3X: conditioning paths and the uv trampoline
# ---------------------------------------------------------------------------------------------


def _conditions():
    generator = torch.Generator().manual_seed(7)
    focal = 30.0
    intrinsics = (
        torch.tensor([[focal, 0.0, W / 2], [0.0, focal, H / 2], [0.0, 0.0, 1.0]])
        .expand(1, 2, 3, 3)
        .clone()
    )
    depths = 1.0 + torch.rand(1, 2, H, W, generator=generator)
    return {"intrinsics": intrinsics, "depths": depths}


def test_pi3x_conditioning_paths_are_untouched(images):
    """Only the image path is patched: ray_embed and depth_encoder see and give the same."""
    net = make("pi3x")
    conditions = _conditions()
    recorded = {}

    def recorder(name):
        return lambda module, args, output: recorded.setdefault(name, []).append(
            output["x_norm_patchtokens"] if isinstance(output, dict) else output
        )

    handles = [
        net.ray_embed.register_forward_hook(recorder("ray")),
        net.depth_encoder.register_forward_hook(recorder("depth")),
    ]
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
    assert not torch.allclose(
        plain["local_points"], patched["local_points"]
    )  # the image path did change


def test_pi3x_pinhole_identity_with_conditions(images):
    net = make("pi3x")
    conditions = _conditions()
    with torch.no_grad():
        plain = net(images, **conditions)
        with rt.apply(net, pinhole(W, H), rt.Adapter.for_model(net)):
            patched = net(images, **conditions)
    for key in ("local_points", "conf", "camera_poses"):
        assert torch.allclose(
            plain[key], patched[key], rtol=0, atol=1e-5 * float(plain[key].abs().max())
        )


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
    assert torch.equal(
        trampoline(width=4, height=3, aspect_ratio=4 / 3, dtype=torch.float32),
        original(width=4, height=3, aspect_ratio=4 / 3, dtype=torch.float32),
    )
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
        rt.load_backbone(
            name,
            _save(
                source.state_dict() | {"extra.weight": torch.zeros(1)}, tmp_path / "x.safetensors"
            ),
        )
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


@pytest.mark.parametrize(
    "name, module_name, hint",
    [
        ("vggt-1b", "vggt.models.vggt", "facebookresearch/vggt"),
        ("pi3", "pi3.models.pi3", "yyfz/Pi3"),
        ("pi3x", "pi3.models.pi3x", "yyfz/Pi3"),
    ],
)
def test_missing_upstream_package_is_a_clear_error(name, module_name, hint, tmp_path, monkeypatch):
    path = _save({"a": torch.zeros(1)}, tmp_path / "w.safetensors")
    monkeypatch.setitem(sys.modules, module_name, None)  # makes the import fail
    with pytest.raises(MissingDependencyError, match=hint):
        rt.load_backbone(name, path)
