"""Camera models: gradients (gradcheck, finite on the axis, to the parameters), batching over
leading dimensions, float32 against float64, and the image helpers (ray tables, crops, scaling)."""

from __future__ import annotations

import math

import pytest
import torch

from raytun3r_plugin.cameras import (
    Camera,
    KannalaBrandt4,
    Pinhole,
)
from raytun3r_plugin.errors import CameraError
from tests.camera_cases import (
    CAMS,
    NAMES,
    TUMVI_KB4,
    directions,
    make_cameras,
)


# ----------------------------------------------------------------------------- gradients
def _probe_points(cam: Camera) -> torch.Tensor:
    return directions(3, 0.8 * min(cam.max_angle, 2.0), seed=10, min_angle=0.2)


@pytest.mark.parametrize("name", NAMES)
def test_gradcheck_project(name):
    cam = CAMS[name]
    X = _probe_points(cam).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: cam.project(x)[0], (X,))
    params = cam.params.clone().requires_grad_(True)
    X0 = X.detach()
    assert torch.autograd.gradcheck(
        lambda p: type(cam)(cam.width, cam.height, p).project(X0)[0], (params,)
    )


@pytest.mark.parametrize("name", NAMES)
def test_gradcheck_unproject(name):
    cam = CAMS[name]
    uv = cam.project(_probe_points(cam))[0].detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: cam.unproject(q)[0], (uv,))
    params = cam.params.clone().requires_grad_(True)
    uv0 = uv.detach()
    assert torch.autograd.gradcheck(
        lambda p: type(cam)(cam.width, cam.height, p).unproject(uv0)[0], (params,)
    )


@pytest.mark.parametrize("name", NAMES)
def test_gradients_finite_on_axis(name):
    cam = CAMS[name]
    params = cam.params.clone().requires_grad_(True)
    c = type(cam)(cam.width, cam.height, params)
    X = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    uv = c.project(X)[0]
    pp = c.params[2:4].detach().clone().reshape(1, 2).requires_grad_(True)
    rays = c.unproject(pp)[0]
    (uv.sum() + rays.sum()).backward()
    assert (
        torch.isfinite(X.grad).all()
        and torch.isfinite(pp.grad).all()
        and torch.isfinite(params.grad).all()
    )
    # At the principal point the ray is the axis, and the analytic Jacobian there matches a
    # central difference (the series branches near the axis must carry the right derivative).
    torch.testing.assert_close(
        rays.detach(), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), rtol=0, atol=1e-12
    )
    q0 = pp.detach()
    j = torch.autograd.functional.jacobian(lambda q: cam.unproject(q)[0], q0)[0, :, 0, :]
    h = 1e-4
    for k in range(2):
        e = torch.zeros(1, 2, dtype=torch.float64)
        e[0, k] = h
        fd = (cam.unproject(q0 + e)[0] - cam.unproject(q0 - e)[0])[0] / (2 * h)
        torch.testing.assert_close(j[:, k], fd, rtol=1e-6, atol=1e-10)
    jp = torch.autograd.functional.jacobian(lambda x: cam.project(x)[0], X.detach()[:1])[0, :, 0, :]
    assert (
        abs(
            float(jp[0, 0])
            - float(
                cam.project(torch.tensor([[1e-6, 0.0, 2.0]], dtype=torch.float64))[0][0, 0]
                - cam.values["cx"]
            )
            / 1e-6
        )
        < 1e-4
    )


def test_params_gradient_reaches_leaf():
    leaf = torch.tensor(TUMVI_KB4, dtype=torch.float64, requires_grad=True)
    cam = KannalaBrandt4(512, 512, leaf)
    assert cam.requires_grad
    rays, _ = cam.ray_table(dtype=torch.float64)  # not cached: it carries the graph
    assert rays.requires_grad
    rays[..., 2].sum().backward()
    assert leaf.grad is not None and torch.isfinite(leaf.grad).all() and leaf.grad[0] != 0
    assert cam.ray_table(dtype=torch.float64)[0] is not rays
    # Parameters given as a float32 tensor are stored as float64.
    assert (
        KannalaBrandt4(512, 512, torch.tensor(TUMVI_KB4, dtype=torch.float32)).params.dtype
        == torch.float64
    )


