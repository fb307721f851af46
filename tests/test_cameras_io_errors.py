"""Malformed calibration files of every format: refused with a message that names the file and
the field; unknown formats, unknown camera ids and missing files."""

from __future__ import annotations

import pytest

from raytun3r_plugin.cameras import (
    load,
)
from raytun3r_plugin.errors import CameraError
from tests.calibration_files import (
    KITTI360_IMAGE_02,
    TUMVI_CAMCHAIN,
    TUMVI_EUCM,
    basalt_json,
    kalibr,
    write,
)

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
