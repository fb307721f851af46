"""The export-friendly equivalents a frozen model runs in place of upstream code that ONNX cannot
express (docs/deployment.md, docs/decisions.md "Export equivalents of Pi3's SVD and nested DA3's
masked quantiles"):

* :func:`raytun3r_plugin.deploy.rotation.closest_rotation` against upstream Pi3's
  ``CameraHead.svd_orthogonalize`` (the stub mirrors upstream's code: ``torch.svd`` of the
  transpose, the det sign on the last singular vector), on realistic and adversarial matrices;
* :mod:`raytun3r_plugin.deploy.metric_alignment` against the installed ``depth_anything_3``'s
  own methods, bit for bit where the arithmetic is the same;
* both traced alone into small ONNX graphs and run in ONNX Runtime (a few seconds each).
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from raytun3r_plugin.deploy.metric_alignment import (
    INSUFFICIENT_NON_SKY,
    frozen_depth_alignment,
    frozen_mono_sky_estimation,
    frozen_sky_regions,
    masked_quantile,
)
from raytun3r_plugin.deploy.rotation import closest_rotation, frozen_svd_orthogonalize

#: |R - R_svd| (largest entry) <= ROTATION_TOLERANCE / gap, gap = s2 + sign(det) s3 of the
#: row-normalised matrix: the rotation's own condition (upstream's float32 SVD is off the
#: float64 answer by the same order, measured 2.7e-6 / gap).
ROTATION_TOLERANCE = 5e-6
#: The least-squares scale sums the masked whole tensor, upstream the compacted pixels: float32
#: rounding of a different summation order (measured up to 1.2e-7 relative).
SCALE_TOLERANCE = 1e-6


# ---------------------------------------------------------------------------------------------
# The closest rotation (Pi3's camera head)
# ---------------------------------------------------------------------------------------------


def _upstream_orthogonalize():
    pytest.importorskip("pi3")
    from pi3.models.layers.camera_head import CameraHead

    return CameraHead(dim=8).svd_orthogonalize


def _random_orthogonal(count: int, generator) -> torch.Tensor:
    q = torch.linalg.qr(torch.randn(count, 3, 3, generator=generator, dtype=torch.float64))[0]
    return q * torch.det(q)[:, None, None]  # det +1


def _matrices() -> dict[str, torch.Tensor]:
    """(N, 9) float32 inputs of the camera head: realistic and adversarial."""
    g = torch.Generator().manual_seed(0)
    count = 2000
    rotation = _random_orthogonal(count, g)
    reflection = rotation @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    u, v = _random_orthogonal(count, g), _random_orthogonal(count, g)

    def spectrum(*values):
        return u @ torch.diag(torch.tensor(values, dtype=torch.float64)) @ v.transpose(-1, -2)

    cases = {
        "gaussian (an untrained head)": torch.randn(count, 3, 3, generator=g),
        "noisy rotations (a trained head)": rotation + 0.1 * torch.randn(count, 3, 3, generator=g),
        "exact rotations": rotation,
        "negative determinant": spectrum(1.0, 0.6, -0.3),
        "rank deficient": spectrum(1.0, 0.5, 0.0),
        "ill-conditioned": spectrum(1.0, 1e-3, 1e-6),
        "two tiny singular values": spectrum(1.0, 1e-4, 1e-4),
        "scaled far from 1": 1e4 * torch.randn(count, 3, 3, generator=g),
    }
    for noise in (1e-1, 1e-2, 1e-3, 1e-4):
        cases[f"near-reflections, noise {noise:g}"] = reflection + noise * torch.randn(
            count, 3, 3, generator=g, dtype=torch.float64
        )
    return {name: m.float().reshape(-1, 9) for name, m in cases.items()}


def _gap(m: torch.Tensor) -> torch.Tensor:
    """s2 + sign(det) s3 of each row-normalised matrix: how well the rotation is determined."""
    normalised = F.normalize(m.reshape(-1, 3, 3).double(), p=2, dim=-1)
    s = torch.linalg.svdvals(normalised)
    return s[:, 1] + torch.sign(torch.det(normalised)) * s[:, 2]


def _largest_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a.double() - b.double()).abs().amax(dim=(-2, -1))


def test_closest_rotation_is_upstreams_svd_orthogonalisation():
    upstream = _upstream_orthogonalize()
    for name, m in _matrices().items():
        expected = upstream(m.clone())
        got = frozen_svd_orthogonalize(None, m.clone())
        assert got.dtype == torch.float32 and got.shape == (m.shape[0], 3, 3)
        # A proper rotation, always (the SVD path's det fix, with no branch).
        identity = torch.eye(3, dtype=torch.float64)
        assert float((got.double() @ got.double().mT - identity).abs().max()) < 1e-5, name
        assert float((torch.det(got.double()) - 1).abs().max()) < 1e-5, name
        # Upstream's rotation, to the rotation's own conditioning.
        scaled = _largest_error(got, expected) * _gap(m)
        assert float(scaled.max()) <= ROTATION_TOLERANCE, (name, float(scaled.max()))
    realistic = _matrices()["noisy rotations (a trained head)"]
    assert (
        float(_largest_error(frozen_svd_orthogonalize(None, realistic), upstream(realistic)).max())
        < 3e-6
    )


def test_negative_determinant_flips_the_smallest_singular_direction():
    """An independent float64 computation of the convention: U diag(1, 1, -1) V^T for det < 0."""
    g = torch.Generator().manual_seed(3)
    m = torch.randn(500, 3, 3, generator=g, dtype=torch.float64)
    m = m * torch.sign(torch.det(m))[:, None, None] * -1  # every determinant negative (3x3)
    u, _, vh = torch.linalg.svd(m)
    expected = u @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)) @ vh
    got = closest_rotation(m)
    scaled = _largest_error(got, expected) * _gap(m)  # rows not normalised here: same maximiser
    assert float(scaled.max()) < 1e-9
    # Upstream's orthogonalisation of the same matrices agrees (it normalises rows first).
    upstream = _upstream_orthogonalize()
    assert (
        float((_largest_error(frozen_svd_orthogonalize(None, m), upstream(m)) * _gap(m)).max())
        < 1e-9
    )


def test_closest_rotation_of_the_zero_matrix_is_the_identity_as_with_the_svd():
    upstream = _upstream_orthogonalize()
    zero = torch.zeros(1, 9)
    assert torch.equal(upstream(zero), torch.eye(3)[None])
    assert torch.equal(frozen_svd_orthogonalize(None, zero), torch.eye(3)[None])


class _Orthogonalize(nn.Module):
    def forward(self, m: torch.Tensor) -> torch.Tensor:
        return frozen_svd_orthogonalize(self, m)


def _onnx_session(module: nn.Module, example: tuple, path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from raytun3r_plugin.deploy.onnx import onnx_session

    program = torch.onnx.export(
        module.eval(), example, dynamo=True, opset_version=18, verbose=False
    )
    program.save(str(path), external_data=False)
    return onnx_session(path)


def test_closest_rotation_in_onnx_runtime(tmp_path):
    """No SVD in the graph; ONNX Runtime gives upstream's rotations to the same tolerance."""
    import onnx

    upstream = _upstream_orthogonalize()
    cases = _matrices()
    stacked = torch.cat(list(cases.values()))
    session = _onnx_session(_Orthogonalize(), (stacked,), tmp_path / "rotation.onnx")
    operators = {node.op_type for node in onnx.load(str(tmp_path / "rotation.onnx")).graph.node}
    assert not any("svd" in name.lower() for name in operators)
    got = torch.from_numpy(session.run(None, {session.get_inputs()[0].name: stacked.numpy()})[0])
    eager = frozen_svd_orthogonalize(None, stacked)
    start = 0
    for name, m in cases.items():
        piece = got[start : start + len(m)]
        start += len(m)
        scaled = _largest_error(piece, upstream(m)) * _gap(m)
        assert float(scaled.max()) <= ROTATION_TOLERANCE, (name, float(scaled.max()))
    # And the eager equivalent, to float32 rounding amplified by the same conditioning.
    scaled = _largest_error(got, eager) * _gap(stacked)
    assert float(scaled.max()) <= ROTATION_TOLERANCE


