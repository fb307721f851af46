"""Calibration readers/writers: Kalibr, basalt, COLMAP, KITTI-360 (OpenCV YAML), raytun3r JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

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

KITTI360_IMAGE_02 = """%YAML:1.0
model_type: MEI
camera_name: image_02
image_width: 1400
image_height: 1400
mirror_parameters:
   xi: 2.2134047507854890e+00
distortion_parameters:
   k1: 1.6798235660113681e-02
   k2: 1.6548773243373522e+00
   p1: 4.2223943394772046e-04
   p2: 4.2462134260997584e-04
projection_parameters:
   gamma1: 1.3363220825849971e+03
   gamma2: 1.3357883350012958e+03
   u0: 7.1694323510126321e+02
   v0: 7.0576498308221585e+02
"""

# image_03 written OpenCV-style without a space after the colons.
KITTI360_IMAGE_03 = """%YAML:1.0
model_type:MEI
camera_name:image_03
image_width:1400
image_height:1400
mirror_parameters:
   xi:2.5535139132482758e+00
distortion_parameters:
   k1:4.9370396274089505e-02
   k2:4.5068455478645308e+00
   p1:1.3477698472982495e-03
   p2:-7.0340482615055284e-04
projection_parameters:
   gamma1:1.4854388981875156e+03
   gamma2:1.4849477411748708e+03
   u0:6.9888316784030962e+02
   v0:6.9814541887723055e+02
"""

TUMVI_CAMCHAIN = """cam0:
  T_cam_imu:
  - [-0.9995250378696743, 0.029615343885863205, -0.008522328211654736, 0.04727988224914392]
  - [0.0075019185074052044, -0.03439736061393144, -0.9993800792498829, -0.047443232143367084]
  - [-0.02989013031643309, -0.998969345370175, 0.03415885127385616, -0.0681999605066297]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
    0.00020293673591811182]
  distortion_model: equidistant
  intrinsics: [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504]
  resolution: [512, 512]
  rostopic: /cam0/image_raw
cam1:
  T_cam_imu:
  - [-0.9995110484978581, 0.030299116376600627, -0.0077218830287333565, -0.053697434688869734]
  - [0.008104079263822521, 0.012511643720192351, -0.9998888851620987, -0.046131737923635924]
  - [-0.030199136245891378, -0.9994625667418545, -0.012751072573940885, -0.07149261284195751]
  - [0.0, 0.0, 0.0, 1.0]
  T_cn_cnm1:
  - [0.9999994457734953, -0.0008233639921576076, -0.0006561436136444361, -0.10106110275180535]
  - [0.0008236530106945868, 0.9999994387942179, 0.0004403256434125341, -0.0019764031223257676]
  - [0.0006557806169985282, -0.0004408658021827109, 0.9999996878307169, 0.0010213797068545]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [0]
  camera_model: pinhole
  distortion_coeffs: [0.0034003170790442797, 0.001766278153469831, -0.00266312569781606,
    0.0003299517423931039]
  distortion_model: equidistant
  intrinsics: [190.44236969414825, 190.4344384721956, 252.59949716835982, 254.91723064636983]
  resolution: [512, 512]
  rostopic: /cam1/image_raw
