"""Cameras are validated when they are built (issue 16, cameras; docs/cameras.md, "What a
camera accepts"): bounds, domain boundaries, the float64 round trip, the error type for any
bad input, and that an accepted camera never breaks the patched forward."""

from __future__ import annotations

import math

import pytest
import torch

from raytun3r_plugin import cameras as C
from raytun3r_plugin.errors import CameraError, Raytun3rError

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# Real calibrations (rounded) that must stay accepted: if a bound refuses one, loosen the bound.
REAL = {
    # Kalibr equidistant, TUM-VI 512 x 512, about 190 degrees.
    "kalibr_eq_190": lambda: C.KannalaBrandt4(
        512, 512, [190.978, 190.973, 254.932, 256.897, 0.00348, 0.000715, -0.00205, 0.000203]
    ),
    # Intel RealSense T265 fisheye (KB4, 848 x 800).
    "t265": lambda: C.KannalaBrandt4(
        848, 800, [286.18, 286.39, 416.94, 403.32, -0.0101, 0.0456, -0.0428, 0.0082]
    ),
    # ScanNet++ DSLR, COLMAP OPENCV_FISHEYE.
    "scannetpp_dslr": lambda: C.KannalaBrandt4(
        1752, 1168, [789.9, 791.0, 879.8, 584.5, -0.0295, -0.0057, -0.0015, 0.0005]
    ),
    # KITTI-360 image_02, MEI with xi = 2.21.
    "kitti360_mei": lambda: C.MEI(
        1400, 1400, [1336.7, 1335.7, 716.9, 705.8, 2.2134, 0.01612, 1.4016, 0.00049, -0.0016]
    ),
    # Kalibr omni + radtan with xi about 1.
    "omni_xi_1": lambda: C.MEI(752, 480, [740.0, 740.0, 376.0, 240.0, 1.05, -0.2, 0.05, 0, 0]),
    # Basalt double sphere, TUM-VI.
    "basalt_ds_tumvi": lambda: C.DoubleSphere(
        512, 512, [158.28, 158.27, 254.73, 256.59, -0.1697, 0.5846]
    ),
    # Project Aria, Fisheye624 (SLAM camera).
    "aria_f624": lambda: C.Fisheye624(
        640,
        480,
        [241.6, 241.6, 316.6, 237.2, -0.0253, 0.0964, -0.0701, 0.0111, 0.00163, -0.00036]
        + [0.00058, -0.00028, -0.00069, 0.00012, 0.00016, -0.00005],
    ),
    "eucm": lambda: C.EUCM(640, 480, [300.0, 300.0, 320.0, 240.0, 0.63, 1.05]),
    "ucm": lambda: C.UCM(640, 480, [300.0, 300.0, 320.0, 240.0, 0.6]),
    "fov_tango": lambda: C.FOV(640, 480, [255.0, 255.0, 320.0, 240.0, 0.92]),
    "opencv": lambda: C.OpenCVRadTan(640, 480, [500, 500, 320, 240, -0.28, 0.07, 1e-4, -2e-4]),
    "thin_prism": lambda: C.ThinPrismFisheye(
        752, 480, [360, 360, 376, 240, 0.03, -0.01, 1e-4, 1e-4, 0.001, 0, 1e-4, -1e-4]
    ),
}


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_calibrations_are_accepted_and_round_trip(name):
    camera = REAL[name]()
    assert C.validate(camera) < 1e-6
    assert bool(camera.valid_mask().any())


