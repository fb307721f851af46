"""The camera models' test cases: official and plausible calibrations of every model (full size
and scaled down) and independent NumPy references of their projections (tests/test_cameras_*)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from raytun3r_plugin.cameras import (
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
)

# Official calibrations (docs/cameras.md), used full size and scaled down.
TUMVI_KB4 = [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504,
             0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
             0.00020293673591811182]  # fmt: skip
TUMVI_DS = [158.28600034966977, 158.2743455478755, 254.96116578191653, 256.8894394501779,
            -0.17213086034353243, 0.5931177593944744]  # fmt: skip
TUMVI_EUCM = [191.14799836282189, 191.13150963902818, 254.9585771534443, 256.88154645599448,
              0.6291060881178562, 1.0418067381860868]  # fmt: skip
KITTI360_02 = [1336.3220825849971, 1335.7883350012958, 716.94323510126321, 705.76498308221585,
               2.2134047507854890, 0.016798235660113681, 1.6548773243373522,
               4.2223943394772046e-04, 4.2462134260997584e-04]  # fmt: skip
ETH3D_TP = [3411.42, 3410.02, 3041.29 - 0.5, 2014.07 - 0.5, 0.21047, 0.21102, -5.36231e-06,
            0.00051541, -0.158023, 0.406856, -8.46499e-05, 0.000861313]  # fmt: skip
# A Project-Tango-like FOV fisheye (640x480, omega about 53 degrees).
TANGO_FOV = [256.1, 255.7, 319.8, 239.4, 0.9217]
# A Project-Aria-SLAM-like Fisheye624 (640x480): plausible coefficients, not an official file.
ARIA_F624 = [241.3, 241.3, 316.9, 237.6, -0.0255, 0.0979, -0.0665, 0.0070, 0.0031, -0.0013,
             -0.0003, 0.0002, 0.0005, -0.0001, -0.0004, 0.00005]  # fmt: skip
EUROC_RADTAN = [458.654, 457.296, 367.215, 248.375, -0.28340811, 0.07395907, 0.00019359,
                1.76187114e-05]  # fmt: skip


def small_camera(cam: Camera, width: int = 200, height: int = 160) -> Camera:
    """Scale a real camera to 200 px wide, then centre-crop/pad to ``width x height``."""
    s = cam.resized(width, round(cam.height * width / cam.width))
    return s.cropped(0, (s.height - height) // 2, width, height)


def make_cameras() -> dict[str, Camera]:
    return {
        "pinhole": Pinhole(200, 160, [160.0, 158.0, 99.3, 80.1]),
        "opencv": small_camera(OpenCVRadTan(752, 480, EUROC_RADTAN)),
        "kb4": small_camera(KannalaBrandt4(512, 512, TUMVI_KB4)),
        "ucm": UCM(200, 160, [74.6, 74.5, 99.8, 80.3, 0.63]),
        "eucm": small_camera(EUCM(512, 512, TUMVI_EUCM)),
        "ds": small_camera(DoubleSphere(512, 512, TUMVI_DS)),
        "mei": small_camera(MEI(1400, 1400, KITTI360_02)),
        "thin_prism_fisheye": small_camera(ThinPrismFisheye(6048, 4032, ETH3D_TP), 200, 133),
        "fov": small_camera(FOV(640, 480, TANGO_FOV), 200, 150),
        "fisheye624": small_camera(Fisheye624(640, 480, ARIA_F624), 200, 150),
    }


CAMS = make_cameras()
NAMES = list(CAMS)


# ----------------------------------------------------------------------------- references
def ref_project(cam: Camera, X: np.ndarray) -> np.ndarray:
    """Independent numpy implementations written from the published formulas."""
    p = cam.values
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    fx, fy, cx, cy = p["fx"], p["fy"], p["cx"], p["cy"]
    if cam.model == "pinhole":
        return np.stack([fx * x / z + cx, fy * y / z + cy], -1)
    if cam.model == "opencv":
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        D = np.array([p["k1"], p["k2"], p["p1"], p["p2"]])
        uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
        return uv.reshape(-1, 2)
    if cam.model == "kb4":
        r = np.hypot(x, y)
        th = np.arctan2(r, z)
        td = th * (1 + p["k1"] * th**2 + p["k2"] * th**4 + p["k3"] * th**6 + p["k4"] * th**8)
        return np.stack([fx * td * x / r + cx, fy * td * y / r + cy], -1)
    if cam.model == "ucm":  # via the xi form: a different formula for the same model
        xi = p["alpha"] / (1 - p["alpha"])
        rho = np.linalg.norm(X, axis=1)
        den = z + xi * rho
        return np.stack([fx * (1 + xi) * x / den + cx, fy * (1 + xi) * y / den + cy], -1)
    if cam.model == "eucm":
        a, b = p["alpha"], p["beta"]
        d = np.sqrt(b * (x * x + y * y) + z * z)
        den = a * d + (1 - a) * z
        return np.stack([fx * x / den + cx, fy * y / den + cy], -1)
    if cam.model == "ds":
        xi, a = p["xi"], p["alpha"]
        d1 = np.linalg.norm(X, axis=1)
        k = xi * d1 + z
        d2 = np.sqrt(x * x + y * y + k * k)
        den = a * d2 + (1 - a) * k
        return np.stack([fx * x / den + cx, fy * y / den + cy], -1)
    if cam.model == "mei":
        s = X / np.linalg.norm(X, axis=1, keepdims=True)
        xu = s[:, 0] / (s[:, 2] + p["xi"])
        yu = s[:, 1] / (s[:, 2] + p["xi"])
        r2 = xu * xu + yu * yu
        rad = 1 + p["k1"] * r2 + p["k2"] * r2 * r2
        xd = xu * rad + 2 * p["p1"] * xu * yu + p["p2"] * (r2 + 2 * xu * xu)
        yd = yu * rad + p["p1"] * (r2 + 2 * yu * yu) + 2 * p["p2"] * xu * yu
        return np.stack([fx * xd + cx, fy * yd + cy], -1)
    if cam.model == "thin_prism_fisheye":  # COLMAP's route: normalised plane, then atan(R)
        a, b = x / z, y / z
        R = np.hypot(a, b)
        th = np.arctan(R)
        u, v = a * th / R, b * th / R
        r2 = u * u + v * v
        rad = p["k1"] * r2 + p["k2"] * r2**2 + p["k3"] * r2**3 + p["k4"] * r2**4
        ud = u + u * rad + 2 * p["p1"] * u * v + p["p2"] * (r2 + 2 * u * u) + p["sx1"] * r2
        vd = v + v * rad + 2 * p["p2"] * u * v + p["p1"] * (r2 + 2 * v * v) + p["sy1"] * r2
        return np.stack([fx * ud + cx, fy * vd + cy], -1)
    if cam.model == "fov":  # COLMAP's FOVCameraModel: normalised plane, atan(2 r tan(w/2)) / (r w)
        a, b = x / z, y / z
        R = np.hypot(a, b)
        factor = np.arctan(2 * R * np.tan(p["omega"] / 2)) / (R * p["omega"])
        return np.stack([fx * a * factor + cx, fy * b * factor + cy], -1)
    if cam.model == "fisheye624":  # COLMAP's route: normalised plane, atan(R), radial, then prism
        a, b = x / z, y / z
        R = np.hypot(a, b)
        th = np.arctan(R)
        u, v = a * th / R, b * th / R
        t2 = u * u + v * v
        rad = 1 + sum(p[f"k{i}"] * t2 ** (i + 1) for i in range(6))
        xr, yr = u * rad, v * rad
        r2 = xr * xr + yr * yr
        dx = 2 * p["p1"] * xr * yr + p["p0"] * (r2 + 2 * xr * xr) + p["s0"] * r2 + p["s1"] * r2 * r2
        dy = 2 * p["p0"] * xr * yr + p["p1"] * (r2 + 2 * yr * yr) + p["s2"] * r2 + p["s3"] * r2 * r2
        return np.stack([fx * (xr + dx) + cx, fy * (yr + dy) + cy], -1)
    raise AssertionError(cam.model)


def directions(n: int, max_angle: float, seed: int = 0, min_angle: float = 0.0) -> torch.Tensor:
    """(n, 3) float64 directions with angle from the axis uniform in [min_angle, max_angle],
    random azimuth, random (positive) length."""
    g = torch.Generator().manual_seed(seed)
    th = min_angle + (max_angle - min_angle) * torch.rand(n, generator=g, dtype=torch.float64)
    ph = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
    d = torch.stack([th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()], -1)
    return d * (0.1 + 10 * torch.rand(n, 1, generator=g, dtype=torch.float64))
