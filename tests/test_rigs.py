"""Multi-camera rigs: ``apply(model, [camera_a, camera_b, ...], [adapter_a, adapter_b, ...])``.

View ``s`` of a forward is taken by camera ``s % V`` (docs/rigs.md). The contracts of a single
camera must hold per view (identity with zero adapters and pinhole cameras, exact remove,
deepcopy), a uniform rig must be the single-camera patch exactly, and each per-image hook must
give a view exactly what a single-camera patch with that view's camera gives it.
"""

from __future__ import annotations

import copy

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import AdapterError, CameraError, InputError
from tests.backbones import CASE, CASES, make
from tests.helpers import assert_same_snapshot, fisheye, outputs, pinhole, randomise_, snapshot


#: Components every family can use per view (VGGT-Omega's RoPE table is one for all frames).
def _components(family: str) -> dict[str, bool] | None:
    if family == "vggt_omega":
        return {
            "pe": True,
            "rope": False,
            "patch_resample": True,
            "border_tokens": True,
            "grid": True,
        }
    if family == "pi3x":
        return {
            "pe": True,
            "rope": True,
            "patch_resample": True,
            "border_tokens": True,
            "grid": False,
        }
    return None


def _rig(family: str):
    case = CASE[family]
    pytest.importorskip(case.package)
    model = make(family)
    height, width = case.size
    cameras = [fisheye(width, height, 190.0), fisheye(width, height, 150.0, k1=0.04)]
    adapters = [
        randomise_(Adapter.for_model(model, cameras[0]), seed=1),
        randomise_(Adapter.for_model(model, cameras[1]), seed=2),
    ]
    if adapters[1].rope is not None:  # randomise_ gives every RoPE table one profile
        with torch.no_grad():
            adapters[1].rope["radial"].mul_(-0.5)
    return case, model, cameras, adapters


def _max_difference(a: dict, b: dict) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a if a[k] is not None)


@pytest.fixture(params=[case.family for case in CASES])
def family(request):
    return request.param


def test_pinhole_zero_adapter_rig_is_upstream_exactly(family):
    case, model, _cameras, _adapters = _rig(family)
    height, width = case.size
    images = case.images(views=4)
    reference = outputs(model, images)
    cameras = [pinhole(width, height, 60.0), pinhole(width, height, 45.0)]
    zero = [Adapter.for_model(model, cameras[0]), None]
    with rt.apply(model, cameras, zero, components=_components(family)) as handle:
        assert handle.is_rig and handle.cameras == tuple(cameras)
        assert _max_difference(outputs(model, images), reference) == 0.0


def test_uniform_rig_is_the_single_camera_patch(family):
    case, model, cameras, adapters = _rig(family)
    images = case.images(views=4)
    with rt.apply(model, cameras[0], adapters[0], components=_components(family)):
        single = outputs(model, images)
    with rt.apply(model, [cameras[0]] * 2, [adapters[0]] * 2, components=_components(family)) as h:
        assert not h.is_rig
        assert _max_difference(outputs(model, images), single) == 0.0


def test_rig_changes_outputs_and_remove_is_exact(family):
    case, model, cameras, adapters = _rig(family)
    images = case.images(views=4)
    reference = outputs(model, images)
    before = snapshot(model)
    with rt.apply(model, cameras[0], adapters[0], components=_components(family)):
        single = outputs(model, images)
    handle = rt.apply(model, cameras, adapters, components=_components(family))
    rig = outputs(model, images)
    # The second camera (and adapter) reaches views 1 and 3: the rig is not the single patch.
    assert _max_difference(rig, single) > 1e-4
    assert rt.apply(model, cameras, adapters, components=_components(family)) is handle
    with handle.disabled():
        assert _max_difference(outputs(model, images), reference) == 0.0
    handle.remove()
    assert_same_snapshot(model, before)
    assert _max_difference(outputs(model, images), reference) == 0.0


def test_rig_forward_of_the_wrong_view_count_is_refused(family):
    case, model, cameras, adapters = _rig(family)
    with rt.apply(model, cameras, adapters, components=_components(family)):
        with pytest.raises(InputError, match="rig"):
            outputs(model, case.images(views=3))
        outputs(model, case.images(views=2))  # the model still runs


def test_deepcopy_of_a_rig_runs_its_own_adapters(family):
    case, model, cameras, adapters = _rig(family)
    images = case.images(views=2)
    with rt.apply(model, cameras, adapters, components=_components(family)):
        expected = outputs(model, images)
        twin = copy.deepcopy(model)
    twin_handle = rt.handle_of(twin)
    assert twin_handle is not None and twin_handle.is_rig
    assert twin_handle.adapters[1] is not adapters[1]
    assert _max_difference(outputs(twin, images), expected) == 0.0


def test_shared_adapter_stays_shared_in_a_deepcopy():
    _case, model, cameras, adapters = _rig("da3")
    with rt.apply(
        model, [cameras[0], cameras[1], cameras[0]], [adapters[0], adapters[1], adapters[0]]
    ):
        twin = copy.deepcopy(model)
    first, _second, third = rt.handle_of(twin).adapters
    assert first is third and first is not adapters[0]


# ---- each view gets its own camera, hook by hook (the real DA3 code) ------------------------


def _single(model, camera, adapter, call):
    with rt.apply(model, camera, adapter):
        return call()


