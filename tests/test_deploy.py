"""Deployment for one camera and input size: the frozen model, the ONNX graph, ``raytun3r export``
(docs/deployment.md).

The default suite freezes every supported backbone in eager mode (fast) and writes three ONNX
graphs through the command line, checked with ONNX Runtime against the eager patched model:
the built-in network, Pi3's stub (its SVD replaced) and the tiny nested DA3 model (its masked
alignment replaced; tests/test_deploy_equivalents.py checks both replacements against
upstream); the other graphs (da3-small with random weights, VGGT's stub, three views) are
``-m slow``: each export traces the whole model (20 s to a minute here)."""

from __future__ import annotations

import copy
import math

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.deploy import SUPPORTED, freeze
from raytun3r_plugin.deploy.frozen import BUFFER_PREFIX, fixed_size_rope
from raytun3r_plugin.errors import InputError, UnsupportedUpstreamError
from raytun3r_plugin.prediction import imagenet_normalise
from tests.backbones import CASE, make
from tests.helpers import fisheye, max_relative_difference, outputs, randomise_

#: ONNX Runtime against the eager patched model (issue 41).
DEPTH_TOLERANCE = 1e-4  # max relative depth difference
POSE_TOLERANCE_RAD = 1e-4


def _tiny(family: str):
    if family == "da3nested":
        pytest.importorskip("depth_anything_3")
        from raytun3r_plugin.patches.da3_networks import build_tiny_nested_network

        return build_tiny_nested_network(), (70, 84)
    case = CASE[family]
    pytest.importorskip(case.package)
    return make(family), case.size


def _patched(family: str):
    net, (height, width) = _tiny(family)
    camera = fisheye(width, height)
    rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))
    return net, (height, width)


def _images(size, views=2, seed=5):
    return torch.rand(1, views, 3, *size, generator=torch.Generator().manual_seed(seed))


def _frozen_outputs(frozen, images) -> dict:
    with torch.no_grad():
        depth, confidence, pose = frozen(images)
    return {"depth": depth, "pose": pose}


