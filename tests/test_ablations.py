"""The component-table ablations as switches (docs/components.md).

``"pe_radial_only"`` (the radial PE table alone) and ``"pe_naive_remap"`` (the backbone's own PE
table sampled at undistorted token positions), their exclusions, their file format and their
removal, on the tiny real DA3 network with a randomised position table (``tests.backbones``).
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

import raytun3r_plugin as rt
from raytun3r_plugin.adapter import ABLATION_SWITCHES, COMPONENTS, normalise_components
from raytun3r_plugin.errors import AdapterError, InputError, Raytun3rError
from raytun3r_plugin.geometry import NAIVE_MAX_ANGLE_DEG, naive_pe_positions, token_centres
from raytun3r_plugin.size_geometry import GeometryCache
from tests.helpers import (
    assert_same_snapshot,
    fisheye,
    max_relative_difference,
    outputs,
    pinhole,
    randomise_,
    snapshot,
)

pytest.importorskip("depth_anything_3")
from tests.backbones import CASES, make  # noqa: E402

CASES_BY_FAMILY = {case.family: case for case in CASES}

H, W = 70, 84
PATCH = 14
FULL_PE = ["pe"]
RADIAL_ONLY = ["pe", "pe_radial_only"]
NAIVE = ["pe_naive_remap"]
TURNED = ["pe", "patch_resample", "resample_turned"]


@pytest.fixture(scope="module")
def net():
    return make("da3")


@pytest.fixture(scope="module")
def images():
    return torch.rand(1, 2, 3, H, W, generator=torch.Generator().manual_seed(3))


@pytest.fixture(scope="module")
def reference(net, images):
    return outputs(net, images)


@pytest.fixture(scope="module")
def camera():
    return fisheye(W, H)


def _fitted(net, camera, seed: int = 0):
    return randomise_(rt.Adapter.for_model(net, camera), seed=seed)


def _run(net, images, camera, adapter, components):
    with rt.apply(net, camera, adapter, components=components):
        return outputs(net, images)


# ---------------------------------------------------------------------------------------------
# Names, defaults and exclusions
# ---------------------------------------------------------------------------------------------


def test_switches_appear_only_while_on():
    assert set(normalise_components(None)) == set(COMPONENTS)
    assert set(normalise_components({"rope": False, "pe_naive_remap": False})) == set(COMPONENTS)
    radial = normalise_components(RADIAL_ONLY)
    assert radial["pe_radial_only"] is True and radial["pe"] is True and not radial["rope"]
    naive = normalise_components({"pe": False, "pe_naive_remap": True})
    assert naive["pe_naive_remap"] is True and naive["pe"] is False and naive["grid"] is True
    # A list that names no switch means what it meant before the switches existed.
    assert normalise_components(["pe", "rope"]) == {
        "pe": True,
        "rope": True,
        "patch_resample": False,
        "border_tokens": False,
        "grid": False,
    }


@pytest.mark.parametrize(
    ("components", "message"),
    [
        (["pe", "pe_naive_remap"], "'pe_naive_remap' and 'pe' exclude each other"),
        ({"pe_naive_remap": True}, "'pe_naive_remap' and 'pe' exclude each other"),
        (["pe_radial_only"], "'pe_radial_only' restricts the 'pe' correction.*'pe' is off"),
        ({"pe": False, "pe_radial_only": True}, "'pe' is off"),
        (["pe_radial_only", "pe_naive_remap"], "'pe' is off"),
        (["pe_angular"], "unknown components \\['pe_angular'\\]"),
        ({"pe_radial_only": 1}, "component 'pe_radial_only' must be True or False"),
        (["resample_turned"], "'resample_turned' chooses the local map.*'patch_resample' is off"),
        ({"patch_resample": False, "resample_turned": True}, "'patch_resample' is off"),
    ],
)
def test_bad_combinations_are_refused_before_the_model_is_touched(net, camera, components, message):
    with pytest.raises(AdapterError, match=message) as caught:
        normalise_components(components)
    assert isinstance(caught.value, Raytun3rError)
    before = snapshot(net)
    with pytest.raises(AdapterError, match=message):
        rt.apply(net, camera, _fitted(net, camera), components=components)
    assert rt.handle_of(net) is None
    assert_same_snapshot(net, before)
    with pytest.raises(AdapterError, match=message):
        rt.Adapter.for_model(net, camera, components=components)


# ---------------------------------------------------------------------------------------------
# Radial PE only
# ---------------------------------------------------------------------------------------------


def test_radial_only_ignores_the_angular_table(net, images, camera, reference):
    adapter = _fitted(net, camera)
    radial = _run(net, images, camera, adapter, RADIAL_ONLY)
    full = _run(net, images, camera, adapter, FULL_PE)
    assert max_relative_difference(full, radial) > 1e-4  # the angular table matters when used
    assert max_relative_difference(reference, radial) > 1e-4  # the radial one still acts
    with torch.no_grad():
        adapter.pe["angular"].mul_(-3.0).add_(0.2)
    assert max_relative_difference(radial, _run(net, images, camera, adapter, RADIAL_ONLY)) == 0.0
    with torch.no_grad():
        adapter.pe["angular"].zero_()
    # With a zero angular table the full PE correction is the radial one, up to float rounding.
    assert max_relative_difference(radial, _run(net, images, camera, adapter, FULL_PE)) < 1e-6


def test_radial_only_gives_the_angular_table_no_gradient(net, images, camera):
    adapter = _fitted(net, camera)
    net.requires_grad_(False)
    try:
        with rt.apply(net, camera, adapter, components=RADIAL_ONLY):
            prediction = rt.predict(net, images)
            prediction.depth.mean().backward()
    finally:
        net.requires_grad_(True)
    angular = adapter.pe["angular"].grad
    assert angular is None or not bool(angular.abs().max() > 0)
    assert bool(adapter.pe["radial"].grad.abs().max() > 0)


def test_pe_correction_radial_only_is_the_radial_term(net, camera):
    adapter = _fitted(net, camera)
    geometry = GeometryCache(camera, PATCH).at(H, W)
    full = adapter.pe_correction(geometry)
    radial = adapter.pe_correction(geometry, angular=False)
    weights, _ = geometry.pe_weights(adapter.n_r, adapter.n_theta, "cpu", torch.float32)
    assert torch.allclose(radial, weights @ adapter.pe["radial"], atol=0, rtol=0)
    assert not torch.allclose(full, radial)
    # None follows the adapter's own components (what the adaptation's regularisers read).
    radial_adapter = rt.Adapter.for_model(net, camera, components=RADIAL_ONLY)
    radial_adapter.load_state_dict(adapter.state_dict())
    assert torch.equal(radial_adapter.pe_correction(geometry), radial)


def test_adapt_with_radial_only_leaves_the_angular_table_at_zero(net, camera, tmp_path):
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.train import adapt
    from tests.test_losses import room_sequence

    frames, _, _ = room_sequence(camera, 4, step=0.35, yaw=0.06)
    config = AdaptConfig.from_recipe(
        "matches",
        steps=2,
        input_size=W,
        n_windows=2,
        checkpoint_every=0,
        cache_dir=str(tmp_path / "cache"),
        matcher_options={"border_px": 2},
        seed=0,
        guard=False,
        components=RADIAL_ONLY,
        pose_source="targets",
    )
    adapter = adapt(
        net, camera, frames, config, out_path=tmp_path / "a.safetensors", progress=False
    )
    assert adapter.components["pe_radial_only"] is True
    assert not bool(adapter.pe["angular"].abs().max() > 0)
    assert bool(adapter.pe["radial"].abs().max() > 0)
    loaded = rt.Adapter.load(tmp_path / "a.safetensors")
    assert loaded.components == adapter.components and loaded.same_as(adapter)


# ---------------------------------------------------------------------------------------------
# Naive remap of the PE table
# ---------------------------------------------------------------------------------------------


def test_naive_remap_is_the_identity_on_a_pinhole(net, images, reference):
    camera = pinhole(W, H)
    assert naive_pe_positions(camera, H, W, PATCH) is None
    assert max_relative_difference(reference, _run(net, images, camera, None, NAIVE)) == 0.0


def test_naive_remap_differs_from_vanilla_and_from_the_raytun3r_pe(net, images, camera, reference):
    naive = _run(net, images, camera, None, NAIVE)
    assert max_relative_difference(reference, naive) > 1e-4
    raytun3r_pe = _run(net, images, camera, _fitted(net, camera), FULL_PE)
    assert max_relative_difference(raytun3r_pe, naive) > 1e-4
    # It needs no adapter, and an adapter's PE tables play no part in it.
    adapter = _fitted(net, camera)
    with_adapter = _run(net, images, camera, adapter, NAIVE)
    assert max_relative_difference(naive, with_adapter) == 0.0


def _bilinear(table: torch.Tensor, column: float, row: float) -> torch.Tensor:
    """table (rows, cols, C) read at a fractional (column, row), by hand."""
    c0, r0 = min(int(math.floor(column)), table.shape[1] - 2), min(int(row), table.shape[0] - 2)
    fc, fr = column - c0, row - r0
    return (
        table[r0, c0] * (1 - fc) * (1 - fr)
        + table[r0, c0 + 1] * fc * (1 - fr)
        + table[r0 + 1, c0] * (1 - fc) * fr
        + table[r0 + 1, c0 + 1] * fc * fr
    )


def test_naive_remap_reads_the_upstream_table_at_the_undistorted_positions(net, camera):
    owner = net.backbone.pretrained
    tokens = torch.zeros(1, 1 + (H // PATCH) * (W // PATCH), owner.pos_embed.shape[-1])
    with torch.no_grad():
        upstream = owner.interpolate_pos_encoding(tokens, H, W)  # upstream's (w, h) = (H, W)
        with rt.apply(net, camera, components=NAIVE):
            remapped = owner.interpolate_pos_encoding(tokens, H, W)
    assert torch.equal(remapped[:, :1], upstream[:, :1])  # the class slot is left alone
    rows, cols = H // PATCH, W // PATCH
    grid = upstream[0, 1:].reshape(rows, cols, -1).double()
    positions = naive_pe_positions(camera, H, W, PATCH)
    expected = torch.stack([_bilinear(grid, float(c), float(r)) for c, r in positions])
    assert torch.allclose(remapped[0, 1:].double(), expected, atol=1e-5)


def test_naive_positions_collapse_towards_the_centre_and_clamp_wide_rays(camera):
    positions = naive_pe_positions(camera, H, W, PATCH)
    rows, cols = H // PATCH, W // PATCH
    assert positions.shape == (rows * cols, 2) and bool(torch.isfinite(positions).all())
    assert bool((positions[:, 0] >= 0).all() and (positions[:, 0] <= cols - 1).all())
    assert bool((positions[:, 1] >= 0).all() and (positions[:, 1] <= rows - 1).all())
    centre = torch.tensor([(camera.cx + 0.5) / PATCH - 0.5, (camera.cy + 0.5) / PATCH - 0.5])
    own = torch.stack(
        (
            (token_centres(H, W, PATCH)[:, 0] + 0.5) / PATCH - 0.5,
            (token_centres(H, W, PATCH)[:, 1] + 0.5) / PATCH - 0.5,
        ),
        dim=-1,
    )
    # Perspective undistortion stretches the rim, so after fitting the grid every token moves
    # towards the principal point (the paper's "collapse onto a small central region").
    moved = (positions - centre.double()).norm(dim=-1)
    assert bool((moved <= (own - centre.double()).norm(dim=-1) + 1e-9).all())
    assert float(moved.mean()) < 0.8 * float((own - centre.double()).norm(dim=-1).mean())
    # Rays at or beyond the clamp angle (and pixels without a ray) land on one undistorted radius.
    rays, valid = camera.unproject(token_centres(H, W, PATCH))
    angle = torch.rad2deg(torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]))
    wide = ~valid.bool() | (angle >= NAIVE_MAX_ANGLE_DEG)
    assert int(wide.sum()) >= 4
    pixels = (positions * PATCH + (PATCH - 1) / 2 - torch.tensor([camera.cx, camera.cy])) / float(
        camera.fx
    )
    radius = pixels[wide].norm(dim=-1)
    assert float(radius.max() - radius.min()) < 1e-6 * float(radius.max())
    with pytest.raises(InputError, match="max_angle_deg must be in \\(0, 90\\)"):
        naive_pe_positions(camera, H, W, PATCH, max_angle_deg=90.0)


# ---------------------------------------------------------------------------------------------
# Adapter files
# ---------------------------------------------------------------------------------------------


def _rewrite_components(path, components_json: str) -> None:
    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata())
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118
    metadata["components"] = components_json
    save_file(tensors, str(path), metadata=metadata)


def test_files_without_switches_load_with_their_old_meaning(
    net, images, camera, reference, tmp_path
):
    adapter = _fitted(net, camera)
    path = adapter.save(tmp_path / "old.safetensors")
    # What a writer from before the switches wrote: exactly the five correction names.
    old = json.dumps(dict.fromkeys(("pe", "rope", "patch_resample", "border_tokens", "grid"), True))
    _rewrite_components(path, old)
    loaded = rt.Adapter.load(path)
    assert loaded.components == dict.fromkeys(COMPONENTS, True)
    with rt.apply(net, camera, loaded) as handle:
        assert set(handle.components) == set(COMPONENTS)
        from_file = outputs(net, images)
    assert max_relative_difference(_run(net, images, camera, adapter, None), from_file) == 0.0
    # ...and the file this version writes for it is the same five keys (old readers accept it).
    again = loaded.save(tmp_path / "again.safetensors")
    with safe_open(str(again), framework="pt") as handle:
        assert set(json.loads(handle.metadata()["components"])) == set(COMPONENTS)


@pytest.mark.parametrize("switches", [RADIAL_ONLY, NAIVE, [*NAIVE, "rope", "grid"], TURNED])
def test_files_with_switches_round_trip(net, images, camera, switches, tmp_path):
    adapter = randomise_(rt.Adapter.for_model(net, camera, components=switches))
    loaded = rt.Adapter.load(adapter.save(tmp_path / "a.safetensors"))
    assert loaded.components == normalise_components(switches)
    assert loaded.same_as(adapter)
    assert (
        max_relative_difference(
            _run(net, images, camera, adapter, switches), _run(net, images, camera, loaded, None)
        )
        == 0.0
    )


@pytest.mark.parametrize(
    ("components", "message"),
    [
        (
            dict.fromkeys(COMPONENTS, True) | {"pe_naive_remap": True},
            "'pe_naive_remap' and 'pe' exclude each other",
        ),
        (dict.fromkeys(COMPONENTS, True) | {"pe_angular": True}, "must be an object with exactly"),
        ({"pe_radial_only": True}, "must be an object with exactly"),
        (dict.fromkeys(COMPONENTS, True) | {"pe_radial_only": "yes"}, "must be true or false"),
    ],
)
def test_files_with_bad_switches_are_refused(net, camera, components, message, tmp_path):
    path = _fitted(net, camera).save(tmp_path / "a.safetensors")
    _rewrite_components(path, json.dumps(components))
    with pytest.raises(AdapterError, match=message):
        rt.Adapter.load(path)


def test_a_false_switch_in_a_file_is_read_as_absent(net, camera, tmp_path):
    path = _fitted(net, camera).save(tmp_path / "a.safetensors")
    _rewrite_components(
        path, json.dumps(dict.fromkeys(COMPONENTS, True) | dict.fromkeys(ABLATION_SWITCHES, False))
    )
    assert rt.Adapter.load(path).components == dict.fromkeys(COMPONENTS, True)


# ---------------------------------------------------------------------------------------------
# Patch resampling with the turned pinhole's local map
# ---------------------------------------------------------------------------------------------


def _patch_projection_inputs(net, images, camera, components) -> torch.Tensor:
    """What the patch embedding's convolution receives under ``apply(..., components)``."""
    (projection,) = [m for n, m in net.named_modules() if n.endswith("patch_embed.proj")]
    seen = []
    hook = projection.register_forward_hook(lambda _m, args, _out: seen.append(args[0]))
    try:
        _run(net, images, camera, None, components)
    finally:
        hook.remove()
    return torch.cat(seen)