# ---------------------------------------------------------------------------------------------
# The masked quantile and nested DA3's metric alignment
# ---------------------------------------------------------------------------------------------


def test_masked_quantile_is_torch_quantile_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    for trial in range(300):
        n = int(torch.randint(1, 3000, (1,), generator=g))
        values = torch.randn(n, generator=g) * 10 ** float(torch.randint(-3, 4, (1,), generator=g))
        if trial % 3 == 0:
            values = values.round()  # ties
        mask = torch.rand(n, generator=g) < float(torch.rand(1, generator=g))
        mask[int(torch.randint(0, n, (1,), generator=g))] = True
        for q in (0.0, 0.25, 0.5, 0.99, 1.0):
            expected = torch.quantile(values[mask], q)
            assert torch.equal(masked_quantile(values, mask, q), expected), (trial, q)
    # Upstream's shapes: (B, S, H, W) values and mask; infinities selected or not.
    values = torch.rand(1, 2, 7, 9, generator=g)
    values[0, 0, 0, :3] = float("inf")
    mask = torch.rand(1, 2, 7, 9, generator=g) < 0.6
    for q in (0.0, 0.5, 0.99):  # 0.99 lands between two infinities: NaN in both
        expected = torch.quantile(values[mask], q)
        got = masked_quantile(values, mask, q)
        assert torch.equal(got, expected) or bool(got.isnan() & expected.isnan())
    # A selected NaN gives NaN (as torch.quantile); an unselected one is ignored.
    values = torch.tensor([1.0, float("nan"), 3.0])
    assert torch.isnan(masked_quantile(values, torch.tensor([True, True, False]), 0.5))
    assert torch.equal(
        masked_quantile(values, torch.tensor([True, False, True]), 0.5), torch.tensor(2.0)
    )
    # An empty selection (torch.quantile raises): NaN.
    assert torch.isnan(masked_quantile(values, torch.zeros(3, dtype=torch.bool), 0.5))