def rotation_angle(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest angle (rad) between the rotations of two (..., 4, 4) pose stacks."""
    difference = torch.linalg.matrix_norm((a - b)[..., :3, :3].double())
    return float((2 * torch.asin((difference / (2 * math.sqrt(2))).clamp(max=1))).max())


# ---------------------------------------------------------------------------------------------
# The fixed-size RoPE: upstream's, bit for bit
# ---------------------------------------------------------------------------------------------


def test_fixed_size_rope_is_upstream_rope_bit_for_bit():
    """DA3's RoPE sizes its tables by ``int(positions.max()) + 1`` (data-dependent); the frozen
    one uses constant tables of upstream's own method for the largest position of the size."""
    net, (height, width) = _tiny("da3")
    vit = net.backbone.pretrained
    rope = vit.rope
    pos, pos_nodiff = vit._prepare_rope(1, 2, height, width, "cpu")
    pos, pos_nodiff = pos.flatten(0, 1), pos_nodiff.flatten(0, 1)
    tokens = torch.randn(2, 2, pos.shape[1], 32, generator=torch.Generator().manual_seed(0))
    count = int(pos.max()) + 1
    cos, sin = rope._compute_frequency_components(16, count, tokens.device, tokens.dtype)
    rope.register_buffer("c", cos.clone(), persistent=False)
    rope.register_buffer("s", sin.clone(), persistent=False)
    for positions in (pos, pos_nodiff):
        frozen = fixed_size_rope(
            rope,
            tokens,
            positions,
            cos="c",
            sin="s",
            apply_1d="_apply_1d_rope",
            base=rope.base_frequency,
            displacement=None,
            columns=width // 14,
        )
        assert torch.equal(frozen, rope(tokens, positions))


# ---------------------------------------------------------------------------------------------
# The frozen model
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", SUPPORTED)
def test_frozen_model_is_the_patched_model(family, monkeypatch):
    net, size = _patched(family)
    images = _images(size)
    expected = outputs(net, images)
    frozen = freeze(net, size, views=2)
    # The model it was frozen from keeps its patch and its outputs.
    assert rt.handle_of(net) is not None
    assert max_relative_difference(expected, outputs(net, images)) == 0.0
    # No raytun3r wrapper, handle or patch state in the frozen copy; constants are buffers.
    for module in frozen.modules():
        assert not any(hasattr(v, "__raytun3r_wrapper__") for v in vars(module).values())
    assert rt.handle_of(frozen.network) is None
    names = [name for name, _ in frozen.named_buffers() if BUFFER_PREFIX in name]
    assert any("interpolate_pos_encoding" in name for name in names)
    assert any("resample_grid" in name for name in names)
    # It runs without the camera model, the geometry cache or the adapter.
    from raytun3r_plugin import adapter, size_geometry

    def refuse(*args, **kwargs):
        raise AssertionError("the frozen model called raytun3r's camera code")

    monkeypatch.setattr(size_geometry.GeometryCache, "at", refuse)
    monkeypatch.setattr(adapter.Adapter, "pe_correction", refuse)
    got = _frozen_outputs(frozen, images)
    assert max_relative_difference({k: expected[k] for k in got}, got) < 1e-6


def test_frozen_model_keeps_the_turned_resampling():
    """The frozen grid is the one the live patch uses, also with the ``resample_turned`` switch."""
    net, (height, width) = _tiny("da3")
    camera = fisheye(width, height)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    images = _images((height, width))
    rt.apply(net, camera, adapter)
    central = outputs(net, images)
    rt.remove(net)
    rt.apply(net, camera, adapter, components=[*COMPONENTS, "resample_turned"])
    turned = outputs(net, images)
    assert max_relative_difference(central, turned) > 1e-4
    got = _frozen_outputs(freeze(net, (height, width), views=2), images)
    assert max_relative_difference({k: turned[k] for k in got}, got) < 1e-6


def test_unpatched_freeze_is_upstream():
    """The baseline of the cost comparison: the same freeze of a plain model is upstream's."""
    net, size = _tiny("da3")
    images = _images(size)
    expected = outputs(net, images)
    frozen = freeze(net, size, views=2)
    got = _frozen_outputs(frozen, images)
    assert max_relative_difference({k: expected[k] for k in got}, got) == 0.0
    assert not frozen.info["patched"]


def test_frozen_model_refuses_another_shape():
    net, size = _patched("da3")
    frozen = freeze(net, size, views=2)
    with pytest.raises(InputError, match="frozen for images of shape"):
        frozen(_images(size, views=3))


@pytest.mark.parametrize("family", ["pi3x", "vggt_omega"])
def test_backbones_without_a_frozen_form_are_refused(family):
    net, size = _patched(family)
    with pytest.raises(UnsupportedUpstreamError, match=f"{family} cannot be frozen for export: "):
        freeze(net, size, views=2)


def test_rig_and_bad_size_are_refused_before_any_copy():
    net, (height, width) = _tiny("da3")
    cameras = [fisheye(width, height), fisheye(width, height, 150.0)]
    with rt.apply(net, cameras):
        with pytest.raises(InputError, match="rig"):
            freeze(net, (height, width), views=2)
    with pytest.raises(InputError, match="multiple of the patch size 14"):
        freeze(net, (height + 1, width), views=2)


def test_onnx_export_of_a_blocked_backbone_is_refused_with_the_reason(tmp_path, monkeypatch):
    """``ONNX_BLOCKERS`` is empty today; a family listed there is refused before any file."""
    pytest.importorskip("onnx")
    from raytun3r_plugin.deploy import export_onnx, onnx

    monkeypatch.setitem(onnx.ONNX_BLOCKERS, "da3", "a reason")
    net, size = _patched("da3")
    frozen = freeze(net, size, views=2)
    with pytest.raises(UnsupportedUpstreamError, match="da3 cannot be exported to ONNX: a reason"):
        export_onnx(frozen, tmp_path / "model.onnx")
    assert not list(tmp_path.iterdir())


def test_frozen_pi3_and_nested_da3_run_the_export_equivalents():
    """Pi3's SVD and nested DA3's masked quantiles are replaced in the frozen copy only
    (tests/test_deploy_equivalents.py checks them against upstream)."""
    for family, replaced in (
        ("pi3", ["CameraHead.svd_orthogonalize"]),
        (
            "da3nested",
            [
                "DepthAnything3Net._process_mono_sky_estimation",
                "NestedDepthAnything3Net._apply_depth_alignment",
                "NestedDepthAnything3Net._handle_sky_regions",
            ],
        ),
    ):
        net, size = _patched(family)
        frozen = freeze(net, size, views=2)
        assert frozen.info["replaced"] == replaced
        for module in net.modules():  # the model it was frozen from runs upstream's code
            assert not any(name.split(".")[1] in vars(module) for name in replaced)


def _sky_mixed(net, images, sky_fraction: float = 0.3):
    """Make the tiny nested model's metric sky head call about ``sky_fraction`` of the pixels
    sky (the built model has none), so every masked path of the alignment runs."""
    conv = net.da3_metric.head.scratch.sky_output_conv2[-1]
    seen = []
    hook = conv.register_forward_hook(lambda module, args, output: seen.append(output.detach()))
    with torch.no_grad():
        conv.weight.mul_(100.0)  # the random head's logits spread over a few 0.01
        outputs(net, images)
        hook.remove()
        logits = seen[-1] - conv.bias.view(1, -1, 1, 1)
        conv.bias.fill_(0.3 - float(torch.quantile(logits.flatten(), 1 - sky_fraction)))
    return net


def test_frozen_nested_da3_with_sky_is_upstreams():
    """Sky in the metric branch: the frozen alignment and sky handling against upstream's,
    equal but for the least-squares scale's float32 summation order (1e-6)."""
    net, size = _patched("da3nested")
    images = _images(size)
    _sky_mixed(net, images)
    frozen = freeze(net, size, views=2)
    for seed in (5, 6, 7):
        images = _images(size, seed=seed)
        expected = outputs(net, images)
        with torch.no_grad():
            sky = net.da3_metric(imagenet_normalise(images))["sky"] >= 0.3
        assert 0.05 < float(sky.float().mean()) < 0.95
        got = _frozen_outputs(frozen, images)
        assert max_relative_difference({k: expected[k] for k in got}, got) < 1e-6


# ---------------------------------------------------------------------------------------------
# ONNX Runtime against the eager patched model
# ---------------------------------------------------------------------------------------------


def _assert_onnx_parity(path, net, size, views=2):
    from raytun3r_plugin.deploy import run_onnx

    images = _images(size, views=views, seed=9)
    with torch.no_grad():
        expected = rt.predict(net, images)
    got = run_onnx(path, images)
    relative = (got["depth"] - expected.depth).abs() / expected.depth.abs().clamp(min=1e-6)
    assert float(relative.max()) < DEPTH_TOLERANCE
    assert rotation_angle(got["cam_from_world"], expected.cam_from_world) < POSE_TOLERANCE_RAD
    translation = (got["cam_from_world"] - expected.cam_from_world)[..., :3, 3].abs().max()
    assert float(translation) < 1e-4 * max(1.0, float(expected.cam_from_world.abs().max()))
    return got


def test_cli_export_of_the_built_in_network_matches_eager_in_onnx_runtime(tmp_path, capsys):
    """``raytun3r export`` end to end, then ONNX Runtime (CPU) against the eager patched model."""
    pytest.importorskip("onnxruntime")
    from raytun3r_plugin.apps.cli import main

    net = rt.load_backbone("raytun3r-da3-tiny-v3")
    size = (112, 112)
    camera = fisheye(112, 112)
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    path = adapter.save(tmp_path / "cam0.safetensors")
    out = tmp_path / "cam0.onnx"
    code = main(
        [
            "export",
            "--backbone",
            "raytun3r-da3-tiny-v3",
            "--adapter",
            str(path),
            "--size",
            "112",
            "112",
            "--views",
            "2",
            "--format",
            "onnx",
            "--out",
            str(out),
        ]
    )
    assert code == 0 and out.is_file()
    assert "wrote" in capsys.readouterr().out
    rt.apply(net, None, rt.Adapter.load(path))
    _assert_onnx_parity(out, net, size)
    # The graph holds the corrections: the unpatched model gives other depths.
    plain = rt.load_backbone("raytun3r-da3-tiny-v3")
    images = _images(size, seed=9)
    with torch.no_grad():
        unpatched = rt.predict(plain, images).depth
    from raytun3r_plugin.deploy import run_onnx

    assert float((run_onnx(out, images)["depth"] - unpatched).abs().max()) > 1e-3


def test_cli_export_needs_a_camera(tmp_path, capsys):
    from raytun3r_plugin.apps.cli import main

    code = main(
        [
            "export",
            "--backbone",
            "raytun3r-da3-tiny-v3",
            "--size",
            "112",
            "112",
            "--out",
            str(tmp_path / "x.onnx"),
        ]
    )
    assert code == 2 and "needs --adapter" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def _cli_export(tmp_path, family, net, size, monkeypatch, capsys):
    """``raytun3r export`` of the tiny ``net`` (patched with a random adapter saved to a file):
    ``load_backbone`` hands the CLI an unpatched copy, as loading the weights would."""
    from raytun3r_plugin.apps.cli import main

    pristine = copy.deepcopy(net)
    camera = fisheye(size[1], size[0])
    adapter = randomise_(rt.Adapter.for_model(net, camera))
    path = adapter.save(tmp_path / "cam0.safetensors")
    monkeypatch.setattr(rt, "load_backbone", lambda name, weights=None: copy.deepcopy(pristine))
    out = tmp_path / f"{family}.onnx"
    arguments = ["export", "--backbone", family, "--adapter", str(path), "--size", *map(str, size)]
    assert main([*arguments, "--views", "2", "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    rt.apply(net, None, rt.Adapter.load(path))
    return out


def test_cli_export_of_pi3_matches_eager_in_onnx_runtime(tmp_path, monkeypatch, capsys):
    """Pi3's stub with tiny random weights: the graph holds no SVD, and ONNX Runtime gives the
    eager patched model's depth and pose (whose rotations come from upstream's SVD)."""
    pytest.importorskip("onnxruntime")
    import onnx

    net, size = _tiny("pi3")
    out = _cli_export(tmp_path, "pi3", net, size, monkeypatch, capsys)
    operators = {node.op_type.lower() for node in onnx.load(str(out)).graph.node}
    assert not any("svd" in name for name in operators)
    _assert_onnx_parity(out, net, size)


def test_cli_export_of_nested_da3_matches_eager_in_onnx_runtime(tmp_path, monkeypatch, capsys):
    """The tiny nested model with sky in its metric branch: the masked quantiles traced, and
    ONNX Runtime against the eager patched model (upstream's masked alignment)."""
    pytest.importorskip("onnxruntime")
    net, size = _tiny("da3nested")
    _sky_mixed(net, _images(size, seed=9))
    out = _cli_export(tmp_path, "da3nested", net, size, monkeypatch, capsys)
    got = _assert_onnx_parity(out, net, size)
    with torch.no_grad():
        sky = net.da3_metric(imagenet_normalise(_images(size, seed=9)))["sky"] >= 0.3
    assert 0.05 < float(sky.float().mean()) < 0.95
    assert torch.isfinite(got["depth"]).all()


@pytest.mark.slow
@pytest.mark.parametrize("family", ["da3", "vggt"])
def test_onnx_export_of_a_tiny_patched_model(family, tmp_path):
    pytest.importorskip("onnxruntime")
    from raytun3r_plugin.deploy import export_onnx

    net, size = _patched(family)
    path = export_onnx(freeze(net, size, views=2), tmp_path / f"{family}.onnx")
    _assert_onnx_parity(path, net, size)


@pytest.mark.slow
def test_onnx_export_with_three_views_and_reference_view_selection(tmp_path):
    """From 3 views DA3 picks a reference view from the tokens (a data-dependent reorder)."""
    pytest.importorskip("onnxruntime")
    from raytun3r_plugin.deploy import export_onnx

    net, size = _patched("da3")
    path = export_onnx(freeze(net, size, views=3), tmp_path / "three.onnx")
    _assert_onnx_parity(path, net, size, views=3)


@pytest.mark.slow
def test_onnx_export_of_da3_small_with_random_weights(tmp_path):
    pytest.importorskip("onnxruntime")
    from raytun3r_plugin.patches.da3_networks import build_network

    from raytun3r_plugin.deploy import export_onnx

    torch.manual_seed(0)
    net = build_network("da3-small").eval()
    with torch.no_grad():  # DA3 leaves its PE table at zero: give the PE hook something to act on
        torch.nn.init.trunc_normal_(net.backbone.pretrained.pos_embed, std=0.02)
    size = (280, 280)
    camera = fisheye(*size)
    rt.apply(net, camera, randomise_(rt.Adapter.for_model(net, camera)))
    path = export_onnx(freeze(net, size, views=2), tmp_path / "small.onnx")
    _assert_onnx_parity(path, net, size)


def test_deepcopy_of_a_frozen_model_runs_its_own_buffers():
    net, size = _patched("da3")
    frozen = freeze(net, size, views=2)
    twin = copy.deepcopy(frozen)
    images = _images(size)
    assert (
        max_relative_difference(_frozen_outputs(frozen, images), _frozen_outputs(twin, images))
        == 0.0
    )
    method = vars(twin.network.backbone.pretrained)["interpolate_pos_encoding"]
    assert method.owner is twin.network.backbone.pretrained