@pytest.mark.parametrize(
    ("components", "local_map"), [(TURNED, "turned"), ([*FULL_PE, "patch_resample"], "central")]
)
def test_the_switch_chooses_the_resampling_map(net, images, camera, components, local_map):
    from raytun3r_plugin.geometry import patch_resample_grid

    # What the convolution gets without resampling: upstream's normalised images.
    plain = _patch_projection_inputs(net, images, camera, FULL_PE)
    grid = patch_resample_grid(camera, H, W, PATCH, local_map=local_map).to(torch.float32)
    expected = torch.nn.functional.grid_sample(
        plain,
        grid.expand(len(plain), -1, -1, -1),
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )
    seen = _patch_projection_inputs(net, images, camera, components)
    assert torch.allclose(seen, expected, atol=1e-5)
    assert not torch.allclose(seen, plain, atol=1e-2)


# ---------------------------------------------------------------------------------------------
# Removal
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "components",
    [RADIAL_ONLY, NAIVE, [*NAIVE, "rope", "patch_resample", "border_tokens", "grid"], TURNED],
)
def test_remove_restores_the_model_bit_for_bit(net, images, camera, reference, components):
    before = snapshot(net)
    handle = rt.apply(net, camera, _fitted(net, camera), components=components)
    assert max_relative_difference(reference, outputs(net, images)) > 1e-4
    with handle.disabled():
        assert max_relative_difference(reference, outputs(net, images)) == 0.0
    handle.remove()
    assert rt.handle_of(net) is None
    assert_same_snapshot(net, before)
    assert max_relative_difference(reference, outputs(net, images)) == 0.0


