"""How closely OPENCV_FISHEYE fits the published lenses COLMAP and nerfstudio have no model for.

For TUM-VI cam0's double-sphere calibration (basalt ``tumvi_512_ds_calib.json``) and KITTI-360
image_02's MEI calibration (``calibration/image_02.yaml``), both at their native size, this
fits the Kannala-Brandt lens the exports write (``raytun3r_plugin.exports.lens.fit_kb4``) over
the region each format can use (within 89 degrees of the axis for COLMAP, the whole valid image
for nerfstudio) and prints the worst and median reprojection error over every valid pixel there
(docs/decisions.md, "Exports").

    python benchmarks/export_lens_fit.py
"""

from __future__ import annotations

import math
import time

import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.exports.lens import COLMAP_MAX_ANGLE_DEG, fit_kb4

CALIBRATIONS = {
    "TUM-VI cam0 DS 512 px": cameras.DoubleSphere(
        512,
        512,
        {"fx": 158.28600034966977, "fy": 158.2743455478755, "cx": 254.96116578191653}
        | {"cy": 256.8894394501779, "xi": -0.17213086034353243, "alpha": 0.5931177593944744},
    ),
    "KITTI-360 image_02 MEI 1400 px": cameras.MEI(
        1400,
        1400,
        {"fx": 1336.3220825849971, "fy": 1335.7883350012958, "cx": 716.94323510126321}
        | {"cy": 705.76498308221585, "xi": 2.2134047507854890, "k1": 0.016798235660113681}
        | {"k2": 1.6548773243373522, "p1": 4.2223943394772046e-04, "p2": 4.2462134260997584e-04},
    ),
}


def main() -> None:
    torch.set_num_threads(1)
    print(
        f"{'calibration':32} {'format':10} {'region':>12} {'worst px':>9} {'median px':>9} {'pixels':>8} {'s':>5}"
    )
    for name, camera in CALIBRATIONS.items():
        whole = math.degrees(camera.max_angle)
        for target, limit in (("COLMAP", min(COLMAP_MAX_ANGLE_DEG, whole)), ("nerfstudio", whole)):
            start = time.perf_counter()
            _, record = fit_kb4(camera, limit)
            print(
                f"{name:32} {target:10} {f'<= {limit:.1f} deg':>12} {record['worst_px']:9.4f} "
                f"{record['median_px']:9.4f} {record['pixels']:8d} {time.perf_counter() - start:5.1f}"
            )


if __name__ == "__main__":
    main()