# ------------------------------------------------------------------------ the fuzz findings
@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: C.KannalaBrandt4(64, 64, [30, 30, 32, 32, 1e300, 0, 0, 0]), "k1"),
        (lambda: C.KannalaBrandt4(64, 64, [30, 30, 32, 32, -1e300, 0, 0, 0]), "k1"),
        (lambda: C.KannalaBrandt4(64, 64, [30, 30, 32, 32, 0, 0, 0, 1e300]), "k4"),
        (lambda: C.Pinhole(64, 64, [1e-310, 30, 32, 32]), "fx"),
        (lambda: C.Pinhole(64, 64, [30, 2e6, 32, 32]), "fy"),
        (lambda: C.MEI(64, 64, [30, 30, 32, 32, 1e300, 0, 0, 0, 0]), "xi"),
        (lambda: C.Pinhole(10**400, 64, [30, 30, 32, 32]), "width"),
        (lambda: C.Pinhole(64, -(10**400), [30, 30, 32, 32]), "height"),
        (lambda: C.Pinhole(100000, 100000, [30, 30, 32, 32]), "width"),
        (lambda: C.Pinhole(64, 64, [30, 30, 1e10, 32]), "cx"),
        (lambda: C.Pinhole(64, 64, [30, 30, 32, -1e10]), "cy"),
        (lambda: C.Pinhole(64, 64, [10**400, 30, 32, 32]), "fx"),
        (lambda: C.Pinhole(64, 64, {"fx": 30, "fy": 30, "cx": 10**400, "cy": 32}), "cx"),
        (lambda: C.Pinhole(64, 64, [30, 30, 32, 32], max_fov_deg=10**400), "max_fov_deg"),
        (lambda: C.DoubleSphere(64, 64, [30, 30, 32, 32, -1.0, 0.6]), "xi"),
        (lambda: C.EUCM(64, 64, [30, 30, 32, 32, 0.6, 1e300]), "beta"),
    ],
)
def test_fuzz_findings_are_refused(build, match):
    with pytest.raises(CameraError, match=match):
        build()


def test_kb4_with_k1_1000_is_refused_naming_model_pixel_and_error():
    with pytest.raises(CameraError, match=r"kb4.*misses pixel \(.*\) by .* px") as info:
        C.KannalaBrandt4(64, 64, [30, 30, 32, 32, 1000, 0, 0, 0])
    assert "tolerance 0.05 px" in str(info.value)


def test_size_limit_is_exported_and_inclusive():
    assert C.MAX_IMAGE_SIDE == 16384
    C.Pinhole(C.MAX_IMAGE_SIDE, 1, [100, 100, 8000, 0])
    with pytest.raises(CameraError, match="16384"):
        C.Pinhole(C.MAX_IMAGE_SIDE + 1, 1, [100, 100, 8000, 0])


def test_bounds_are_inclusive_where_documented():
    lo, hi = C.FOCAL_RANGE_PX
    C.Pinhole(64, 64, [lo, hi, 32, 32])
    m = C.PRINCIPAL_MARGIN
    C.Pinhole(64, 48, [30, 30, -m * 64, (1 + m) * 48])
    with pytest.raises(CameraError, match="cx"):
        C.Pinhole(64, 48, [30, 30, -m * 64 - 1e-6, 24])
    b = C.DISTORTION_BOUND
    with pytest.raises(CameraError, match="k2"):
        C.KannalaBrandt4(64, 64, [30, 30, 32, 32, 0, b * 1.01, 0, 0])


def test_no_valid_pixel_is_refused():
    # The lens circle (fx = 1e-3: radius about 0.003 px) lies between pixel centres.
    with pytest.raises(CameraError, match="no pixel"):
        C.KannalaBrandt4(64, 64, [1e-3, 1e-3, 31.25, 31.25, 0, 0, 0, 0])