def _nested_owner():
    pytest.importorskip("depth_anything_3")
    from depth_anything_3.model.da3 import DepthAnything3Net, NestedDepthAnything3Net

    def bare(klass):
        module = klass.__new__(klass)
        nn.Module.__init__(module)  # upstream's methods under test read nothing from self
        return module

    return bare(NestedDepthAnything3Net), bare(DepthAnything3Net)


def _outputs(seed: int, sky_fraction: float, shape=(1, 2, 14, 18)):
    """Upstream's two output dicts (addict) with a sky map of about ``sky_fraction`` sky."""
    from addict import Dict

    g = torch.Generator().manual_seed(seed)
    batch, views = shape[:2]
    depth = 0.5 + 4 * torch.rand(shape, generator=g)
    depth.view(-1)[:5] = 1e-4  # below upstream's min depth: left out of the fit
    extrinsics = torch.randn(batch, views, 3, 4, generator=g)
    output = Dict(depth=depth, depth_conf=1 + torch.rand(shape, generator=g), extrinsics=extrinsics)
    output.depth_conf.view(-1)[7:40] = 1.5  # ties at the median
    sky = torch.where(
        torch.rand(shape, generator=g) < sky_fraction, torch.tensor(0.9), torch.tensor(0.1)
    )
    metric = Dict(depth=300 * torch.rand(shape, generator=g), sky=sky)
    return output, metric


def _copy(output):
    return copy.deepcopy(output)


def _upstream_alignment(nested, output, metric):
    output = nested._apply_depth_alignment(output, metric)
    return nested._handle_sky_regions(output, metric)


def _frozen_alignment(nested, output, metric):
    output = frozen_depth_alignment(nested, output, metric)
    return frozen_sky_regions(nested, output, metric)


@pytest.mark.parametrize("sky_fraction", [0.0, 0.3, 0.9])
def test_nested_alignment_is_upstreams(sky_fraction):
    nested, _ = _nested_owner()
    for seed in range(20):
        output, metric = _outputs(seed, sky_fraction)
        expected = _upstream_alignment(nested, _copy(output), _copy(metric))
        got = _frozen_alignment(nested, _copy(output), _copy(metric))
        non_sky = metric.sky < 0.3
        # Sky pixels: upstream's 0.99 quantile (capped at 200) of the scaled depth, conf 1.
        assert torch.equal(got.depth_conf, expected.depth_conf)
        scale = got.depth[non_sky] / output.depth[non_sky]
        expected_scale = expected.depth[non_sky] / output.depth[non_sky]
        assert float((scale / expected_scale - 1).abs().max()) <= SCALE_TOLERANCE
        relative = (got.depth - expected.depth).abs() / expected.depth
        assert float(relative.max()) <= SCALE_TOLERANCE
        translation = got.extrinsics[..., :3, 3] - expected.extrinsics[..., :3, 3]
        assert float(translation.abs().max()) <= SCALE_TOLERANCE * float(
            expected.extrinsics[..., :3, 3].abs().max()
        )
        assert torch.equal(got.extrinsics[..., :3, :3], expected.extrinsics[..., :3, :3])
        assert got.is_metric == 1 and "scale_factor" not in got


