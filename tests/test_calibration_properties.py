"""Calibration readers are strict and bounded: any bytes load a valid camera or raise
CameraError, quickly, with a short message (issue 16)."""

from __future__ import annotations

import random
import time

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from raytun3r_plugin.cameras import Camera  # noqa: E402
from raytun3r_plugin.cameras.formats import (  # noqa: E402
    MAX_FILE_BYTES,
    MAX_YAML_BYTES,
    detect_format,
    load,
)
from raytun3r_plugin.errors import CameraError  # noqa: E402
from tests.calibration_generators import FORMATS, mutate, valid_calibration  # noqa: E402

DETECTED = {"kalibr_cv_header": "kalibr"}
SEEDS = st.integers(0, 2**32 - 1)


def _write(tmp_path, text: str | bytes, name: str = "calib.txt"):
    p = tmp_path / name
    if isinstance(text, str):
        p.write_text(text)
    else:
        p.write_bytes(text)
    return p


def _load_or_camera_error(path) -> Camera | None:
    """Load; a CameraError is fine if short and naming the file. Asserts < 1 s."""
    t0 = time.perf_counter()
    try:
        cam = load(path)
    except CameraError as e:
        msg = str(e)
        assert str(path) in msg, msg
        assert len(msg) < 1000, msg[:200]
        cam = None
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0, f"{elapsed:.2f} s"
    if cam is not None:
        assert isinstance(cam, Camera)
    return cam


@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=15)
@given(seed=SEEDS)
def test_valid_calibration_round_trips(tmp_path_factory, fmt, seed):
    text, expected = valid_calibration(random.Random(seed), fmt)
    path = _write(tmp_path_factory.mktemp("v"), text)
    assert detect_format(path) == DETECTED.get(fmt, fmt)
    cam = load(path)
    assert cam.model == expected.model and (cam.width, cam.height) == (
        expected.width,
        expected.height,
    )
    for k, v in expected.values.items():
        assert cam.values[k] == pytest.approx(v, rel=1e-12, abs=1e-12), k


@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=200)
@given(seed=SEEDS)
def test_mutated_calibration_loads_or_raises_camera_error(tmp_path_factory, fmt, seed):
    rng = random.Random(seed)
    text, _ = valid_calibration(rng, fmt)
    data = mutate(rng, text)
    _load_or_camera_error(_write(tmp_path_factory.mktemp("m"), data))


@settings(max_examples=200)
@given(data=st.binary(max_size=300))
def test_arbitrary_bytes_load_or_raise_camera_error(tmp_path_factory, data):
    _load_or_camera_error(_write(tmp_path_factory.mktemp("b"), data))


# ------------------------------------------------------------------------ plain tests
BOMB = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)
)


def test_alias_bomb_is_refused_quickly_with_short_message(tmp_path):
    path = _write(tmp_path, BOMB + "model_type: MEI\n", "bomb.yaml")
    t0 = time.perf_counter()
    with pytest.raises(CameraError, match="aliases are not accepted") as ei:
        load(path)
    assert time.perf_counter() - t0 < 0.5
    assert len(str(ei.value)) < 600


def test_alias_in_kalibr_is_refused(tmp_path):
    text, _ = valid_calibration(random.Random(0), "kalibr")
    path = _write(
        tmp_path, "x: &r [640, 480]\n" + text.replace("resolution: [", "resolution: *r #[")
    )
    with pytest.raises(CameraError, match="aliases"):
        load(path)


@pytest.mark.parametrize("ext", ["json", "yaml"])
def test_deep_nesting_is_refused(tmp_path, ext):
    deep = "[" * 100_000 + "]" * 100_000
    text = deep if ext == "json" else "model_type: " + deep
    with pytest.raises(CameraError, match="nest"):
        load(_write(tmp_path, text, f"deep.{ext}"))


@pytest.mark.parametrize(
    "text",
    [
        '{"model": "pinhole", "width": ' + "9" * 5000 + ', "height": 480, "params": {}}',
        "%YAML:1.0\nmodel_type: MEI\nimage_width: " + "9" * 5000 + "\n",
        "cam0:\n  camera_model: pinhole\n  resolution: [" + "9" * 5000 + ", 480]\n",
        "1 PINHOLE " + "9" * 5000 + " 480 400 400 320 240\n",
        "cam0:\n  camera_model: pinhole\n  resolution: [0x" + "f" * 5000 + ", 480]\n",
    ],
    ids=["json", "opencv", "kalibr", "colmap", "yaml-hex"],
)
def test_huge_integers_raise_camera_error(tmp_path, text):
    path = _write(tmp_path, text)
    t0 = time.perf_counter()
    with pytest.raises(CameraError) as ei:
        load(path)
    assert time.perf_counter() - t0 < 0.5
    assert len(str(ei.value)) < 600