# ------------------------------------------------------------------------ domain boundaries
def _patched_geometry_is_finite(camera: C.Camera, patch: int = 14) -> None:
    """Build everything the patched forward builds from the camera, at the camera's size."""
    from raytun3r_plugin.size_geometry import SizeGeometry

    geometry = SizeGeometry(camera, camera.height, camera.width, patch, None, 80.0, 2.0)
    polar = geometry.polar
    for t in (polar.rho, polar.theta, polar.direction_yx):
        assert bool(torch.isfinite(t).all())
    for t in geometry.pe_weights(8, 8, "cpu", torch.float32):
        assert bool(torch.isfinite(t).all())
    for t in geometry.rope_basis(8, "cpu", torch.float32):
        assert bool(torch.isfinite(t).all())
    grid = geometry.resample_grid("cpu", torch.float32)
    assert grid is None or bool(torch.isfinite(grid).all())
    uv = geometry.uv_grid(camera.height // patch, camera.width // patch, "cpu", torch.float32)
    assert uv is None or bool(torch.isfinite(uv).all())
    rays, valid = camera.ray_table()
    assert bool(torch.isfinite(rays).all())
    assert torch.equal(camera.valid_mask(), camera.ray_table(dtype=torch.float64)[1])
    try:
        geometry.token_valid("cpu")
    except Raytun3rError:
        pass  # "no patch inside the valid region" is a refusal, not a break


@pytest.mark.parametrize(
    "build",
    [
        # Double sphere: xi = -1 is refused (above); just inside it and the other end work.
        # xi = 1 with a short focal length: the image reaches past the back pole's radius
        # 1 / alpha (those pixels are invalid, not wrong rays).
        lambda: C.DoubleSphere(56, 56, [12, 12, 27.5, 27.5, 1.0, 0.6]),
        lambda: C.DoubleSphere(56, 56, [30, 30, 27.5, 27.5, -0.999, 0.6]),
        lambda: C.DoubleSphere(56, 56, [20, 20, 27.5, 27.5, 1.0, 0.6]),
        lambda: C.DoubleSphere(56, 56, [20, 20, 27.5, 27.5, 1.0, 1.0]),
        lambda: C.DoubleSphere(56, 56, [20, 20, 27.5, 27.5, -0.5, 0.0]),
        # UCM / EUCM alpha at both ends of [0, 1].
        lambda: C.UCM(56, 56, [20, 20, 27.5, 27.5, 0.0]),
        lambda: C.UCM(56, 56, [20, 20, 27.5, 27.5, 1.0]),
        lambda: C.EUCM(56, 56, [20, 20, 27.5, 27.5, 1.0, 100.0]),
        lambda: C.EUCM(56, 56, [20, 20, 27.5, 27.5, 0.0, 1e-6]),
        # MEI xi at 0 (pinhole + radtan), 1 (parabolic) and the bound.
        lambda: C.MEI(56, 56, [20, 20, 27.5, 27.5, 0.0, 0, 0, 0, 0]),
        lambda: C.MEI(56, 56, [20, 20, 27.5, 27.5, 1.0, 0, 0, 0, 0]),
        lambda: C.MEI(56, 56, [200, 200, 27.5, 27.5, 100.0, 0, 0, 0, 0]),
        lambda: C.FOV(56, 56, [20, 20, 27.5, 27.5, 3.14]),
    ],
)
def test_domain_boundaries_that_are_included_work_in_the_patched_geometry(build):
    camera = build()
    assert C.validate(camera) <= C.ROUND_TRIP_TOL_PX
    _patched_geometry_is_finite(camera)


def test_double_sphere_near_minus_one():
    """xi = -1 is refused by the bound; just above it the camera works (geometry finite)."""
    for focal in (5.0, 20.0, 300.0):
        camera = C.DoubleSphere(56, 56, [focal, focal, 27.5, 27.5, -0.999, 0.6])
        _patched_geometry_is_finite(camera)
    with pytest.raises(CameraError, match=r"'xi' must be in \(-1, 1\]"):
        C.DoubleSphere(56, 56, [30, 30, 27.5, 27.5, -1.0, 0.6])


@pytest.mark.parametrize(
    "build",
    [
        lambda: C.UCM(56, 56, [20, 20, 27.5, 27.5, 1.0 + 1e-12]),
        lambda: C.EUCM(56, 56, [20, 20, 27.5, 27.5, 0.5, 0.0]),
        lambda: C.MEI(56, 56, [20, 20, 27.5, 27.5, -1e-9, 0, 0, 0, 0]),
        lambda: C.FOV(56, 56, [20, 20, 27.5, 27.5, math.pi]),
        lambda: C.DoubleSphere(56, 56, [20, 20, 27.5, 27.5, -1.0 - 1e-9, 0.6]),
    ],
)
def test_domain_boundaries_that_are_excluded_are_refused(build):
    with pytest.raises(CameraError):
        build()


# ------------------------------------------------------------------------ cost and caching
def test_round_trip_check_runs_once_per_camera_key(monkeypatch):
    # The cost (about 1.3 ms per new camera, 0.03 ms per cached build on the project's machine)
    # is a benchmark's business; what a test can hold is that repeated builds of the same camera
    # (one resized copy per forward) do not run the round trip again, while validate() does.
    camera = REAL["aria_f624"]()  # the most expensive model to invert
    calls = []
    original = type(camera).round_trip_error

    def counting(self):
        calls.append(self.key())
        return original(self)

    monkeypatch.setattr(type(camera), "round_trip_error", counting)
    for _ in range(5):
        C.validate(camera)
    assert len(calls) == 5
    calls.clear()
    first = camera.resized(320, 240)
    for _ in range(50):
        assert camera.resized(320, 240) == first
    assert len(calls) <= 1  # at most the first build of that size, none after it


def test_differentiable_camera_is_validated_on_detached_values():
    params = torch.tensor([30.0, 30.0, 32.0, 32.0, 0.02, 0, 0, 0], requires_grad=True)
    camera = C.KannalaBrandt4(64, 64, params)
    assert camera.requires_grad
    rays, _ = camera.unproject(torch.tensor([[10.0, 12.0]]))
    rays.sum().backward()
    assert params.grad is not None and bool(torch.isfinite(params.grad).all())
    bad = torch.tensor([30.0, 30.0, 32.0, 32.0, 1000.0, 0, 0, 0], requires_grad=True)
    with pytest.raises(CameraError, match="misses pixel"):
        C.KannalaBrandt4(64, 64, bad)


def test_validate_rejects_non_cameras():
    with pytest.raises(CameraError, match="expected a Camera"):
        C.validate("pinhole")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "call",
    [
        lambda c: c.scaled(10**400, 1),
        lambda c: c.scaled(1e300, 1),
        lambda c: c.scaled(float("nan"), 1),
        lambda c: c.cropped(10**400, 0, 4, 4),
        lambda c: c.cropped(0, 0, 10**400, 4),
        lambda c: c.resized(10**400, 4),
    ],
)
def test_geometry_edits_with_huge_inputs_raise_camera_error(call):
    with pytest.raises(CameraError):
        call(C.Pinhole(64, 64, [30, 30, 32, 32]))


