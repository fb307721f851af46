"""The PE-Jacobian analysis against fields whose Jacobian is known in closed form."""

from __future__ import annotations

import math

import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.analysis import (
    jacobian_of_field,
    pe_field,
    pe_jacobian,
    reference_curves,
    token_rho,
)
from raytun3r_plugin.cameras import fisheye


def test_a_linear_field_has_its_slopes_as_singular_values():
    h, w, channels = 9, 11, 6
    a = torch.zeros(channels, dtype=torch.float64)
    b = torch.zeros(channels, dtype=torch.float64)
    a[0], b[1], b[2] = 3.0, 1.2, 1.6  # |a| = 3, |b| = 2, a . b = 0
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    grid = xs[..., None] * a + ys[..., None] * b
    sigma1, area = jacobian_of_field(grid)
    assert torch.allclose(sigma1, torch.full_like(sigma1, 3.0))
    assert torch.allclose(area, torch.full_like(area, 6.0))


def test_rho_is_one_at_the_nearest_grid_edge():
    rho = token_rho(4, 6, 14, cx=(6 * 14 - 1) / 2, cy=(4 * 14 - 1) / 2)
    assert rho.shape == (4, 6)
    # The four centre tokens are 7 px off in x and y; the nearest grid edge is 28 px away.
    assert float(rho.min()) == pytest.approx(math.hypot(7, 7) / 28)
    assert float(rho[1, 0]) == pytest.approx(math.hypot(35, 7) / 28)


def test_the_equidistant_reference_is_sec_squared():
    camera = fisheye((224, 224), 180.0, "kb4", k=(0.0, 0.0, 0.0, 0.0))
    rho = torch.linspace(0.05, 0.8, 6, dtype=torch.float64)
    reference = reference_curves(camera, rho, 224, 224)
    edge = min(float(camera.cx) + 0.5, 224 - 0.5 - float(camera.cx))
    theta = rho * edge / float(camera.fx)
    assert torch.allclose(reference["sigma1"], 1 / theta.cos() ** 2, rtol=1e-3)
    assert torch.allclose(reference["area"], theta.tan() / theta / theta.cos() ** 2, rtol=1e-3)


pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_tiny_network  # noqa: E402


def _set_table(net, values):
    table = net.backbone.pretrained.pos_embed
    with torch.no_grad():
        table[0, 1:] = values.reshape(-1, table.shape[-1]).to(table.dtype)


def test_a_linear_pe_table_gives_flat_curves_through_the_backbones_interpolation():
    # Bicubic interpolation (Keys, a = -0.75) reproduces a linear table inside its border to
    # within a percent, so away from the edge the field's slope is the table's slope times the
    # resampling stretch (37 -> 36 tokens).
    net = build_tiny_network(seed=0)
    side = int(math.isqrt(net.backbone.pretrained.pos_embed.shape[1] - 1))
    channels = net.backbone.pretrained.embed_dim
    s = torch.arange(side, dtype=torch.float64)
    direction = torch.zeros(channels, dtype=torch.float64)
    direction[0] = 0.01
    _set_table(net, s[None, :, None] * direction + 0 * s[:, None, None])
    sigma1, _ = jacobian_of_field(pe_field(net, 504, 504))
    inner = sigma1[2:-2, 2:-2]
    stretch = side / (36 + 0.1)  # DINOv2 samples the table at (36 + 0.1) / 37 scale
    assert torch.allclose(inner, torch.full_like(inner, 0.01 * stretch), rtol=1e-2)
    curves = pe_jacobian(net, 504, 504)
    filled = curves.sigma1[curves.count > 0, 1]
    assert float(filled[0]) == pytest.approx(1.0)
    assert float((filled[:-2] - 1).abs().max()) < 0.02, "flat inside the border bins"


