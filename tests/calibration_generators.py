"""Valid calibration texts per format, and byte mutators, for property tests and fuzzing.

API (``rng`` is a :class:`random.Random`):

- ``valid_calibration(rng, fmt) -> (text, expected_camera)``: one file of format ``fmt`` (one of
  :data:`FORMATS`) and the camera :func:`raytun3r_plugin.cameras.formats.load` must return.
- ``valid_calibrations(rng, n) -> list[(format, text)]``: ``n`` files, formats cycled.
- ``mutate(rng, text) -> bytes``: the file with one structural or byte-level damage.
"""

from __future__ import annotations

import json
import random

from raytun3r_plugin.cameras import KannalaBrandt4, Pinhole
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats import to_colmap_line
from raytun3r_plugin.cameras.pinhole import OpenCVRadTan
from raytun3r_plugin.cameras.unified import EUCM, MEI, UCM, DoubleSphere

FORMATS = ("raytun3r", "basalt", "kalibr", "kalibr_cv_header", "opencv_yaml", "colmap")


def _intr(rng: random.Random) -> tuple[int, int, float, float, float, float]:
    """Image size (px) and fx, fy, cx, cy (px) of a moderate camera."""
    w = rng.choice([320, 640, 752, 1024])
    h = rng.choice([240, 480, 512])
    f = rng.uniform(0.35, 0.9) * w
    return (
        w,
        h,
        f,
        f * rng.uniform(0.98, 1.02),
        w / 2 + rng.uniform(-5, 5),
        h / 2 + rng.uniform(-5, 5),
    )


def _kb(rng: random.Random) -> list[float]:
    return [rng.uniform(-0.02, 0.02) for _ in range(4)]


def _radtan(rng: random.Random) -> list[float]:
    return [
        rng.uniform(-0.05, 0.05),
        rng.uniform(-0.01, 0.01),
        rng.uniform(-1e-3, 1e-3),
        rng.uniform(-1e-3, 1e-3),
    ]


def _basalt(rng: random.Random) -> tuple[str, Camera]:
    w, h, fx, fy, cx, cy = _intr(rng)
    kind = rng.choice(["kb4", "ds", "eucm", "ucm", "pinhole"])
    base = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    if kind == "kb4":
        vals = base | dict(zip(("k1", "k2", "k3", "k4"), _kb(rng), strict=True))
        cam: Camera = KannalaBrandt4(w, h, vals)
    elif kind == "ds":
        vals = base | {"xi": rng.uniform(-0.2, 0.2), "alpha": rng.uniform(0.45, 0.6)}
        cam = DoubleSphere(w, h, vals)
    elif kind == "eucm":
        vals = base | {"alpha": rng.uniform(0.4, 0.6), "beta": rng.uniform(0.9, 1.1)}
        cam = EUCM(w, h, vals)
    elif kind == "ucm":
        vals = base | {"alpha": rng.uniform(0.4, 0.6)}
        cam = UCM(w, h, vals)
    else:
        vals = base
        cam = Pinhole(w, h, vals)
    d = {
        "value0": {
            "T_imu_cam": [],
            "intrinsics": [{"camera_type": kind, "intrinsics": vals}],
            "resolution": [[w, h]],
        }
    }
    return json.dumps(d, indent=rng.choice([None, 2, 4])), cam