# ------------------------------------------------------------------------ property tests
def _coef(scale: float) -> st.SearchStrategy[float]:
    # Mostly realistic magnitudes, sometimes ten times larger (where inversion starts to fail).
    return st.one_of(st.floats(-scale, scale, allow_nan=False), st.floats(-10 * scale, 10 * scale))


# Per model: the distortion parameters after fx, fy, cx, cy, as strategies.
_EXTRA = {
    "pinhole": [],
    "opencv": [_coef(0.5), _coef(0.5), _coef(0.01), _coef(0.01)],
    "kb4": [_coef(0.1), _coef(0.05), _coef(0.02), _coef(0.01)],
    "thin_prism_fisheye": [_coef(0.1), _coef(0.05), _coef(0.01), _coef(0.01)]
    + [_coef(0.02), _coef(0.01), _coef(0.01), _coef(0.01)],
    "fisheye624": [_coef(0.3) for _ in range(6)] + [_coef(0.01) for _ in range(6)],
    "ucm": [st.floats(-0.1, 1.1)],
    "eucm": [st.floats(-0.1, 1.1), st.floats(-0.5, 3.0)],
    "ds": [st.floats(-1.1, 1.1), st.floats(-0.1, 1.1)],
    "mei": [st.floats(-0.5, 4.0), _coef(0.3), _coef(0.3), _coef(0.01), _coef(0.01)],
    "fov": [st.floats(-0.5, 3.5)],
}
MODELS = sorted(_EXTRA)
assert set(MODELS) == set(C.CAMERA_MODELS)