def test_an_adapter_radial_ramp_has_the_jacobian_of_rho():
    # With a zero table and pe.radial = rho_k v, the field is rho(x, y) v: its Jacobian is
    # v grad(rho), so sigma_1 = |v| / r_max everywhere off the centre, and the area is 0.
    net = build_tiny_network(seed=0)
    _set_table(net, torch.zeros(net.backbone.pretrained.pos_embed.shape[1] - 1, 64))
    camera = fisheye((224, 224), 190.0, "kb4")
    adapter = rt.Adapter.for_model(net, camera)
    v = torch.zeros(64)
    v[3] = 2.0
    n_r = adapter.n_r
    with torch.no_grad():
        adapter.pe["radial"].copy_(torch.linspace(0, 1, n_r)[:, None] * v)
    h = w = 224 // 14
    with rt.apply(net, camera, adapter, components=["pe"]):
        field = pe_field(net, 224, 224)
        curves = pe_jacobian(net, 224, 224, camera=camera)
    assert float(field[..., 3].abs().max()) > 0.5, "the adapter's correction reached the field"
    sigma1, area = jacobian_of_field(field)
    centre = ((w * 14 - 1) / 2, (h * 14 - 1) / 2)
    offsets = torch.stack(
        torch.meshgrid(
            (torch.arange(h) + 0.5) * 14 - 0.5 - centre[1],
            (torch.arange(w) + 0.5) * 14 - 0.5 - centre[0],
            indexing="ij",
        ),
        -1,
    )
    r_max = float(offsets.norm(dim=-1).max()) / 14
    ring = (offsets.norm(dim=-1) / 14 > 2.5) & (offsets.norm(dim=-1) / 14 < 6.5)
    assert torch.allclose(sigma1[ring], torch.full_like(sigma1[ring], 2.0 / r_max), rtol=0.03)
    assert float(area.max()) < 1e-6
    assert curves.scale["sigma1"] > 0
    unpatched = pe_jacobian(net, 224, 224, camera=camera)
    assert unpatched.scale["sigma1"] == 0.0, "removing the adapter restores the zero table"


def test_the_report_writes_a_csv_and_a_picture_with_every_curve(tmp_path):
    import csv

    import cv2

    from raytun3r_plugin.apps.analysis import jacobian_report

    net = build_tiny_network(seed=0)
    camera = fisheye((224, 224), 190.0, "kb4")
    adapter = rt.Adapter.for_model(net, camera)
    with torch.no_grad():
        adapter.pe["radial"].normal_(0, 0.05)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    report = jacobian_report(net, adapter, tmp_path / "out", size=224, bins=8)
    with open(report["csv"]) as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 8
    assert {"pretrained_sigma1", "adapted_sigma1", "reference_sigma1", "adapted_area_q75"} <= set(
        rows[0]
    )
    assert cv2.imread(str(report["png"])).shape[1] == 1280
    assert set(report["summary"]) == {"pretrained", "adapted"}
    assert report["summary"]["adapted"]["sigma1"] != report["summary"]["pretrained"]["sigma1"]
    assert rt.handle_of(net) is None
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())


def test_cli_analyze_jacobian_prints_the_curves_and_writes_the_files(tmp_path, capsys):
    from raytun3r_plugin.apps.cli import main
    from raytun3r_plugin.weights import load_backbone

    net = load_backbone("raytun3r-da3-tiny")
    adapter = rt.Adapter.for_model(net, fisheye((224, 224), 190.0, "kb4"))
    path = adapter.save(tmp_path / "a.safetensors")
    args = ["analyze", "jacobian", "--backbone", "raytun3r-da3-tiny", "--adapter", str(path)]
    code = main([*args, "--size", "112", "--bins", "4", "--out", str(tmp_path / "jac")])
    out = capsys.readouterr().out
    assert code == 0
    assert "pretrained" in out and "adapted" in out and "reference" in out
    assert (tmp_path / "jac" / "jacobian.csv").is_file()
    assert (tmp_path / "jac" / "jacobian.png").is_file()
