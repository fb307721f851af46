"""Calibration readers/writers: Kalibr, basalt, COLMAP, KITTI-360 (OpenCV YAML), raytun3r JSON
(malformed files: test_cameras_io_errors.py)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from raytun3r_plugin.cameras import (
    EUCM,
    FOV,
    MEI,
    UCM,
    DoubleSphere,
    Fisheye624,
    KannalaBrandt4,
    OpenCVRadTan,
    Pinhole,
    ThinPrismFisheye,
    load,
    save,
    to_colmap_line,
)
from raytun3r_plugin.cameras.formats import detect_format
from raytun3r_plugin.errors import CameraError
from tests.calibration_files import (
    COLMAP_LINES,
    COLMAP_TXT,
    KITTI360_IMAGE_02,
    KITTI360_IMAGE_03,
    TUMVI_CAM0,
    TUMVI_CAMCHAIN,
    TUMVI_DS,
    TUMVI_EUCM,
    basalt_json,
    kalibr,
    write,
)


# ----------------------------------------------------------------------------- KITTI-360
def test_kitti360_image_02(tmp_path):
    path = write(tmp_path, "image_02.yaml", KITTI360_IMAGE_02)
    assert detect_format(path) == "opencv_yaml"
    cam = load(path)
    assert isinstance(cam, MEI) and (cam.width, cam.height) == (1400, 1400)
    assert cam.values == {
        "fx": 1336.3220825849971, "fy": 1335.7883350012958, "cx": 716.94323510126321,
        "cy": 705.76498308221585, "xi": 2.2134047507854890, "k1": 0.016798235660113681,
        "k2": 1.6548773243373522, "p1": 4.2223943394772046e-04, "p2": 4.2462134260997584e-04,
    }  # fmt: skip
    assert math.isclose(
        math.degrees(cam.max_angle), 180 - math.degrees(math.acos(1 / 2.2134047507854890))
    )
    assert load(path, camera="image_02") == cam
    # The lens circle: the principal point sees the axis, a corner is outside the model.
    rays, valid = cam.unproject(
        torch.tensor([[716.94323510126321, 705.76498308221585], [0.0, 0.0]])
    )
    assert valid.tolist() == [True, False]
    torch.testing.assert_close(rays[0], torch.tensor([0.0, 0.0, 1.0]))
    with pytest.raises(CameraError, match="camera"):
        load(path, camera="image_03")


def test_kitti360_image_03_without_spaces(tmp_path):
    cam = load(write(tmp_path, "image_03.yaml", KITTI360_IMAGE_03))
    assert isinstance(cam, MEI)
    assert cam.values["xi"] == 2.5535139132482758 and cam.values["p2"] == -7.0340482615055284e-04
    assert cam.values["fx"] == 1485.4388981875156 and cam.values["cy"] == 698.14541887723055


def test_camodocal_pinhole_and_kannala_brandt(tmp_path):
    pin = """%YAML:1.0
---
model_type: PINHOLE
camera_name: cam0
image_width: 752
image_height: 480
distortion_parameters:
   k1: -2.917e-01
   k2: 8.228e-02
   p1: 5.333e-05
   p2: -1.578e-04
projection_parameters:
   fx: 4.616e+02
   fy: 4.603e+02
   cx: 3.630e+02
   cy: 2.481e+02
"""
    cam = load(write(tmp_path, "pin.yaml", pin))
    assert (
        isinstance(cam, OpenCVRadTan) and cam.values["k1"] == -0.2917 and cam.values["fx"] == 461.6
    )
    kb = """%YAML:1.0
model_type: KANNALA_BRANDT
camera_name: camera
image_width: 512
image_height: 512
projection_parameters:
   k2: 0.0034823894022493434
   k3: 0.0007150348452162257
   k4: -0.0020532361418706202
   k5: 0.00020293673591811182
   mu: 190.97847715128717
   mv: 190.9733070521226
   u0: 254.93170605935475
   v0: 256.8974428996504