# Values a fuzzer tries; one of them replaces one parameter in a quarter of the draws.
_SPECIAL = [0.0, -1.0, 1e300, -1e300, float("nan"), float("inf"), -float("inf"), 1e-310, 1e10]


@st.composite
def camera_inputs(draw, max_side: int = 48, models=MODELS):
    """(model, width, height, params, max_fov_deg): mostly plausible cameras (focal length
    0.05 to 30 times the image side, principal point up to three sides outside the image,
    distortion up to ten times real magnitudes), a quarter with one fuzzer value."""
    model = draw(st.sampled_from(models))
    width = draw(st.integers(1, max_side))
    height = draw(st.integers(1, max_side))
    side = max(width, height)
    fx = side * 10.0 ** draw(st.floats(-1.3, 1.5))
    fy = draw(st.one_of(st.just(fx), st.just(fx * draw(st.floats(0.8, 1.25)))))
    cx = draw(st.floats(-3.0 * width, 4.0 * width))
    cy = draw(st.floats(-3.0 * height, 4.0 * height))
    params = [fx, fy, cx, cy, *(draw(s) for s in _EXTRA[model])]
    if draw(st.integers(0, 3)) == 0:
        params[draw(st.integers(0, len(params) - 1))] = draw(st.sampled_from(_SPECIAL))
    fov = draw(st.one_of(st.none(), st.floats(10.0, 400.0)))
    return model, width, height, params, fov


def _dense_round_trip(camera: C.Camera) -> float:
    """Worst round-trip error over every pixel centre and the pixel-centre midpoints (a
    denser, different set than the construction grid), float64."""
    xs = torch.arange(0, camera.width, 0.5, dtype=torch.float64)[: 2 * camera.width - 1]
    ys = torch.arange(0, camera.height, 0.5, dtype=torch.float64)[: 2 * camera.height - 1]
    uv = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    with torch.no_grad():
        rays, valid = camera.unproject(uv)
        assert bool(torch.isfinite(rays).all())
        if not bool(valid.any()):
            return 0.0
        back, _ = camera.project(rays[valid])
    return float((back - uv[valid]).norm(dim=-1).max())


@settings(max_examples=300)
@given(camera_inputs())
def test_any_input_builds_a_round_tripping_camera_or_raises_camera_error(inputs):
    model, width, height, params, fov = inputs
    try:
        camera = C.CAMERA_MODELS[model](width, height, params, max_fov_deg=fov)
    except CameraError:
        return
    # Construction checks a 17 x 17 grid plus the border; every other pixel of the image
    # (here: all centres and midpoints) round-trips as well, within twice the tolerance.
    assert _dense_round_trip(camera) <= 2 * C.ROUND_TRIP_TOL_PX


_junk_scalar = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(min_value=10**300, max_value=10**400),
    st.floats(),
    st.text(max_size=4),
    st.binary(max_size=4),
    st.complex_numbers(max_magnitude=1e3),
)
_junk = st.recursive(
    _junk_scalar,
    lambda inner: st.one_of(
        st.lists(inner, max_size=10), st.dictionaries(st.text(max_size=3), inner, max_size=4)
    ),
    max_leaves=20,
)


@settings(max_examples=300)
@given(
    st.sampled_from(MODELS),
    st.one_of(_junk, st.integers(1, 64)),
    st.one_of(_junk, st.integers(1, 64)),
    st.one_of(
        _junk,
        st.lists(st.floats(), min_size=4, max_size=16),
        st.lists(_junk_scalar, min_size=4, max_size=16),
    ),
    st.one_of(st.none(), _junk),
)
def test_any_constructor_input_raises_only_camera_error(model, width, height, params, fov):
    cls = C.CAMERA_MODELS[model]
    for p in (params, _as_tensor_or_same(params)):
        try:
            camera = cls(width, height, p, max_fov_deg=fov)
        except CameraError:
            continue
        assert isinstance(camera, C.Camera)
        assert C.validate(camera) <= C.ROUND_TRIP_TOL_PX


def _as_tensor_or_same(params):
    try:
        return torch.tensor(params)
    except Exception:  # noqa: BLE001 - any failure: keep the original junk
        return params