"""

TUMVI_CAM0 = [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504,
              0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
              0.00020293673591811182]  # fmt: skip


def basalt_json(intrinsics: list[dict], resolution: list[list[int]]) -> str:
    value0 = {
        "T_imu_cam": [{"px": 0.0, "py": 0.0, "pz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0}]
        * len(intrinsics),
        "intrinsics": intrinsics,
        "resolution": resolution,
        "vignette": [],
        "calib_accel_bias": [0.0] * 9,
        "calib_gyro_bias": [0.0] * 12,
        "imu_update_rate": 200.0,
        "accel_noise_std": [0.016, 0.016, 0.016],
        "gyro_noise_std": [0.000282, 0.000282, 0.000282],
        "cam_time_offset_ns": 0,
    }
    return json.dumps({"value0": value0}, indent=4)


TUMVI_DS = {"fx": 158.28600034966977, "fy": 158.2743455478755, "cx": 254.96116578191653,
            "cy": 256.8894394501779, "xi": -0.17213086034353243, "alpha": 0.5931177593944744}  # fmt: skip
TUMVI_EUCM = {"fx": 191.14799836282189, "fy": 191.13150963902818, "cx": 254.9585771534443,
              "cy": 256.88154645599448, "alpha": 0.6291060881178562, "beta": 1.0418067381860868}  # fmt: skip

COLMAP_LINES = [
    "0 THIN_PRISM_FISHEYE 6048 4032 3411.42 3410.02 3041.29 2014.07 0.21047 0.21102 -5.36231e-06 0.00051541 -0.158023 0.406856 -8.46499e-05 0.000861313",
    "1 PINHOLE 752 480 458.654 457.296 367.715 248.875",
    "2 OPENCV_FISHEYE 1752 1168 789.9080967683176 791.5566599926353 879.703786509326 585.2893145555763 -0.029473047856246333 -0.005769803970428537 -0.002148236771485755 0.00014840568362061509",
    "3 SIMPLE_PINHOLE 201 101 150.0 100.5 50.5",
    "7 OPENCV 752 480 458.654 457.296 367.715 248.875 -0.28340811 0.07395907 0.00019359 1.76187114e-05",
    "8 FOV 640 480 256.1 255.7 320.5 240.25 0.9217",
    "9 RAD_TAN_THIN_PRISM_FISHEYE 640 480 241.3 241.3 317.5 238.0 -0.0255 0.0979 -0.0665 0.007 0.0031 -0.0013 -0.0003 0.0002 0.0005 -0.0001 -0.0004 5e-05",
]
COLMAP_TXT = (
    "# Camera list with one line of data per camera:\n"
    "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
    f"# Number of cameras: {len(COLMAP_LINES)}\n" + "\n".join(COLMAP_LINES) + "\n"
)


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


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


def kalibr(
    camera_model: str, intrinsics: list, distortion_model: str, coeffs: list, res=(640, 480)
) -> str:
    return (
        "cam0:\n"
        f"  camera_model: {camera_model}\n"
        f"  intrinsics: {intrinsics}\n"
        f"  distortion_model: {distortion_model}\n"
        f"  distortion_coeffs: {coeffs}\n"
        f"  resolution: [{res[0]}, {res[1]}]\n"
        "  rostopic: /cam0/image_raw\n"
    )


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


# ----------------------------------------------------------------------------- malformed files
KALIBR_OK = kalibr(
    "pinhole", [190.97, 190.97, 254.9, 256.9], "equidistant", [0.0035, 0.0007, -0.002, 0.0002]
)
KITTI_OK = KITTI360_IMAGE_02
BASALT_EUCM = basalt_json([{"camera_type": "eucm", "intrinsics": TUMVI_EUCM}], [[512, 512]])


def basalt_eucm(**changes: float) -> str:
    return basalt_json(
        [{"camera_type": "eucm", "intrinsics": {**TUMVI_EUCM, **changes}}], [[512, 512]]
    )


@pytest.mark.parametrize(
    "name,text,field",
    [
        # missing fields
        (
            "chain.yaml",
            KALIBR_OK.replace("  intrinsics: [190.97, 190.97, 254.9, 256.9]\n", ""),
            "cam0.intrinsics",
        ),
        (
            "image_02.yaml",
            KITTI_OK.replace("   gamma1: 1.3363220825849971e+03\n", ""),
            "projection_parameters.gamma1",
        ),
        (
            "calib.json",
            BASALT_EUCM.replace('"beta"', '"gamma"'),
            "value0.intrinsics[0].intrinsics.gamma",
        ),
        (
            "calib.json",
            basalt_json(
                [
                    {
                        "camera_type": "eucm",
                        "intrinsics": {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "alpha": 0.5},
                    }
                ],
                [[5, 5]],
            ),
            "value0.intrinsics[0].intrinsics.beta",
        ),
        ("image_02.yaml", KITTI_OK.replace("image_width: 1400\n", ""), "image_width"),
        # wrong parameter counts
        (
            "chain.yaml",
            KALIBR_OK.replace(
                "[190.97, 190.97, 254.9, 256.9]", "[190.97, 190.97, 254.9, 256.9, 1.0]"
            ),
            "cam0.intrinsics",
        ),
        (
            "chain.yaml",
            KALIBR_OK.replace("[0.0035, 0.0007, -0.002, 0.0002]", "[0.0035, 0.0007, -0.002]"),
            "cam0.distortion_coeffs",
        ),
        ("cameras.txt", "1 PINHOLE 640 480 500 500 320 240 0.1\n", "camera 1 (line 1) PARAMS"),
        (
            "cameras.txt",
            "1 OPENCV_FISHEYE 640 480 500 500 320 240 0.1 0.0 0.0\n",
            "camera 1 (line 1) PARAMS",
        ),
        (
            "image_02.yaml",
            KITTI_OK.replace(
                "   p2: 4.2462134260997584e-04\n", "   p2: 4.2462134260997584e-04\n   k3: 0.1\n"
            ),
            "distortion_parameters.k3",
        ),
        # negative focal
        (
            "chain.yaml",
            KALIBR_OK.replace("[190.97, 190.97,", "[-190.97, 190.97,"),
            "cam0.intrinsics[0] (fu)",
        ),
        ("cameras.txt", "4 SIMPLE_PINHOLE 640 480 -500 320 240\n", "camera 4 (line 1) param f"),
        (
            "image_02.yaml",
            KITTI_OK.replace("gamma2: 1.3357883350012958e+03", "gamma2: -1.3e+03"),
            "projection_parameters.gamma2",
        ),
        ("calib.json", basalt_eucm(fy=-191.1), "value0.intrinsics[0].intrinsics.fy"),
        # non-finite values
        ("cameras.txt", "7 PINHOLE 640 480 nan 500 320 240\n", "camera 7 (line 1) param fx"),
        (
            "image_02.yaml",
            KITTI_OK.replace("xi: 2.2134047507854890e+00", "xi: .nan"),
            "mirror_parameters.xi",
        ),
        (
            "chain.yaml",
            KALIBR_OK.replace("0.0007, -0.002", "0.0007, .inf"),
            "cam0.distortion_coeffs[2] (k3)",
        ),
        ("calib.json", basalt_eucm(cx=float("nan")), "value0.intrinsics[0].intrinsics.cx"),
        # outside the model's domain
        ("calib.json", basalt_eucm(beta=0.0), "value0.intrinsics[0].intrinsics.beta"),
        ("calib.json", basalt_eucm(beta=-2.0), "value0.intrinsics[0].intrinsics.beta"),
        (
            "chain.yaml",
            kalibr("eucm", [0.6, -1.0, 190.0, 190.0, 255.0, 256.0], "none", []),
            "cam0.intrinsics[1] (beta)",
        ),
        (
            "chain.yaml",
            kalibr("ds", [1.5, 0.6, 190.0, 190.0, 255.0, 256.0], "none", []),
            "cam0.intrinsics[0] (xi)",
        ),
        (
            "chain.yaml",
            kalibr("omni", [-0.5, 190.0, 190.0, 255.0, 256.0], "none", []),
            "cam0.intrinsics[0] (xi)",
        ),
        (
            "chain.yaml",
            kalibr("omni", [-0.5, 190.0, 190.0, 255.0, 256.0], "radtan", [0, 0, 0, 0]),
            "cam0.intrinsics[0] (xi)",
        ),
        (
            "image_02.yaml",
            KITTI_OK.replace("xi: 2.2134047507854890e+00", "xi: -1.0"),
            "mirror_parameters.xi",
        ),
        (
            "cameras.txt",
            "1 EUCM 640 480 300 300 320 240 1.5 1.0\n",
            "camera 1 (line 1) param alpha",
        ),
        # unknown models
        (
            "chain.yaml",
            KALIBR_OK.replace("camera_model: pinhole", "camera_model: fancy"),
            "cam0.camera_model",
        ),
        (
            "chain.yaml",
            KALIBR_OK.replace("distortion_model: equidistant", "distortion_model: fov"),
            "cam0.distortion_model",
        ),
        (
            "image_02.yaml",
            KITTI_OK.replace("model_type: MEI", "model_type: SCARAMUZZA"),
            "model_type",
        ),
        (
            "calib.json",
            BASALT_EUCM.replace('"camera_type": "eucm"', '"camera_type": "fov"'),
            "value0.intrinsics[0].camera_type",
        ),
        ("cameras.txt", "1 SIMPLE_DIVISION 640 480 300 320 240 0.1\n", "camera 1 (line 1) MODEL"),
        ("camera.json", '{"model": "fisheye9", "width": 10, "height": 10, "params": {}}', "model"),
        # own JSON with a bad value
        (
            "camera.json",
            '{"model": "pinhole", "width": 10, "height": 10, "params": {"fx": -1, "fy": 1, "cx": 0, "cy": 0}}',
            "params.fx",
        ),
        (
            "camera.json",
            '{"model": "pinhole", "width": 10, "height": 10, "params": {"fx": 1, "fy": 1, "cx": 0}}',
            "params.cy",
        ),
        # bad sizes
        (
            "chain.yaml",
            KALIBR_OK.replace("resolution: [640, 480]", "resolution: [640, -480]"),
            "cam0.resolution[1]",
        ),
        ("cameras.txt", "1 PINHOLE 640 0 500 500 320 240\n", "camera 1 (line 1) HEIGHT"),
    ],
    ids=lambda v: v if isinstance(v, str) and len(v) < 60 else "",
)
def test_malformed_files_name_file_and_field(tmp_path, name, text, field):
    path = write(tmp_path, name, text)
    with pytest.raises(CameraError) as ei:
        load(path)
    msg = str(ei.value)
    assert str(path) in msg and field in msg, msg


@pytest.mark.parametrize(
    "text",
    [
        "just some words\n",
        "[1, 2, 3]\n",
        '{"hello": 1}\n',
        "a: 1\nb: [2]\n",
        "%YAML:1.0\nfoo: 1\n",
        "",
    ],
)
def test_unknown_format(tmp_path, text):
    path = write(tmp_path, "mystery.txt", text)
    with pytest.raises(CameraError, match="unknown calibration format") as ei:
        load(path)
    assert str(path) in str(ei.value)


def test_unknown_camera_ids_and_missing_file(tmp_path):
    path = write(tmp_path, "chain.yaml", TUMVI_CAMCHAIN)
    for bad in ("cam5", 5, "left", -1):
        with pytest.raises(CameraError, match=r"chain\.yaml.*'camera'"):
            load(path, camera=bad)
    missing = tmp_path / "nope.yaml"
    with pytest.raises(CameraError, match="nope.yaml"):
        load(missing)