"""
    assert load(write(tmp_path, "kb.yaml", kb)) == KannalaBrandt4(512, 512, TUMVI_CAM0)


# ----------------------------------------------------------------------------- Kalibr
def test_kalibr_tumvi_camchain(tmp_path):
    path = write(tmp_path, "camchain-imucam-room1.yaml", TUMVI_CAMCHAIN)
    assert detect_format(path) == "kalibr"
    cam0 = load(path)
    assert cam0 == KannalaBrandt4(512, 512, TUMVI_CAM0)
    assert load(path, camera="cam0") == cam0 and load(path, camera=0) == cam0
    cam1 = load(path, camera="cam1")
    assert load(path, camera=1) == cam1 and cam1 != cam0
    assert cam1.values["fx"] == 190.44236969414825 and cam1.values["k4"] == 0.0003299517423931039
    # The TUM-VI lens sees beyond 90 degrees: the image corner ray points backwards.
    assert cam0.fov_deg > 180.0


def test_kalibr_models(tmp_path):
    def rd(*args, **kw):
        return load(write(tmp_path, "chain.yaml", kalibr(*args, **kw)))

    cam = rd(
        "pinhole",
        [458.654, 457.296, 367.215, 248.375],
        "radtan",
        [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
    )
    assert cam == OpenCVRadTan(
        640,
        480,
        [458.654, 457.296, 367.215, 248.375, -0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
    )
    assert rd("pinhole", [400.0, 401.0, 320.0, 240.0], "none", []) == Pinhole(
        640, 480, [400.0, 401.0, 320.0, 240.0]
    )
    mei = rd(
        "omni",
        [2.2134, 1336.3, 1335.8, 716.9, 705.8],
        "radtan",
        [0.0168, 1.6549, 0.000422, 0.000425],
    )
    assert mei == MEI(
        640, 480, [1336.3, 1335.8, 716.9, 705.8, 2.2134, 0.0168, 1.6549, 0.000422, 0.000425]
    )
    assert rd("ds", [-0.172, 0.593, 158.3, 158.3, 255.0, 256.9], "none", []) == DoubleSphere(
        640, 480, [158.3, 158.3, 255.0, 256.9, -0.172, 0.593]
    )
    assert rd("eucm", [0.629, 1.042, 191.1, 191.1, 255.0, 256.9], "none", []) == EUCM(
        640, 480, [191.1, 191.1, 255.0, 256.9, 0.629, 1.042]
    )


def test_kalibr_yaml11_numbers_and_aliases(tmp_path):
    # YAML 1.1 reads 1e-05 (no dot) as a string; Kalibr writes such numbers.
    text = kalibr("pinhole", [400.0, 401.0, 320.0, 240.0], "equi", [1e-05, -2e-06, 0.0, 3e-07])
    assert "1e-05" in text
    cam = load(write(tmp_path, "chain.yaml", text))
    assert isinstance(cam, KannalaBrandt4)
    assert cam.values["k1"] == 1e-05 and cam.values["k2"] == -2e-06 and cam.values["k4"] == 3e-07


def test_kalibr_omni_without_distortion_is_ucm(tmp_path):
    xi, fu, fv, pu, pv = 1.7, 700.0, 690.0, 320.0, 240.0
    cam = load(write(tmp_path, "omni.yaml", kalibr("omni", [xi, fu, fv, pu, pv], "none", [])))
    assert isinstance(cam, UCM)
    assert math.isclose(cam.values["alpha"], xi / (1 + xi)) and math.isclose(
        cam.values["fx"], fu / (1 + xi)
    )
    # Same pixels as Kalibr's xi-form projection u = fu x / (z + xi |P|) + pu.
    X = torch.tensor([[0.3, -0.2, 1.0], [1.0, 0.5, -0.3], [-0.1, 0.9, 0.2]], dtype=torch.float64)
    den = X[:, 2] + xi * X.norm(dim=-1)
    ref = torch.stack([fu * X[:, 0] / den + pu, fv * X[:, 1] / den + pv], -1)
    uv, valid = cam.project(X)
    assert valid.all()
    torch.testing.assert_close(uv, ref, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- basalt
def test_basalt_tumvi_ds_and_eucm(tmp_path):
    path = write(
        tmp_path,
        "tumvi_512_ds_calib.json",
        basalt_json(
            [
                {"camera_type": "ds", "intrinsics": TUMVI_DS},
                {"camera_type": "eucm", "intrinsics": TUMVI_EUCM},
            ],
            [[512, 512], [512, 512]],
        ),
    )
    assert detect_format(path) == "basalt"
    ds = load(path)
    assert (
        isinstance(ds, DoubleSphere)
        and ds.values == TUMVI_DS
        and (ds.width, ds.height) == (512, 512)
    )
    eucm = load(path, camera=1)
    assert isinstance(eucm, EUCM) and eucm.values == TUMVI_EUCM
    assert load(path, camera="cam1") == eucm
    # Both calibrations describe the same lens: the corner pixel rays (~118 degrees off-axis)
    # agree to within a degree.
    corner = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    r_ds, r_eu = ds.unproject(corner)[0][0], eucm.unproject(corner)[0][0]
    assert r_ds[2] < 0 and math.degrees(math.acos(float(r_ds @ r_eu))) < 1.5
    with pytest.raises(CameraError, match="camera"):
        load(path, camera=2)


def test_basalt_other_types(tmp_path):
    kb = dict(zip(KannalaBrandt4.param_names, TUMVI_CAM0, strict=True))
    path = write(
        tmp_path,
        "calib.json",
        basalt_json(
            [
                {"camera_type": "kb4", "intrinsics": kb},
                {
                    "camera_type": "ucm",
                    "intrinsics": {
                        "fx": 300.0,
                        "fy": 301.0,
                        "cx": 320.0,
                        "cy": 240.0,
                        "alpha": 0.6,
                    },
                },
                {
                    "camera_type": "pinhole",
                    "intrinsics": {"fx": 300.0, "fy": 301.0, "cx": 320.0, "cy": 240.0},
                },
            ],
            [[512, 512], [640, 480], [640, 480]],
        ),
    )
    assert load(path, camera=0) == KannalaBrandt4(512, 512, TUMVI_CAM0)
    assert load(path, camera=1) == UCM(640, 480, [300.0, 301.0, 320.0, 240.0, 0.6])
    assert load(path, camera=2) == Pinhole(640, 480, [300.0, 301.0, 320.0, 240.0])


# ----------------------------------------------------------------------------- COLMAP
def test_colmap_cameras_txt(tmp_path):
    path = write(tmp_path, "cameras.txt", COLMAP_TXT)
    assert detect_format(path) == "colmap"
    eth3d = load(path)  # the first camera by default
    assert isinstance(eth3d, ThinPrismFisheye) and (eth3d.width, eth3d.height) == (6048, 4032)
    assert eth3d.values["cx"] == 3041.29 - 0.5 and eth3d.values["sy1"] == 0.000861313
    pin = load(path, camera=1)
    assert pin == Pinhole(752, 480, [458.654, 457.296, 367.215, 248.375])
    assert isinstance(load(path, camera="2"), KannalaBrandt4)
    simple = load(path, camera=3)
    assert simple.values == {"fx": 150.0, "fy": 150.0, "cx": 100.0, "cy": 50.0}  # 100.5 -> 100.0
    assert isinstance(load(path, camera=7), OpenCVRadTan)
    with pytest.raises(CameraError, match=r"cameras\.txt.*'camera'.*42"):
        load(path, camera=42)


def test_colmap_export_round_trip(tmp_path):
    path = write(tmp_path, "cameras.txt", COLMAP_TXT)
    for line in COLMAP_LINES:
        cid = int(line.split()[0])
        model = "SIMPLE_PINHOLE" if "SIMPLE_PINHOLE" in line else None
        assert to_colmap_line(load(path, camera=cid), cid, model=model) == line
    # A principal point at the image centre in our convention is W/2 in COLMAP's.
    assert (
        to_colmap_line(Pinhole(640, 480, [500.0, 500.0, 319.5, 239.5]), 5)
        == "5 PINHOLE 640 480 500.0 500.0 320.0 240.0"
    )
    with pytest.raises(CameraError, match="no COLMAP equivalent"):
        to_colmap_line(DoubleSphere(512, 512, list(TUMVI_DS.values())), 1)
    with pytest.raises(CameraError, match="SIMPLE_PINHOLE"):
        to_colmap_line(Pinhole(640, 480, [500.0, 501.0, 319.5, 239.5]), 1, model="SIMPLE_PINHOLE")


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("10 SIMPLE_FISHEYE 640 480 300.0 320.0 240.0", (300.0, 300.0, 0.0, 0.0)),
        ("11 FISHEYE 640 480 300.0 301.0 320.0 240.0", (300.0, 301.0, 0.0, 0.0)),
        ("12 SIMPLE_RADIAL_FISHEYE 640 480 300.0 320.0 240.0 0.05", (300.0, 300.0, 0.05, 0.0)),
        ("13 RADIAL_FISHEYE 640 480 300.0 320.0 240.0 0.05 -0.01", (300.0, 300.0, 0.05, -0.01)),
    ],
)
def test_colmap_equidistant_family_is_kb4(tmp_path, line, expected):
    camera = load(write(tmp_path, "cameras.txt", line + "\n"))
    fx, fy, k1, k2 = expected
    assert isinstance(camera, KannalaBrandt4)
    assert camera.values == {
        "fx": fx,
        "fy": fy,
        "cx": 319.5,
        "cy": 239.5,
        "k1": k1,
        "k2": k2,
        "k3": 0.0,
        "k4": 0.0,
    }
    # COLMAP's own formula (normalised plane, theta = atan(r), theta_d = theta (1 + k1 theta^2
    # + k2 theta^4)), pixel corner at 0: our pixels are 0.5 less.
    points = torch.tensor(
        [[0.3, -0.2, 1.0], [-0.9, 0.5, 1.0], [0.01, 0.02, 1.0]], dtype=torch.float64
    )
    a, b = points[:, 0], points[:, 1]
    r = torch.hypot(a, b)
    theta = torch.atan(r)
    scale = theta * (1 + k1 * theta**2 + k2 * theta**4) / r
    colmap = torch.stack([fx * a * scale + 320.0, fy * b * scale + 240.0], -1)
    uv, valid = camera.project(points)
    assert valid.all() and torch.allclose(uv, colmap - 0.5, atol=1e-9)
    # Exported as the general model.
    assert to_colmap_line(camera, 1).split()[1] == "OPENCV_FISHEYE"


def test_colmap_fov_and_fisheye624(tmp_path):
    camera = load(write(tmp_path, "cameras.txt", COLMAP_TXT), camera=8)
    assert (
        isinstance(camera, FOV)
        and camera.values["omega"] == 0.9217
        and camera.values["cx"] == 320.0
    )
    aria = load(write(tmp_path, "cameras.txt", COLMAP_TXT), camera=9)
    assert (
        isinstance(aria, Fisheye624) and aria.values["k5"] == -0.0013 and aria.values["s3"] == 5e-05
    )
    with pytest.raises(CameraError, match=r"param omega.*\(0, pi\)"):
        load(write(tmp_path, "bad.txt", "1 FOV 640 480 256.1 255.7 320.5 240.25 0.0\n"))


# ----------------------------------------------------------------------------- own JSON
def test_save_load_own_json(tmp_path):
    cam = KannalaBrandt4(512, 512, TUMVI_CAM0, max_fov_deg=195.0)
    path = tmp_path / "camera.json"
    save(cam, path)
    assert detect_format(path) == "raytun3r"
    back = load(path)
    assert back == cam and torch.equal(back.params, cam.params) and back.max_fov_deg == 195.0
    assert json.loads(path.read_text()) == cam.to_dict()
    save(Pinhole(10, 10, [5.0, 5.0, 4.5, 4.5]), path)  # overwrite in place
    assert isinstance(load(str(path)), Pinhole)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.json"]  # no temp files left
    with pytest.raises(CameraError):
        save("not a camera", tmp_path / "x.json")  # type: ignore[arg-type]
