"""Camera models: exactness against independent references, round trips, domains, identity,
JSON and validation (gradients, batching and image helpers: test_cameras_differentiable.py)."""

from __future__ import annotations

import math
import pickle

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin.cameras import (
    CAMERA_MODELS,
    EUCM,
    FOV,
    MEI,
    UCM,
    Camera,
    DoubleSphere,
    Fisheye624,
    KannalaBrandt4,
    OpenCVRadTan,
    Pinhole,
    ThinPrismFisheye,
    from_dict,
)
from raytun3r_plugin.errors import CameraError, Raytun3rError
from tests.camera_cases import (
    CAMS,
    KITTI360_02,
    NAMES,
    TUMVI_DS,
    TUMVI_KB4,
    directions,
    ref_project,
    small_camera,
)


def test_registry_names():
    assert set(CAMERA_MODELS) == {
        "pinhole",
        "opencv",
        "kb4",
        "ucm",
        "eucm",
        "ds",
        "mei",
        "thin_prism_fisheye",
        "fov",
        "fisheye624",
    }
    assert KannalaBrandt4.param_names == ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    for cls in CAMERA_MODELS.values():
        assert cls.param_names[:4] == ("fx", "fy", "cx", "cy")
    assert issubclass(CameraError, Raytun3rError)


