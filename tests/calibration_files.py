"""Calibration files of every format the readers take, with the official values where they are
published (KITTI-360, TUM-VI Kalibr and basalt, ETH3D / ScanNet++ COLMAP lines), and writers of
variants: the cases of tests/test_cameras_io*.py."""

from __future__ import annotations

import json
from pathlib import Path

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
