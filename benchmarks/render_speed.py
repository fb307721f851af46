"""Synthetic renderer speed: milliseconds per 504 x 504 frame, per camera model and scene.

Usage::

    python benchmarks/render_speed.py [--size 504] [--frames 5] [--threads 1] [--full]

Cameras: a 90-degree pinhole and the public TUM-VI (KB4, double sphere, EUCM; cam0, 512 px) and
KITTI-360 (MEI, image_02, 1400 px) calibrations, resized to ``size`` x ``size``. For each camera
and scene kind (indoor, outdoor) a few frames of a trajectory are rendered with a shared
:class:`Renderer` (camera rays cached), after one warm-up frame; the median wall-clock time per
frame and the median CPU time of this process per frame (``process_time``; on a loaded, shared
machine wall time grows with the other processes' load, CPU time much less) are printed, plus the
one-off ray-cache set-up time and the machine's 1-minute load average before and after.
``--full`` supersamples every pixel instead of only edge pixels.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.synthetic import Renderer, make_scene, make_trajectory
from raytun3r_plugin.synthetic.generate import camera_centres


def benchmark_cameras(size: int) -> dict[str, cameras.Camera]:
    """The benchmark cameras resized to ``size`` x ``size`` pixels."""
    tumvi_kb4 = cameras.KannalaBrandt4(
        512,
        512,
        {
            "fx": 190.97847715128717,
            "fy": 190.9733070521226,
            "cx": 254.93170605935475,
            "cy": 256.8974428996504,
            "k1": 0.0034823894022493434,
            "k2": 0.0007150348452162257,
            "k3": -0.0020532361418706202,
            "k4": 0.00020293673591811182,
        },
    )
    tumvi_ds = cameras.DoubleSphere(
        512,
        512,
        {
            "fx": 158.28600034966977,
            "fy": 158.2743455478755,
            "cx": 254.96116578191653,
            "cy": 256.8894394501779,
            "xi": -0.17213086034353243,
            "alpha": 0.5931177593944744,
        },
    )
    tumvi_eucm = cameras.EUCM(
        512,
        512,
        {
            "fx": 191.14799836282189,
            "fy": 191.13150963902818,
            "cx": 254.9585771534443,
            "cy": 256.88154645599448,
            "alpha": 0.6291060881178562,
            "beta": 1.0418067381860868,
        },
    )
    kitti_mei = cameras.MEI(
        1400,
        1400,
        {
            "fx": 1336.3220825849971,
            "fy": 1335.7883350012958,
            "cx": 716.94323510126321,
            "cy": 705.76498308221585,
            "xi": 2.2134047507854890,
            "k1": 0.016798235660113681,
            "k2": 1.6548773243373522,
            "p1": 4.2223943394772046e-04,
            "p2": 4.2462134260997584e-04,
        },
    )
    half = (size - 1) / 2.0
    return {
        "pinhole-90": cameras.Pinhole(
            size, size, {"fx": size / 2.0, "fy": size / 2.0, "cx": half, "cy": half}
        ),
        "kb4-tumvi": tumvi_kb4.resized(size, size),
        "ds-tumvi": tumvi_ds.resized(size, size),
        "eucm-tumvi": tumvi_eucm.resized(size, size),
        "mei-kitti360": kitti_mei.resized(size, size),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=504)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads while rendering (default 1)"
    )
    ap.add_argument("--full", action="store_true", help="supersample every pixel (not only edges)")
    args = ap.parse_args()
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), {args.size}x{args.size}, "
        f"{'full' if args.full else 'adaptive'} 2x2 supersampling, {args.frames} frames after 1 warm-up, "
        f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"
    )
    print(
        f"{'camera':<14} {'fov_deg':>8} {'setup_ms':>9} {'indoor_ms':>10} {'(cpu)':>7} {'outdoor_ms':>11} {'(cpu)':>7}"
    )
    for name, cam in benchmark_cameras(args.size).items():
        t0 = time.perf_counter()
        renderer = Renderer(cam, supersample=2, adaptive=not args.full, num_threads=args.threads)
        setup = (time.perf_counter() - t0) * 1e3
        row: list[float] = []
        for kind in ("indoor", "outdoor"):
            poses, _ = make_trajectory(
                kind, "handheld" if kind == "indoor" else "driving", cam, args.frames + 1, 0
            )
            scene = make_scene(kind, 0, camera_centres(poses))
            renderer.render(scene, poses[0])  # warm-up
            wall, cpu = [], []
            for k in range(1, args.frames + 1):
                t0, c0 = time.perf_counter(), time.process_time()
                renderer.render(scene, poses[k])
                wall.append((time.perf_counter() - t0) * 1e3)
                cpu.append((time.process_time() - c0) * 1e3)
            row += [statistics.median(wall), statistics.median(cpu)]
        print(
            f"{name:<14} {cam.fov_deg:>8.1f} {setup:>9.0f} {row[0]:>10.0f} {row[1]:>7.0f} {row[2]:>11.0f} {row[3]:>7.0f}"
        )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