# ---------------------------------------------------------------------------------------------
# Every backbone
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", [case.family for case in CASES])
def test_switches_on_every_backbone(family):
    case = CASES_BY_FAMILY[family]
    pytest.importorskip(case.package)
    net = make(family)
    images = case.images()
    height, width = case.size
    reference = outputs(net, images)
    before = snapshot(net)
    fish = fisheye(width, height)
    adapter = randomise_(rt.Adapter.for_model(net, fish))
    naive = _run(net, images, fish, None, NAIVE)
    identity = _run(net, images, pinhole(width, height), None, NAIVE)
    radial = _run(net, images, fish, adapter, RADIAL_ONLY)
    with torch.no_grad():
        adapter.pe["angular"].zero_()
    radial_again = _run(net, images, fish, adapter, RADIAL_ONLY)
    assert max_relative_difference(reference, identity) == 0.0
    if "pe" in case.inert:  # no absolute PE table: neither switch has anything to act on
        assert max_relative_difference(reference, naive) == 0.0
        assert max_relative_difference(reference, radial) == 0.0
    else:
        assert max_relative_difference(reference, naive) > 1e-4
        assert max_relative_difference(reference, radial) > 1e-4
    assert max_relative_difference(radial, radial_again) == 0.0
    assert_same_snapshot(net, before)