def test_da3_pe_patch_embedding_and_grid_are_per_view():
    case, model, cameras, adapters = _rig("da3")
    height, width = case.size
    vit = model.backbone.pretrained
    tokens = torch.zeros(4, 1 + (height // 14) * (width // 14), vit.embed_dim)
    images = torch.rand(4, 3, height, width, generator=torch.Generator().manual_seed(3))
    features = torch.rand(4, model.head.projects[0].out_channels, height // 14, width // 14)

    def calls():
        return {
            "pe": vit.interpolate_pos_encoding(tokens, height, width),
            "patch": vit.patch_embed(images),
            "grid": model.head._add_pos_embed(features, width, height),
        }

    with torch.no_grad():
        per_camera = [_single(model, cameras[v], adapters[v], calls) for v in range(2)]
        with rt.apply(model, cameras, adapters):
            rig = calls()
    for name in ("pe", "patch", "grid"):
        for row in range(4):
            expected = per_camera[row % 2][name]
            expected = expected[row] if expected.shape[0] == 4 else expected[0]
            assert torch.equal(rig[name][row], expected), (name, row)
    assert not torch.equal(per_camera[0]["patch"], per_camera[1]["patch"])


def test_da3_rope_positions_are_per_view():
    case, model, cameras, adapters = _rig("da3")
    height, width = case.size
    vit = model.backbone.pretrained

    def positions():
        return vit._prepare_rope(2, 4, height, width, torch.device("cpu"))[0]

    per_camera = [_single(model, cameras[v], adapters[v], positions) for v in range(2)]
    with rt.apply(model, cameras, adapters):
        rig = positions()
    assert rig.shape == per_camera[0].shape == (2, 4, rig.shape[2], 2)
    for view in range(4):
        assert torch.equal(rig[:, view], per_camera[view % 2][:, view])
    assert not torch.equal(per_camera[0], per_camera[1])


def test_da3_reference_view_is_the_first_when_rig_positions_differ(monkeypatch):
    case, model, cameras, adapters = _rig("da3")
    vit = model.backbone.pretrained
    seen = []
    original = type(vit)._get_intermediate_layers_not_chunked

    def spy(self, x, n=1, export_feat_layers=[], **kwargs):  # noqa: B006
        seen.append(kwargs.get("ref_view_strategy"))
        return original(self, x, n, export_feat_layers, **kwargs)

    monkeypatch.setattr(type(vit), "_get_intermediate_layers_not_chunked", spy)
    images = case.images(views=4)
    outputs(model, images)
    with rt.apply(model, cameras, adapters):
        outputs(model, images)
    zero = [Adapter.for_model(model, camera) for camera in cameras]
    with rt.apply(model, cameras, zero):
        outputs(model, images)
    # Upstream's default, the rig's "first", and zero RoPE tables (nothing to keep apart).
    assert seen == ["saddle_balanced", "first", "saddle_balanced"]


def test_vggt_rope_is_per_view_in_frame_and_global_blocks():
    """Upstream positions of 4 views in both layouts: per frame ((B S), N) and global (B, S N)."""
    from raytun3r_plugin.hooks import displace_grid_positions

    case, model, cameras, adapters = _rig("vggt")
    rows, cols = (side // 14 for side in case.size)
    grid = torch.stack(
        torch.meshgrid(torch.arange(1, rows + 1), torch.arange(1, cols + 1), indexing="ij"), -1
    ).reshape(-1, 2)
    frame = torch.cat((torch.zeros(5, 2, dtype=torch.long), grid))  # camera + 4 register tokens
    local = frame.expand(4, -1, -1)
    everything = local.reshape(1, -1, 2)

    def displaced(camera, adapter):
        with rt.apply(model, camera, adapter):
            state = rt.handle_of(model)._state
            return displace_grid_positions(local, state, 14), displace_grid_positions(
                everything, state, 14
            )

    rig_local, rig_global = displaced(cameras, adapters)
    singles = [displaced(cameras[v], adapters[v]) for v in range(2)]
    span = frame.shape[0]
    for view in range(4):
        single_local, single_global = singles[view % 2]
        assert torch.equal(rig_local[view], single_local[view])
        part = slice(view * span, (view + 1) * span)
        assert torch.equal(rig_global[0, part], single_global[0, part])
    assert not torch.equal(singles[0][0], singles[1][0])
    with rt.apply(model, cameras, adapters):
        state = rt.handle_of(model)._state
        with pytest.raises(InputError, match="2 cameras"):
            displace_grid_positions(frame.expand(3, -1, -1).reshape(1, -1, 2), state, 14)


# ---- refusals, before anything changes -------------------------------------------------------


def test_rig_refusals_leave_the_model_untouched():
    case, model, cameras, adapters = _rig("da3")
    height, width = case.size
    before = snapshot(model)
    with pytest.raises(AdapterError, match="2 cameras and 3 adapters"):
        rt.apply(model, cameras, adapters + [None])
    with pytest.raises(CameraError, match="aspect"):
        rt.apply(model, [cameras[0], fisheye(width, width, 190.0)], None)
    with pytest.raises(CameraError, match="empty camera list"):
        rt.apply(model, [], None)
    with pytest.raises(CameraError, match="one mask per camera"):
        rt.apply(model, cameras, adapters, mask=torch.ones(height, width, dtype=torch.bool))
    with pytest.raises(AdapterError, match="fitted on"):
        rt.apply(model, cameras, [adapters[1], adapters[0]])  # each adapter checks its camera
    assert rt.handle_of(model) is None
    assert_same_snapshot(model, before)


def test_a_hook_that_is_one_value_for_all_views_refuses_a_rig():
    case, model, cameras, adapters = _rig("pi3x")
    before = snapshot(model)
    with pytest.raises(InputError, match="prediction_grid"):
        rt.apply(model, cameras, adapters)
    assert rt.handle_of(model) is None
    assert_same_snapshot(model, before)
    with rt.apply(model, cameras, adapters, components=_components("pi3x")) as handle:
        assert handle.is_rig