def _kalibr(rng: random.Random, header: bool) -> tuple[str, Camera]:
    w, h, fx, fy, cx, cy = _intr(rng)
    kind = rng.choice(["pinhole-none", "pinhole-radtan", "pinhole-equi", "omni-radtan", "ds"])
    if kind == "pinhole-none":
        cm, dm, intr, dist = "pinhole", "none", [fx, fy, cx, cy], []
        cam: Camera = Pinhole(w, h, {"fx": fx, "fy": fy, "cx": cx, "cy": cy})
    elif kind == "pinhole-radtan":
        dist = _radtan(rng)
        cm, dm, intr = "pinhole", "radtan", [fx, fy, cx, cy]
        cam = OpenCVRadTan(w, h, dict(zip(OpenCVRadTan.param_names, intr + dist, strict=True)))
    elif kind == "pinhole-equi":
        dist = _kb(rng)
        cm, dm, intr = "pinhole", rng.choice(["equidistant", "equi"]), [fx, fy, cx, cy]
        cam = KannalaBrandt4(w, h, dict(zip(KannalaBrandt4.param_names, intr + dist, strict=True)))
    elif kind == "omni-radtan":
        xi = rng.uniform(0.5, 1.5)
        dist = _radtan(rng)
        cm, dm, intr = "omni", "radtan", [xi, fx * (1 + xi), fy * (1 + xi), cx, cy]
        vals = {"fx": intr[1], "fy": intr[2], "cx": cx, "cy": cy, "xi": xi}
        vals |= dict(zip(("k1", "k2", "p1", "p2"), dist, strict=True))
        cam = MEI(w, h, vals)
    else:
        xi, alpha = rng.uniform(-0.2, 0.2), rng.uniform(0.45, 0.6)
        cm, dm, intr, dist = "ds", "none", [xi, alpha, fx, fy, cx, cy], []
        cam = DoubleSphere(w, h, {"xi": xi, "alpha": alpha, "fx": fx, "fy": fy, "cx": cx, "cy": cy})
    lines = ["%YAML:1.0"] if header else []
    lines += [
        "cam0:",
        "  cam_overlaps: []",
        f"  camera_model: {cm}",
        f"  distortion_coeffs: [{', '.join(repr(x) for x in dist)}]",
        f"  distortion_model: {dm}",
        f"  intrinsics: [{', '.join(repr(x) for x in intr)}]",
        f"  resolution: [{w}, {h}]",
        "  rostopic: /cam0/image_raw",
    ]
    return "\n".join(lines) + "\n", cam


def _opencv(rng: random.Random) -> tuple[str, Camera]:
    w, h, fx, fy, cx, cy = _intr(rng)
    kind = rng.choice(["MEI", "PINHOLE", "KANNALA_BRANDT"])
    lines = [
        "%YAML:1.0",
        "---",
        f"model_type: {kind}",
        "camera_name: image_02",
        f"image_width: {w}",
        f"image_height: {h}",
    ]
    if kind == "MEI":
        xi = rng.uniform(0.5, 1.5)
        k1, k2, p1, p2 = _radtan(rng)
        fx, fy = fx * (1 + xi), fy * (1 + xi)
        lines += [
            "mirror_parameters:",
            f"   xi: {xi:.16e}",
            "distortion_parameters:",
            f"   k1: {k1:.16e}",
            f"   k2: {k2:.16e}",
            f"   p1: {p1:.16e}",
            f"   p2: {p2:.16e}",
            "projection_parameters:",
            f"   gamma1: {fx:.16e}",
            f"   gamma2: {fy:.16e}",
            f"   u0: {cx:.16e}",
            f"   v0: {cy:.16e}",
        ]
        vals = {
            "xi": xi,
            "k1": k1,
            "k2": k2,
            "p1": p1,
            "p2": p2,
            "fx": fx,
            "fy": fy,
            "cx": cx,
            "cy": cy,
        }
        vals = {k: float(f"{v:.16e}") for k, v in vals.items()}
        cam: Camera = MEI(w, h, vals)
    elif kind == "PINHOLE":
        k1, k2, p1, p2 = _radtan(rng)
        lines += [
            "distortion_parameters:",
            f"   k1: {k1!r}",
            f"   k2: {k2!r}",
            f"   p1: {p1!r}",
            f"   p2: {p2!r}",
            "projection_parameters:",
            f"   fx: {fx!r}",
            f"   fy: {fy!r}",
            f"   cx: {cx!r}",
            f"   cy: {cy!r}",
        ]
        cam = OpenCVRadTan(
            w, h, {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "p1": p1, "p2": p2}
        )
    else:
        ks = _kb(rng)
        lines += ["projection_parameters:"] + [f"   k{i + 2}: {k!r}" for i, k in enumerate(ks)]
        lines += [f"   mu: {fx!r}", f"   mv: {fy!r}", f"   u0: {cx!r}", f"   v0: {cy!r}"]
        cam = KannalaBrandt4(
            w, h, dict(zip(KannalaBrandt4.param_names, [fx, fy, cx, cy, *ks], strict=True))
        )
    return "\n".join(lines) + "\n", cam


