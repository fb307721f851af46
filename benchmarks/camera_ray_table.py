"""Time ``Camera.ray_table`` (all pixel rays of a 1400 x 1400 image) for every camera model.

Each repeat builds a fresh camera object, so the per-camera ray-table cache never hits; the
construction itself (parameter checks, the cached inverse tables of the distortion) is outside
the timed region. The models take turns in every repeat. Prints a markdown table with the
median time and the ratio to the pinhole model measured in the same run.

    python benchmarks/camera_ray_table.py [--repeats 7] [--size 1400] [--dtype float32]
"""

from __future__ import annotations

import argparse
import statistics
import time

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


def cameras(size: int) -> dict[str, tuple[Camera, str]]:
    """Realistic calibrations (docs/cameras.md) resized to ``size x size``."""

    def sq(cam: Camera) -> Camera:
        # Centre-crop to a square, then resize: the benchmark compares equal pixel counts.
        side = min(cam.width, cam.height)
        c = cam.cropped((cam.width - side) // 2, (cam.height - side) // 2, side, side)
        return c.resized(size, size)

    return {
        "pinhole": (
            sq(Pinhole(752, 480, [458.654, 457.296, 367.215, 248.375])),
            "EuRoC cam0 without distortion",
        ),
        "opencv": (
            sq(
                OpenCVRadTan(
                    752,
                    480,
                    [
                        458.654,
                        457.296,
                        367.215,
                        248.375,
                        -0.28340811,
                        0.07395907,
                        0.00019359,
                        1.76187114e-05,
                    ],
                )
            ),
            "EuRoC cam0 radtan",
        ),
        "kb4": (
            sq(
                KannalaBrandt4(
                    512,
                    512,
                    [
                        190.97847715128717,
                        190.9733070521226,
                        254.93170605935475,
                        256.8974428996504,
                        0.0034823894022493434,
                        0.0007150348452162257,
                        -0.0020532361418706202,
                        0.00020293673591811182,
                    ],
                )
            ),
            "TUM-VI cam0",
        ),  # fmt: skip
        "ucm": (sq(UCM(512, 512, [191.1, 191.1, 254.96, 256.88, 0.63])), "TUM-VI-like"),
        "eucm": (
            sq(
                EUCM(
                    512,
                    512,
                    [
                        191.14799836282189,
                        191.13150963902818,
                        254.9585771534443,
                        256.88154645599448,
                        0.6291060881178562,
                        1.0418067381860868,
                    ],
                )
            ),
            "basalt TUM-VI cam0",
        ),  # fmt: skip
        "ds": (
            sq(
                DoubleSphere(
                    512,
                    512,
                    [
                        158.28600034966977,
                        158.2743455478755,
                        254.96116578191653,
                        256.8894394501779,
                        -0.17213086034353243,
                        0.5931177593944744,
                    ],
                )
            ),
            "basalt TUM-VI cam0",
        ),  # fmt: skip
        "mei": (
            MEI(
                1400,
                1400,
                [
                    1336.3220825849971,
                    1335.7883350012958,
                    716.94323510126321,
                    705.76498308221585,
                    2.2134047507854890,
                    0.016798235660113681,
                    1.6548773243373522,
                    4.2223943394772046e-04,
                    4.2462134260997584e-04,
                ],
            ).resized(size, size),
            "KITTI-360 image_02",
        ),  # fmt: skip
        "thin_prism_fisheye": (
            sq(
                ThinPrismFisheye(
                    6048,
                    4032,
                    [
                        3411.42,
                        3410.02,
                        3040.79,
                        2013.57,
                        0.21047,
                        0.21102,
                        -5.36231e-06,
                        0.00051541,
                        -0.158023,
                        0.406856,
                        -8.46499e-05,
                        0.000861313,
                    ],
                )
            ),
            "ETH3D DSLR",
        ),  # fmt: skip
        "fov": (sq(FOV(640, 480, [256.1, 255.7, 319.8, 239.4, 0.9217])), "Project-Tango-like"),
        "fisheye624": (
            sq(
                Fisheye624(
                    640,
                    480,
                    [
                        241.3,
                        241.3,
                        316.9,
                        237.6,
                        -0.0255,
                        0.0979,
                        -0.0665,
                        0.0070,
                        0.0031,
                        -0.0013,
                        -0.0003,
                        0.0002,
                        0.0005,
                        -0.0001,
                        -0.0004,
                        0.00005,
                    ],
                )
            ),
            "Project-Aria-SLAM-like",
        ),  # fmt: skip
    }


def time_ray_tables(cams: dict[str, Camera], repeats: int, dtype: torch.dtype) -> dict[str, float]:
    """Median wall time (ms) of building the ray table of a fresh copy of each camera.

    The models take turns within each repeat (round robin), so that a change of machine load
    during the run affects all of them alike and the ratios stay meaningful.
    """
    times: dict[str, list[float]] = {name: [] for name in cams}
    for r in range(repeats + 1):
        for name, cam in cams.items():
            fresh = type(cam)(cam.width, cam.height, cam.params)
            t0 = time.perf_counter()
            fresh.ray_table(dtype=dtype)
            if r > 0:  # the first round warms up the allocator and the shared tables
                times[name].append(1000.0 * (time.perf_counter() - t0))
    return {name: statistics.median(ts) for name, ts in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--size", type=int, default=1400)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    args = ap.parse_args()
    dtype = getattr(torch, args.dtype)
    cams = cameras(args.size)
    results = time_ray_tables(
        {name: cam for name, (cam, _src) in cams.items()}, args.repeats, dtype
    )
    base = results["pinhole"]
    print(
        f"Ray table of a {args.size}x{args.size} image, {args.dtype}, CPU, "
        f"{torch.get_num_threads()} threads, torch {torch.__version__}, median of {args.repeats}\n"
    )
    print("| model | calibration | valid pixels | ms | x pinhole |")
    print("|---|---|---:|---:|---:|")
    for name, (cam, src) in cams.items():
        frac = float(cam.valid_mask().float().mean())
        print(
            f"| {name} | {src} | {100 * frac:.1f}% | {results[name]:.1f} | {results[name] / base:.2f} |"
        )


if __name__ == "__main__":
    main()