def test_kalibr_with_opencv_header_loads(tmp_path):
    text, expected = valid_calibration(random.Random(3), "kalibr")
    path = _write(tmp_path, "%YAML:1.0\n" + text, "camchain.yaml")
    assert detect_format(path) == "kalibr"
    assert load(path) == expected


@pytest.mark.parametrize(
    ("fmt", "name"),
    [
        ("basalt", "calib.yaml"),  # the extension does not decide
        ("raytun3r", "camera.txt"),
        ("opencv_yaml", "image_02.json"),
        ("colmap", "cameras.yaml"),
        ("kalibr", "camchain.json"),
    ],
)
def test_detect_format_ignores_extension(tmp_path, fmt, name):
    text, _ = valid_calibration(random.Random(1), fmt)
    assert detect_format(_write(tmp_path, text, name)) == fmt


def test_opencv_yaml_without_header_is_detected(tmp_path):
    text, expected = valid_calibration(random.Random(2), "opencv_yaml")
    path = _write(tmp_path, text.split("\n", 2)[2])  # no "%YAML:1.0", no "---"
    assert detect_format(path) == "opencv_yaml"
    assert load(path) == expected


@pytest.mark.parametrize(
    ("replace", "field"),
    [
        ("camera_model: pinhole", "camera_model: [pinhole]"),
        ("resolution: [", "resolution: 7 #["),
        ("distortion_model: none", "distortion_model: []"),
        ("camera_model: pinhole", "camera_model: true"),
    ],
)
def test_kalibr_wrong_types_raise_camera_error_naming_field(tmp_path, replace, field):
    text, _ = valid_calibration(random.Random(3), "kalibr")  # seed 3: pinhole, none
    assert "camera_model: pinhole" in text and "distortion_model: none" in text
    key = field.split(":")[0]
    with pytest.raises(CameraError, match=f"cam0.{key}"):
        load(_write(tmp_path, text.replace(replace, field)))


@pytest.mark.parametrize("bad", ["[]", "{}", "7", "true", "null"])
def test_model_type_wrong_type_lists_supported(tmp_path, bad):
    text, _ = valid_calibration(random.Random(0), "opencv_yaml")
    text = "\n".join(
        f"model_type: {bad}" if ln.startswith("model_type") else ln for ln in text.splitlines()
    )
    with pytest.raises(CameraError, match="model_type.*supported: \\['KANNALA_BRANDT'"):
        load(_write(tmp_path, text))


def test_string_number_and_bool_are_not_numbers(tmp_path):
    text, _ = valid_calibration(random.Random(0), "basalt")
    for bad in ('"400.0"', "true"):
        d = text.replace('"fx": ', '"fx": ' + bad + ', "_x": ', 1)
        with pytest.raises(CameraError, match="fx"):
            load(_write(tmp_path, d, "b.json"))


def test_yaml_exponent_without_dot_is_a_number(tmp_path):
    text, expected = valid_calibration(random.Random(0), "kalibr")
    cam = load(_write(tmp_path, text))
    text2 = text.replace("[]", "[0e0, 0e+0, 0E-0, 0e1]", 1).replace("cam_overlaps: [0e0", "x: [0")
    assert load(_write(tmp_path, text2)) == cam == expected


def test_oversized_and_non_utf8_files_raise(tmp_path):
    with pytest.raises(CameraError, match="larger than"):
        load(_write(tmp_path, b"#" * (MAX_FILE_BYTES + 1)))
    t0 = time.perf_counter()
    with pytest.raises(CameraError, match="YAML calibration file larger than"):
        load(_write(tmp_path, b"cam0:\n  x: [" + b"1.0, " * MAX_YAML_BYTES + b"]\n"))
    assert time.perf_counter() - t0 < 0.5
    with pytest.raises(CameraError, match="UTF-8"):
        load(_write(tmp_path, b"cam0:\n  camera_model: \xff\xfe\n"))


def test_huge_value_message_is_short(tmp_path):
    text, _ = valid_calibration(random.Random(0), "kalibr")
    big = "[" + ", ".join(["1.0"] * 10_000) + "]"
    path = _write(tmp_path, text.replace("intrinsics: [", f"intrinsics: {big} #["))
    with pytest.raises(CameraError, match="cam0.intrinsics") as ei:
        load(path)
    assert len(str(ei.value)) < 600