def test_exotic_inputs_raise_camera_error():
    cls = C.KannalaBrandt4
    nested: list = []
    nested.append(nested)
    for width, params in [
        (64, nested),
        (64, torch.zeros(2, 8)),
        (64, torch.zeros(8, dtype=torch.complex64)),
        (64, {"fx": torch.zeros(3)}),
        (64, {**dict.fromkeys(cls.param_names, 1.0), "fx": torch.tensor(1j)}),
        (64, iter([30, 30, 32, 32, 0, 0, 0, float("nan")])),
        (64.5, [30, 30, 32, 32, 0, 0, 0, 0]),
        ("64", [30, 30, 32, 32, 0, 0, 0, 0]),
        (torch.tensor(64), [30, 30, 32, 32, 0, 0, 0, 0]),
    ]:
        with pytest.raises(CameraError):
            cls(width, 64, params)


# ------------------------------------------------------------------------ patched forward
@settings(max_examples=15)
@given(camera_inputs(max_side=3).map(lambda t: (t[0], 28 * t[1], 28 * t[2], t[3], t[4])))
def test_accepted_cameras_never_break_the_patched_geometry(inputs):
    model, width, height, params, fov = inputs
    try:
        camera = C.CAMERA_MODELS[model](width, height, params, max_fov_deg=fov)
    except CameraError:
        return
    _patched_geometry_is_finite(camera)


def test_accepted_edge_cameras_run_the_tiny_da3_network_end_to_end():
    pytest.importorskip("depth_anything_3")
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    import raytun3r_plugin as rt

    net = build_tiny_network(seed=0).eval()
    images = torch.rand(1, 1, 3, 56, 56, generator=torch.Generator().manual_seed(0))
    cameras = [
        C.DoubleSphere(56, 56, [30, 30, 27.5, 27.5, -0.999, 0.6]),
        C.MEI(56, 56, [2000, 2000, 27.5, 27.5, 100.0, 0, 0, 0, 0]),
        C.KannalaBrandt4(56, 56, [8, 8, 27.5, 27.5, 10.0, 0, 0, 0]),
        C.FOV(56, 56, [20, 20, 27.5, 27.5, 3.14]),
        C.Fisheye624(56, 56, [25, 25, 40.0, 10.0, 0.4, -0.4, -0.1, 1.5, -1.7, 0.6, *[0.01] * 6]),
        # Its valid region is smaller than one patch: refused by the first forward, cleanly.
        C.FOV(56, 56, [6, 6, 27.5, 27.5, 3.14]),
    ]
    ran = 0
    for camera in cameras:
        try:
            with rt.apply(net, camera), torch.no_grad():
                prediction = rt.predict(net, images)
        except Raytun3rError:
            # A clean refusal (e.g. "no patch of the image is inside the camera's valid
            # region", raised by the first forward) is allowed; anything else is a break.
            assert rt.handle_of(net) is None
            continue
        assert bool(torch.isfinite(prediction.depth).all())
        ran += 1
    assert ran == len(cameras) - 1


@settings(max_examples=200)
@given(
    st.dictionaries(
        st.sampled_from(["model", "width", "height", "params", "max_fov_deg", "extra"]),
        st.one_of(_junk, st.sampled_from(MODELS)),
    ),
)
def test_from_dict_raises_only_camera_error(record):
    record = {"model": "pinhole", "width": 8, "height": 8, "params": {}, **record}
    try:
        C.from_dict(record)
    except CameraError:
        pass


def test_from_dict_with_an_unhashable_model_raises_camera_error():
    with pytest.raises(CameraError, match="unknown camera model"):
        C.from_dict({"model": ["kb4"], "width": 8, "height": 8, "params": {}})


@pytest.mark.parametrize(
    "size, fov", [("64", 190.0), ((64,), 190.0), (64, "190"), (64, None), (10**400, 190.0)]
)
def test_fisheye_builder_raises_only_camera_error(size, fov):
    with pytest.raises(CameraError):
        C.fisheye(size, fov)
