"""cameras.fisheye: the one constructor of the synthetic fisheye, bit-identical to the old hand-built lenses."""

from __future__ import annotations

import math

import pytest
import torch

from raytun3r_plugin.cameras import DoubleSphere, KannalaBrandt4, fisheye
from raytun3r_plugin.errors import CameraError


# The formulas the benchmark (benchmark.make_camera) and the demo (demo.demo_camera) used before
# the constructor existed, kept verbatim: the published benchmark numbers depend on every bit.
def _old_benchmark_kb4(size: int, fov_deg: float) -> KannalaBrandt4:
    half = math.radians(fov_deg / 2)
    centre = (size - 1) / 2
    k1 = 0.02
    focal = (size / 2) / (half * (1 + k1 * half**2))
    return KannalaBrandt4(
        size,
        size,
        {
            "fx": focal,
            "fy": focal,
            "cx": centre,
            "cy": centre,
            "k1": k1,
            "k2": 0.0,
            "k3": 0.0,
            "k4": 0.0,
        },
        max_fov_deg=fov_deg,
    )


def _old_benchmark_ds(size: int, fov_deg: float) -> DoubleSphere:
    half = math.radians(fov_deg / 2)
    centre = (size - 1) / 2
    xi, alpha = -0.15, 0.6
    x, z = math.sin(half), math.cos(half)
    k = xi * 1.0 + z
    d2 = math.sqrt(x * x + k * k)
    focal = (size / 2) / (x / (alpha * d2 + (1 - alpha) * k))
    return DoubleSphere(
        size,
        size,
        {"fx": focal, "fy": focal, "cx": centre, "cy": centre, "xi": xi, "alpha": alpha},
        max_fov_deg=fov_deg,
    )


def _old_demo(size: int) -> KannalaBrandt4:
    half = math.radians(95.0)
    focal = (size / 2) / (half * (1 + 0.02 * half**2))
    centre = (size - 1) / 2
    return KannalaBrandt4(
        size,
        size,
        {
            "fx": focal,
            "fy": focal,
            "cx": centre,
            "cy": centre,
            "k1": 0.02,
            "k2": 0.0,
            "k3": 0.0,
            "k4": 0.0,
        },
        max_fov_deg=190.0,
    )


def _assert_identical(a, b) -> None:
    assert type(a) is type(b)
    assert (a.width, a.height, a.max_fov_deg) == (b.width, b.height, b.max_fov_deg)
    assert a.params.dtype == b.params.dtype == torch.float64
    assert torch.equal(a.params, b.params), a.params - b.params
    assert a.to_json() == b.to_json()


@pytest.mark.parametrize("size", [56, 112, 113, 518])
def test_benchmark_and_demo_cameras_are_bit_identical_to_their_old_formulas(size):
    from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera
    from raytun3r_plugin.apps.demo import demo_camera

    old = {"kb4": _old_benchmark_kb4, "ds": _old_benchmark_ds}
    for spec in CAMERAS:
        _assert_identical(make_camera(spec, size), old[spec.model](size, spec.fov_deg))
    _assert_identical(demo_camera(size), _old_demo(size))


def test_the_boundary_ray_lands_on_the_requested_radius():
    for camera, radius in (
        (fisheye(112, 185.0), 56.0),
        (fisheye((96, 80), 195.0, "ds"), 40.0),
        (fisheye(100, 190.0, k=(0.01, -0.004, 0.0005, 0.0), radius_px=47.5), 47.5),
        (fisheye(64, 120.0, k=(0.0, 0.0, 0.0, 0.0)), 32.0),
        (fisheye(112, 185.0, "ucm"), 56.0),
        (fisheye((96, 80), 195.0, "eucm", alpha=0.62, beta=1.2), 40.0),
    ):
        half = math.radians(camera.max_fov_deg / 2)
        ray = torch.tensor([[math.sin(half), 0.0, math.cos(half)]], dtype=torch.float64)
        uv, ok = camera.project(ray)
        assert bool(ok[0])
        assert float(uv[0, 0] - camera.cx) == pytest.approx(radius, abs=1e-9)
        assert float(camera.cy) == (camera.height - 1) / 2


def test_the_new_lenses_are_the_unified_models_at_their_fields_of_view():
    from raytun3r_plugin.apps.benchmark import NEW_LENSES, make_camera
    from raytun3r_plugin.cameras import EUCM, UCM

    ucm, eucm = (make_camera(spec, 112) for spec in NEW_LENSES)
    assert isinstance(ucm, UCM) and isinstance(eucm, EUCM) and type(eucm) is not UCM
    assert (ucm.max_fov_deg, eucm.max_fov_deg) == (200.0, 210.0)
    assert float(eucm.params[eucm.param_names.index("beta")]) == pytest.approx(1.2)
    assert float(ucm.params[ucm.param_names.index("alpha")]) == pytest.approx(0.6)
    # The image circle fills the width, as for the benchmark's own lenses.
    for camera in (ucm, eucm):
        assert float(camera.valid_mask().float().mean()) == pytest.approx(math.pi / 4, abs=0.02)


def test_fisheye_refuses_bad_arguments():
    with pytest.raises(CameraError, match="model"):
        fisheye(64, 190.0, "pinhole")
    with pytest.raises(CameraError, match="alpha"):
        fisheye(64, 190.0, "ucm", alpha=1.5)
    with pytest.raises(CameraError, match="fov_deg"):
        fisheye(64, 0.0)
    with pytest.raises(CameraError, match="four"):
        fisheye(64, 190.0, k=(0.1,))
    with pytest.raises(CameraError, match="size"):
        fisheye((0, 64), 190.0)


def test_perturbed_changes_each_group_by_the_given_amount():
    import pytest

    from raytun3r_plugin.cameras import fisheye, perturbed
    from raytun3r_plugin.errors import CameraError

    camera = fisheye((120, 100), 190.0, "ds")
    rough = perturbed(camera, focal=0.05, principal=0.01, distortion=-0.1)
    p, q = camera.params, rough.params
    assert type(rough) is type(camera) and rough.max_fov_deg == camera.max_fov_deg
    assert float(q[0]) == pytest.approx(1.05 * float(p[0]))
    assert float(q[2]) == pytest.approx(float(p[2]) + 1.2)
    assert float(q[3]) == pytest.approx(float(p[3]) + 1.0)
    assert float(q[5]) == pytest.approx(0.9 * float(p[5]))
    assert perturbed(camera) == camera
    with pytest.raises(CameraError, match="focal must be a number in"):
        perturbed(camera, focal=2.0)
    with pytest.raises(CameraError):
        perturbed(fisheye((120, 100), 190.0, "ds", alpha=0.95), distortion=0.2)  # alpha > 1