# ----------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("name", NAMES)
def test_project_matches_reference(name):
    cam = CAMS[name]
    # Reference formulas of the perspective-based models only exist in front of the camera.
    lim = min(
        cam.max_angle,
        math.radians(89)
        if name in ("pinhole", "opencv", "thin_prism_fisheye", "fov", "fisheye624")
        else 10.0,
    )
    X = directions(500, 0.98 * lim, seed=1, min_angle=1e-3)
    uv, valid = cam.project(X)
    assert valid.all()
    ref = ref_project(cam, X.numpy())
    np.testing.assert_allclose(uv.numpy(), ref, rtol=0, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_kb4_matches_cv2_fisheye_full_resolution():
    cam = KannalaBrandt4(512, 512, TUMVI_KB4)
    X = directions(2000, math.radians(85), seed=2)
    uv, valid = cam.project(X)
    p = cam.values
    K = np.array([[p["fx"], 0, p["cx"]], [0, p["fy"], p["cy"]], [0, 0, 1.0]])
    D = np.array([p["k1"], p["k2"], p["k3"], p["k4"]])
    ref, _ = cv2.fisheye.projectPoints(X.numpy().reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    assert valid.all()
    err = np.abs(uv.numpy() - ref.reshape(-1, 2)).max()
    assert err < 1e-6, err


def test_special_cases_agree_across_models():
    X = directions(300, math.radians(85), seed=3)
    base = [150.0, 151.0, 99.5, 80.5]

    def proj(c):
        return c.project(X)[0]

    ucm = UCM(200, 160, [*base, 0.6])
    torch.testing.assert_close(
        proj(EUCM(200, 160, [*base, 0.6, 1.0])), proj(ucm), rtol=0, atol=1e-10
    )
    torch.testing.assert_close(
        proj(DoubleSphere(200, 160, [*base, 0.0, 0.6])), proj(ucm), rtol=0, atol=1e-10
    )
    xi = 0.6 / 0.4  # MEI without distortion is UCM in the xi form
    mei = MEI(200, 160, [base[0] * (1 + xi), base[1] * (1 + xi), 99.5, 80.5, xi, 0, 0, 0, 0])
    torch.testing.assert_close(proj(mei), proj(ucm), rtol=0, atol=1e-10)
    tp = ThinPrismFisheye(200, 160, [*base] + [0.0] * 8)
    torch.testing.assert_close(
        proj(tp), proj(KannalaBrandt4(200, 160, [*base, 0, 0, 0, 0])), rtol=0, atol=1e-10
    )
    torch.testing.assert_close(
        proj(OpenCVRadTan(200, 160, [*base, 0, 0, 0, 0])),
        proj(Pinhole(200, 160, base)),
        rtol=0,
        atol=1e-10,
    )
    # Equidistant: a ray at 90 degrees lands at f * pi / 2 from the principal point.
    uv, ok = KannalaBrandt4(200, 160, [*base, 0, 0, 0, 0]).project(
        torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    )
    assert ok and abs(float(uv[0]) - (99.5 + 150.0 * math.pi / 2)) < 1e-12


# ----------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 1e-3)])
@pytest.mark.parametrize("name", NAMES)
def test_pixel_round_trip_every_valid_pixel(name, dtype, tol):
    cam = CAMS[name]
    uv = cam.pixel_grid(dtype=dtype)
    rays, valid = cam.unproject(uv)
    assert rays.dtype == dtype and rays.shape == (cam.height, cam.width, 3)
    assert torch.isfinite(rays).all()
    torch.testing.assert_close(
        rays.norm(dim=-1), torch.ones_like(rays[..., 0]), rtol=0, atol=10 * torch.finfo(dtype).eps
    )
    # Most of each test image is inside the model's domain.
    assert valid.float().mean() > 0.8
    uv2, valid2 = cam.project(rays)
    assert valid2[valid].all()
    err = (uv2 - uv).norm(dim=-1)[valid].max().item()
    assert err < tol, (name, err)


@pytest.mark.parametrize("name", NAMES)
def test_ray_round_trip(name):
    cam = CAMS[name]
    X = directions(2000, 0.995 * cam.max_angle, seed=4)
    uv, valid = cam.project(X)
    assert valid.all()
    rays, valid2 = cam.unproject(uv)
    assert valid2.all()
    torch.testing.assert_close(rays, X / X.norm(dim=-1, keepdim=True), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_invalid_outside_domain_and_finite(name):
    cam = CAMS[name]
    if cam.max_angle < math.pi - 1e-9:
        X = directions(200, math.pi, seed=5, min_angle=cam.max_angle + 1e-3)
        uv, valid = cam.project(X)
        assert not valid.any()
        assert torch.isfinite(uv).all()
    # The zero vector has no direction.
    uv, valid = cam.project(torch.zeros(3, dtype=torch.float64))
    assert not valid and torch.isfinite(uv).all()
    # Far outside the image circle: invalid for models with a bounded image, always finite.
    far = torch.tensor([[1e4, -3e4], [-5e5, 2e5]], dtype=torch.float64)
    rays, valid = cam.unproject(far)
    assert torch.isfinite(rays).all()
    if name in ("kb4", "mei", "eucm", "ds", "thin_prism_fisheye"):
        assert not valid.any()


# ----------------------------------------------------------------------------- FoV edges
@pytest.mark.parametrize(
    "cam",
    [
        KannalaBrandt4(512, 512, TUMVI_KB4, max_fov_deg=195.0),
        DoubleSphere(512, 512, TUMVI_DS, max_fov_deg=195.0),
    ],
    ids=["kb4", "ds"],
)
def test_195_degree_cameras_beyond_90_degrees(cam):
    assert math.isclose(cam.max_angle, math.radians(97.5))
    free = type(cam)(cam.width, cam.height, cam.params)  # same lens without the cap
    az = torch.tensor([0.25, 0.75, 1.25, 1.75], dtype=torch.float64) * math.pi  # image diagonals

    def rays_at(deg):
        th = torch.full_like(az, math.radians(deg))
        return torch.stack([th.sin() * az.cos(), th.sin() * az.sin(), th.cos()], -1)

    inside = rays_at(96.0)
    uv, valid = cam.project(inside)
    assert valid.all()
    assert ((uv >= 0) & (uv <= 511)).all()  # visible in the image
    rays, valid = cam.unproject(uv)
    assert valid.all() and (rays[:, 2] < 0).all()
    torch.testing.assert_close(rays, inside, rtol=0, atol=1e-9)
    outside = rays_at(99.0)
    assert not cam.project(outside)[1].any()
    uv_out, ok = free.project(outside)
    assert ok.all() and free.unproject(uv_out)[1].all()
    assert not cam.unproject(uv_out)[1].any()
    mask = cam.valid_mask()
    assert mask.shape == (512, 512) and mask.dtype == torch.bool
    assert mask[256, 256] and not mask[0, 0] and not mask[511, 511]
    assert 194.0 < cam.fov_deg <= 195.0


def test_double_sphere_natural_domain():
    cam = DoubleSphere(512, 512, TUMVI_DS)
    p = cam.values
    # Exact boundary on the unit sphere (the fold of the projection); see DoubleSphere docs.
    w1 = (1 - p["alpha"]) / p["alpha"]
    q = 1 - w1 * w1
    z_b = -p["xi"] * q - w1 * math.sqrt(1 - p["xi"] ** 2 * q)
    assert math.isclose(cam.max_angle, math.acos(z_b), rel_tol=1e-12)
    assert math.degrees(cam.max_angle) > 125.0  # far beyond 90 degrees
    X_in = directions(100, cam.max_angle - 1e-4, seed=6, min_angle=cam.max_angle - 0.05)
    X_out = directions(100, cam.max_angle + 0.05, seed=7, min_angle=cam.max_angle + 1e-4)
    assert cam.project(X_in)[1].all()
    assert not cam.project(X_out)[1].any()
    # Unprojection domain: r2 < 1 / (2 alpha - 1) in normalised coordinates.
    r_lim = math.sqrt(1 / (2 * p["alpha"] - 1))
    r = torch.tensor([0.999 * r_lim, 1.001 * r_lim], dtype=torch.float64)
    uv = torch.stack([p["cx"] + p["fx"] * r, torch.full_like(r, p["cy"])], -1)
    rays, valid = cam.unproject(uv)
    assert valid.tolist() == [True, False]
    assert rays[0, 2] < -0.5  # ~125 degrees from the axis


def test_kb4_fold_limits_domain():
    # k1 < 0 makes theta_d(theta) fold at 1 + 3 k1 theta^2 = 0.
    k1 = -0.05
    cam = KannalaBrandt4(400, 400, [60.0, 60.0, 199.5, 199.5, k1, 0, 0, 0])
    fold = math.sqrt(-1 / (3 * k1))
    assert math.isclose(cam.max_angle, fold, rel_tol=1e-12)
    td_max = fold * (1 + k1 * fold**2)
    uv = torch.tensor(
        [[199.5 + 60 * td_max * 0.999, 199.5], [199.5 + 60 * td_max * 1.001, 199.5]],
        dtype=torch.float64,
    )
    rays, valid = cam.unproject(uv)
    assert valid.tolist() == [True, False]
    assert math.acos(rays[0, 2]) < fold
    assert cam.project(directions(50, fold - 1e-6, seed=8))[1].all()
    assert not cam.project(directions(50, math.pi, seed=9, min_angle=fold + 1e-6))[1].any()


def test_mei_kitti360_lens_circle():
    cam = MEI(1400, 1400, KITTI360_02)
    assert math.isclose(math.degrees(cam.max_angle), 116.86, abs_tol=0.01)  # pi - acos(1/xi)
    small = small_camera(cam, 200, 200)
    mask = small.valid_mask()
    assert mask[100, 100] and not mask[0, 0] and not mask[199, 0] and not mask[0, 199]
    # The mask is the image of the fold circle (tangential terms shift it by < 1 px).
    xi, k1, k2 = 2.2134047507854890, 0.016798235660113681, 1.6548773243373522
    rho = 1 / math.sqrt(xi * xi - 1)
    rd = rho * (1 + k1 * rho**2 + k2 * rho**4) * small.values["fx"]
    v, u = torch.meshgrid(torch.arange(200.0), torch.arange(200.0), indexing="ij")
    r = torch.hypot(u - small.values["cx"], v - small.values["cy"])
    assert mask[r < rd - 1].all() and not mask[r > rd + 1].any()
    assert 230.0 < small.fov_deg < 2 * math.degrees(cam.max_angle)


def test_thin_prism_only_front_hemisphere():
    cam = ThinPrismFisheye(
        200, 200, [40.0, 40.0, 99.5, 99.5, 0.01, 0, 1e-3, 1e-3, 0, 0, 1e-3, 1e-3]
    )
    assert cam.max_angle == math.pi / 2
    rays, valid = cam.ray_table(dtype=torch.float64)
    assert valid.any() and not valid.all()
    assert (rays[valid][:, 2] > 0).all()
    assert not cam.project(torch.tensor([1.0, 0.0, -0.01], dtype=torch.float64))[1]


def test_fov_image_circle_beyond_90_degrees_and_pinhole_limit():
    omega, f = 1.9, 30.0
    cam = FOV(200, 200, [f, f, 99.5, 99.5, omega])
    assert cam.max_angle == math.pi
    # basalt's atan2 form of the model: the same as COLMAP's in front, and defined behind.
    points = directions(300, math.radians(175), seed=5, min_angle=math.radians(95))
    x, y, z = points.unbind(-1)
    rho = torch.hypot(x, y)
    rd = torch.atan2(2 * math.tan(omega / 2) * rho, z) / (rho * omega)
    uv, valid = cam.project(points)
    assert valid.all() and torch.allclose(
        uv, torch.stack([f * x * rd + 99.5, f * y * rd + 99.5], -1), atol=1e-9
    )
    # 90 degrees lands on the circle of radius f pi / (2 omega), 180 on f pi / omega: inside
    # that circle every pixel has a ray, the ones beyond 90 degrees point backwards.
    rays, valid = cam.ray_table(dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(200.0), torch.arange(200.0), indexing="ij")
    r = torch.hypot(u - 99.5, v - 99.5)
    edge = f * math.pi / omega
    assert valid[r < edge - 0.5].all() and not valid[r > edge + 0.5].any()
    assert (rays[r < f * math.pi / (2 * omega) - 0.5][:, 2] > 0).all() and (
        rays[valid & (r > f * math.pi / (2 * omega) + 0.5)][:, 2] < 0
    ).all()
    assert not cam.project(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))[1]
    # A small omega is almost a pinhole: factor atan(c r) / (omega r) -> 1.
    near_pinhole = FOV(200, 200, [f, f, 99.5, 99.5, 1e-4])
    points = directions(50, math.radians(60), seed=3)
    uv, _ = near_pinhole.project(points)
    uv_pinhole, _ = Pinhole(200, 200, [f, f, 99.5, 99.5]).project(points)
    assert torch.allclose(uv, uv_pinhole, atol=1e-5)


def test_fisheye624_without_prism_terms_is_kb4_in_front():
    ks = [0.02, -0.01, 0.003, -0.0004]
    f624 = Fisheye624(
        200, 200, [60.0, 61.0, 99.5, 100.5, *ks, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    )
    kb4 = KannalaBrandt4(200, 200, [60.0, 61.0, 99.5, 100.5, *ks])
    points = directions(200, math.radians(85), seed=4)
    uv, valid = f624.project(points)
    uv_kb, _ = kb4.project(points)
    assert valid.all() and torch.allclose(uv, uv_kb, atol=1e-9)
    # The prism / tangential stage moves pixels; unprojection undoes it.
    tilted = Fisheye624(
        200, 200, [60.0, 61.0, 99.5, 100.5, *ks, 0.0, 0.0, 2e-3, -1e-3, 1e-3, 5e-4, -8e-4, 2e-4]
    )
    uv_t, _ = tilted.project(points)
    assert (uv_t - uv).abs().max() > 0.05
    rays, ok = tilted.unproject(uv_t)
    assert ok.all() and torch.allclose(rays, points / points.norm(dim=-1, keepdim=True), atol=1e-9)
    assert not tilted.project(torch.tensor([1.0, 0.0, -0.01], dtype=torch.float64))[1]


# ----------------------------------------------------------------------------- identity, JSON
@pytest.mark.parametrize("name", NAMES)
def test_json_round_trip_exact(name):
    cam = CAMS[name]
    back = Camera.from_json(cam.to_json())
    assert type(back) is type(cam) and back == cam and hash(back) == hash(cam)
    assert torch.equal(back.params, cam.params)
    assert back.to_json() == cam.to_json()
    assert from_dict(cam.to_dict()) == cam
    assert pickle.loads(pickle.dumps(cam)) == cam


def test_json_floats_exact_and_format():
    cam = KannalaBrandt4(
        512,
        512,
        [0.1 + 0.2, 1 / 3, 255.5, 2**-30, 1e-300, -1.2345678901234567e-7, 0, 5e-324],
        max_fov_deg=195,
    )
    d = cam.to_dict()
    assert d == {
        "model": "kb4",
        "width": 512,
        "height": 512,
        "params": dict(zip(cam.param_names, cam.params.tolist(), strict=True)),
        "max_fov_deg": 195.0,
    }
    back = KannalaBrandt4.from_json(cam.to_json())
    assert (
        back.values["fx"] == 0.1 + 0.2 and back.values["k4"] == 5e-324 and back.max_fov_deg == 195.0
    )
    with pytest.raises(CameraError, match="expected a 'pinhole' camera"):
        Pinhole.from_json(cam.to_json())
    assert "max_fov_deg" not in CAMS["kb4"].to_dict()


def test_identity_and_repr():
    a = KannalaBrandt4(1400, 1400, [700.0, 700.0, 699.5, 699.5, 0.01, 0.0, 0.0, 0.0])
    b = KannalaBrandt4(
        1400,
        1400,
        {"fx": 700.0, "fy": 700.0, "cx": 699.5, "cy": 699.5, "k1": 0.01, "k2": 0, "k3": 0, "k4": 0},
    )
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    assert a.key() == ("kb4", 1400, 1400, (700.0, 700.0, 699.5, 699.5, 0.01, 0.0, 0.0, 0.0), None)
    assert a != KannalaBrandt4(1400, 1400, [700.0, 700.0, 699.5, 699.5, 0.01, 0.0, 0.0, 1e-12])
    assert a != a.cropped(0, 0, 1400, 1399)
    assert a != KannalaBrandt4(1400, 1400, a.params, max_fov_deg=190)
    assert (
        repr(a)
        == "KannalaBrandt4(1400x1400, fx=700, fy=700, cx=699.5, cy=699.5, k1=0.01, k2=0, k3=0, k4=0)"
    )
    assert float(a.fx) == 700.0 and float(a.cy) == 699.5 and a.fx.ndim == 0
    with pytest.raises(AttributeError):
        a.width = 3
    with pytest.raises(TypeError):
        Camera(10, 10, [1.0, 1.0, 0.0, 0.0])


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "cls,params,field",
    [
        (Pinhole, [-1.0, 1.0, 0.0, 0.0], "fx"),
        (Pinhole, [1.0, 0.0, 0.0, 0.0], "fy"),
        (Pinhole, [1.0, 1.0, float("nan"), 0.0], "cx"),
        (KannalaBrandt4, [1.0, 1.0, 0.0, 0.0, 0.0, float("inf"), 0.0, 0.0], "k2"),
        (UCM, [1.0, 1.0, 0.0, 0.0, 1.5], "alpha"),
        (UCM, [1.0, 1.0, 0.0, 0.0, -0.1], "alpha"),
        (EUCM, [1.0, 1.0, 0.0, 0.0, 0.5, 0.0], "beta"),
        (EUCM, [1.0, 1.0, 0.0, 0.0, 1.2, 1.0], "alpha"),
        (DoubleSphere, [1.0, 1.0, 0.0, 0.0, 1.5, 0.5], "xi"),
        (DoubleSphere, [1.0, 1.0, 0.0, 0.0, 0.0, 2.0], "alpha"),
        (MEI, [1.0, 1.0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0], "xi"),
        (FOV, [1.0, 1.0, 0.0, 0.0, 0.0], "omega"),
        (FOV, [1.0, 1.0, 0.0, 0.0, math.pi], "omega"),
    ],
)
def test_parameter_validation_names_the_parameter(cls, params, field):
    with pytest.raises(CameraError, match=f"'{field}'") as ei:
        cls(10, 10, params)
    assert ei.value.param == field


def test_parameter_count_and_names():
    with pytest.raises(CameraError, match="expected 8 parameters"):
        KannalaBrandt4(10, 10, [1.0] * 9)
    with pytest.raises(CameraError, match="'k4' is missing"):
        KannalaBrandt4(10, 10, {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "k1": 0, "k2": 0, "k3": 0})
    with pytest.raises(CameraError, match="unexpected parameter 'k5'"):
        Pinhole(10, 10, {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "k5": 0})
    for w in (0, -1, 2.5, True, "10"):
        with pytest.raises(CameraError, match="width"):
            Pinhole(w, 10, [1, 1, 0, 0])
    with pytest.raises(CameraError, match="max_fov_deg"):
        Pinhole(10, 10, [1, 1, 0, 0], max_fov_deg=0)
    with pytest.raises(CameraError, match="unknown camera model"):
        from_dict({"model": "fisheye9", "width": 1, "height": 1, "params": {}})
    with pytest.raises(CameraError, match="'params.fx'"):
        from_dict(
            {
                "model": "pinhole",
                "width": 1,
                "height": 1,
                "params": {"fx": -1, "fy": 1, "cx": 0, "cy": 0},
            }
        )
    with pytest.raises(CameraError, match="unexpected field 'extra'"):
        from_dict({**CAMS["pinhole"].to_dict(), "extra": 1})


@pytest.mark.parametrize("n_k,prism", [(1, False), (2, False), (4, True)])
def test_distortion_jacobians(n_k, prism):
    from raytun3r_plugin.cameras._math import RadTan

    g = torch.Generator().manual_seed(14)
    ks = (0.3 * torch.randn(n_k, generator=g, dtype=torch.float64)).tolist()
    s = (1e-3, -2e-3) if prism else (None, None)
    dist = RadTan(ks, 1.3e-3, -7e-4, *s)
    xy = 0.7 * torch.randn(2, 50, generator=g, dtype=torch.float64)
    xd, yd, a, b, c, d = dist.with_jacobian(*xy)
    for got, ref in zip(dist.with_jacobian_fast(*xy), (xd, yd, a, b, c, d), strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(torch.stack([xd, yd]), torch.stack(dist(*xy)), rtol=0, atol=1e-15)
    for i in range(3):  # against autograd's Jacobian of the distortion itself
        jac = torch.autograd.functional.jacobian(lambda p: torch.stack(dist(p[0], p[1])), xy[:, i])
        ref = torch.tensor([[a[i], b[i]], [c[i], d[i]]], dtype=torch.float64)
        torch.testing.assert_close(jac, ref, rtol=1e-12, atol=1e-12)