# ----------------------------------------------------------------------------- batching, dtypes
@pytest.mark.parametrize("name", NAMES)
def test_batching_over_leading_dims(name):
    cam = CAMS[name]
    X = directions(4 * 2 * 3, 0.9 * min(cam.max_angle, 2.0), seed=11).reshape(2, 3, 4, 3)
    uv, valid = cam.project(X)
    assert uv.shape == (2, 3, 4, 2) and valid.shape == (2, 3, 4)
    uv_flat, _ = cam.project(X.reshape(-1, 3))
    torch.testing.assert_close(uv.reshape(-1, 2), uv_flat, rtol=0, atol=0)
    rays, valid = cam.unproject(uv)
    assert rays.shape == (2, 3, 4, 3) and valid.shape == (2, 3, 4)
    torch.testing.assert_close(rays.reshape(-1, 3), cam.unproject(uv_flat)[0], rtol=0, atol=0)
    # A single point (no batch dims).
    assert cam.project(X[0, 0, 0])[0].shape == (2,)


@pytest.mark.parametrize("name", NAMES)
def test_float32_agrees_with_float64(name):
    cam = CAMS[name]
    r32, v32 = cam.ray_table(dtype=torch.float32)
    r64, v64 = cam.ray_table(dtype=torch.float64)
    assert r32.dtype == torch.float32
    both = v32 & v64
    assert (v32 != v64).sum() <= 2  # only pixels on the domain boundary may differ
    torch.testing.assert_close(r32[both].double(), r64[both], rtol=0, atol=2e-5)
    X = directions(50, 0.9 * min(cam.max_angle, 2.0), seed=12)
    torch.testing.assert_close(
        cam.project(X.float())[0].double(), cam.project(X)[0], rtol=1e-5, atol=1e-3
    )
    with pytest.raises(CameraError):
        cam.project(torch.zeros(4, 2))
    with pytest.raises(CameraError):
        cam.unproject(torch.zeros(4, 3))


# ----------------------------------------------------------------------------- image helpers
def test_ray_table_cache_and_valid_mask():
    cam = make_cameras()["mei"]
    a = cam.ray_table()
    assert cam.ray_table() is a
    assert cam.ray_table(dtype=torch.float64) is not a
    assert cam.ray_table(device="cpu") is a
    assert a[0].shape == (cam.height, cam.width, 3) and a[1].shape == (cam.height, cam.width)
    mask = cam.valid_mask()
    assert mask.dtype == torch.bool and mask.shape == (cam.height, cam.width)
    assert torch.equal(mask, cam.ray_table(dtype=torch.float64)[1])
    assert cam.valid_mask() is mask
    # Pixel (u, v) of the table is the ray of pixel centre (u, v).
    r, _ = cam.unproject(torch.tensor([[17.0, 42.0]]))
    torch.testing.assert_close(a[0][42, 17], r[0])


def test_fov_deg():
    pin = Pinhole(200, 100, [100.0, 100.0, 99.5, 49.5])
    corner = math.degrees(math.atan(math.hypot(99.5, 49.5) / 100.0))
    assert math.isclose(pin.fov_deg, 2 * corner, rel_tol=1e-12)
    assert CAMS["kb4"].fov_deg > 180.0


@pytest.mark.parametrize("name", NAMES)
def test_crop_and_scale_keep_rays(name):
    cam = CAMS[name]
    g = torch.Generator().manual_seed(13)
    uv = torch.rand(300, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [cam.width - 1.0, cam.height - 1.0]
    )
    rays, valid = cam.unproject(uv)
    crop = cam.cropped(13, 7, 150, 120)
    assert (crop.width, crop.height) == (150, 120)
    r2, v2 = crop.unproject(uv - torch.tensor([13.0, 7.0], dtype=torch.float64))
    assert torch.equal(valid, v2) and valid.sum() > 200
    torch.testing.assert_close(r2[valid], rays[valid], rtol=0, atol=1e-12)
    for sx, sy in [(0.5, 0.5), (2.0, 2.0), (0.7, 1.3)]:
        sc = cam.scaled(sx, sy)
        assert (sc.width, sc.height) == (round(cam.width * sx), round(cam.height * sy))
        uv_s = (uv + 0.5) * torch.tensor([sx, sy], dtype=torch.float64) - 0.5
        r3, v3 = sc.unproject(uv_s)
        assert torch.equal(valid, v3)
        torch.testing.assert_close(r3[valid], rays[valid], rtol=0, atol=1e-10)
    rs = cam.resized(100, 80)
    assert (rs.width, rs.height) == (100, 80)
    assert math.isclose(rs.values["cx"], (cam.values["cx"] + 0.5) * 100 / cam.width - 0.5)
    # Scaling keeps the lens cap; the grid of a 2x resize covers the same field of view.
    assert cam.scaled(2.0, 2.0).max_angle == cam.max_angle


def test_scaled_is_differentiable():
    leaf = torch.tensor(TUMVI_KB4, dtype=torch.float64, requires_grad=True)
    cam = KannalaBrandt4(512, 512, leaf).resized(256, 256).cropped(10, 10, 200, 200)
    cam.fx.backward()
    assert float(leaf.grad[0]) == 0.5