def test_nested_alignment_quantiles_are_bit_for_bit_given_upstreams_scale():
    """With the scale out of the way (depth already aligned), every value is upstream's."""
    nested, _ = _nested_owner()
    for seed in range(10):
        output, metric = _outputs(seed, 0.3)
        expected = nested._handle_sky_regions(_copy(output), _copy(metric))
        got = frozen_sky_regions(nested, _copy(output), _copy(metric))
        assert torch.equal(got.depth, expected.depth) and torch.equal(
            got.depth_conf, expected.depth_conf
        )
    # The 200 m cap (Python's min(quantile, 200.0) upstream).
    output, metric = _outputs(0, 0.3)
    output.depth = output.depth * 1000
    expected = nested._handle_sky_regions(_copy(output), _copy(metric))
    got = frozen_sky_regions(nested, _copy(output), _copy(metric))
    assert torch.equal(got.depth, expected.depth) and float(got.depth.max()) > 200


def test_too_few_non_sky_pixels_raise_upstreams_assertion():
    nested, _ = _nested_owner()
    output, metric = _outputs(0, 1.0)
    metric.sky.view(-1)[:10] = 0.0  # exactly 10 non-sky pixels: upstream needs more than 10
    with pytest.raises(AssertionError, match=INSUFFICIENT_NON_SKY):
        nested._apply_depth_alignment(_copy(output), _copy(metric))
    with pytest.raises(AssertionError, match=INSUFFICIENT_NON_SKY):
        frozen_depth_alignment(nested, _copy(output), _copy(metric))


@pytest.mark.parametrize("sky_pixels", [None, 0, 5, 10, 11, 252, 493, 494, 504])
def test_mono_sky_estimation_is_upstreams_bit_for_bit(sky_pixels):
    """The metric branch's own sky handling, with upstream's count rules at their edges
    (504 pixels: more than 10 sky and more than 10 non-sky needed)."""
    _, network = _nested_owner()
    output, metric = _outputs(1, 0.0)
    if sky_pixels is not None:
        sky = torch.zeros_like(metric.sky)
        sky.view(-1)[
            torch.randperm(sky.numel(), generator=torch.Generator().manual_seed(2))[:sky_pixels]
        ] = 0.8
        output.sky = sky
    expected = network._process_mono_sky_estimation(_copy(output))
    got = frozen_mono_sky_estimation(network, _copy(output))
    assert torch.equal(got.depth, expected.depth)


class _Alignment(nn.Module):
    """Nested DA3's alignment alone, traced: (depth, conf, extrinsics, metric depth, sky) in."""

    def __init__(self, nested: nn.Module):
        super().__init__()
        self.nested = nested

    def forward(self, depth, conf, extrinsics, metric_depth, sky):
        from addict import Dict

        output = Dict(depth=depth, depth_conf=conf, extrinsics=extrinsics)
        metric = Dict(depth=metric_depth, sky=sky)
        output = _frozen_alignment(self.nested, output, metric)
        return output.depth, output.depth_conf, output.extrinsics


def test_nested_alignment_in_onnx_runtime(tmp_path):
    """The traced alignment: upstream's values in ONNX Runtime, and NaN where upstream raises."""
    nested, _ = _nested_owner()
    names = ("depth", "depth_conf", "extrinsics")

    def inputs(output, metric):
        return (output.depth, output.depth_conf, output.extrinsics, metric.depth, metric.sky)

    session = _onnx_session(_Alignment(nested), inputs(*_outputs(0, 0.3)), tmp_path / "a.onnx")
    feed_names = [item.name for item in session.get_inputs()]

    def run(output, metric):
        arrays = session.run(
            None, dict(zip(feed_names, (t.numpy() for t in inputs(output, metric)), strict=True))
        )
        return dict(zip(names, (torch.from_numpy(a) for a in arrays), strict=True))

    for seed, fraction in ((1, 0.0), (2, 0.3), (3, 0.9)):
        output, metric = _outputs(seed, fraction)
        expected = _upstream_alignment(nested, _copy(output), _copy(metric))
        got = run(output, metric)
        relative = (got["depth"] - expected.depth).abs() / expected.depth
        assert float(relative.max()) < 1e-5
        assert torch.equal(got["depth_conf"], expected.depth_conf)
        scale = float(expected.extrinsics.abs().max())
        assert float((got["extrinsics"] - expected.extrinsics).abs().max()) < 1e-5 * scale
    # At most 10 non-sky pixels: upstream (and the eager equivalent) raise; a graph cannot.
    output, metric = _outputs(4, 1.0)
    got = run(output, metric)
    assert torch.isnan(got["depth"]).all() and torch.isnan(got["extrinsics"][..., :3, 3]).all()