def valid_calibration(rng: random.Random, fmt: str) -> tuple[str, Camera]:
    """One valid file of format ``fmt`` and the camera it describes."""
    if fmt == "basalt":
        return _basalt(rng)
    if fmt in ("kalibr", "kalibr_cv_header"):
        return _kalibr(rng, header=fmt == "kalibr_cv_header")
    if fmt == "opencv_yaml":
        return _opencv(rng)
    if fmt == "raytun3r":
        text, cam = _basalt(rng)
        return cam.to_json(), cam
    if fmt == "colmap":
        text, cam = _basalt(rng)
        if cam.model not in ("pinhole", "kb4", "eucm"):
            w, h, fx, fy, cx, cy = _intr(rng)
            cam = Pinhole(w, h, {"fx": fx, "fy": fy, "cx": cx, "cy": cy})
        line = to_colmap_line(cam, rng.randint(1, 9))
        # COLMAP's +0.5 pixel shift is not exact in floating point: expect what the line says.
        vals = cam.values
        vals["cx"] = (vals["cx"] + 0.5) - 0.5
        vals["cy"] = (vals["cy"] + 0.5) - 0.5
        return "# Camera list\n" + line + "\n", type(cam)(cam.width, cam.height, vals)
    raise ValueError(f"unknown format {fmt!r}")


def valid_calibrations(rng: random.Random, n: int) -> list[tuple[str, str]]:
    """``n`` valid calibration texts ``(format, text)``, formats cycled through :data:`FORMATS`."""
    return [
        (FORMATS[i % len(FORMATS)], valid_calibration(rng, FORMATS[i % len(FORMATS)])[0])
        for i in range(n)
    ]


_BAD_VALUES = [
    "99999999999999999999" * 300,
    "[[[[[[[[1]]]]]]]]",
    ".nan",
    "NaN",
    "'text'",
    "[]",
    "{}",
    "true",
    "null",
    "-1",
    "1e999",
    "[" * 200 + "]" * 200,
    "&a x",
    "*a",
]


def mutate(rng: random.Random, text: str) -> bytes:
    """``text`` with one damage: a line deleted, a value replaced by a bad value (huge int,
    nested list, NaN, string, bool, alias...), bytes truncated or flipped, or an alias bomb."""
    op = rng.randrange(6)
    lines = text.splitlines()
    if op == 0 and lines:  # delete a line (a field)
        del lines[rng.randrange(len(lines))]
        return ("\n".join(lines) + "\n").encode()
    if op == 1:  # replace a number (or a word) by a bad value
        import re

        spans = [m.span() for m in re.finditer(r"-?[0-9][0-9.e+-]*|[A-Za-z_]+", text)]
        if spans:
            a, b = rng.choice(spans)
            bad = rng.choice(_BAD_VALUES)
            if text.lstrip().startswith("{"):
                bad = rng.choice(
                    [
                        "1" * 5000,
                        "[[[[1]]]]",
                        "NaN",
                        '"text"',
                        "[]",
                        "{}",
                        "true",
                        "null",
                        "-1",
                        "1e999",
                        "[" * 5000 + "]" * 5000,
                    ]
                )
            return (text[:a] + bad + text[b:]).encode()
    if op == 2:  # truncate
        raw = text.encode()
        return raw[: rng.randrange(len(raw) + 1)]
    if op == 3:  # flip bytes
        raw = bytearray(text.encode())
        for _ in range(rng.randint(1, 4)):
            if raw:
                raw[rng.randrange(len(raw))] = rng.randrange(256)
        return bytes(raw)
    if op == 4:  # swap types: wrap a value in a list, or unwrap a list
        raw = (
            text.replace("[", "", 1).replace("]", "", 1)
            if rng.random() < 0.5
            else text.replace(": ", ": [", 1)
        )
        return raw.encode()
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)
    )
    return (bomb + text).encode() if rng.random() < 0.5 else text.encode() + b"\xff\xfe"
