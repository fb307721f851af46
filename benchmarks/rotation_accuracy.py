"""How close the exported graph's rotation (``deploy.rotation.closest_rotation``, no SVD) is to
the SVD's, on the matrices Pi3's camera head could produce: realistic and adversarial.

For each case it prints the largest entry difference from the float64 SVD answer (the closest
proper rotation, U diag(1, 1, det(U V^T)) V^T of the row-normalised matrix) of

* the float32 SVD (what upstream Pi3 computes), and
* the float32 equivalent (what the frozen model and the ONNX graph compute),

each also scaled by the rotation's condition, gap = s2 + sign(det) s3: a rotation is
determined only to rounding / gap, by either method. Docs: docs/deployment.md.

    python benchmarks/rotation_accuracy.py [--count 5000]
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F

from raytun3r_plugin.deploy.rotation import closest_rotation


def svd_rotation(m: torch.Tensor) -> torch.Tensor:
    """The closest proper rotation by the SVD, by its definition (m: (N, 3, 3))."""
    u, _, vh = torch.linalg.svd(m)
    sign = torch.ones_like(m[..., 0])
    sign[..., 2] = torch.det(u @ vh)
    return (u * sign[..., None, :]) @ vh


def cases(count: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)

    def orthogonal():
        q = torch.linalg.qr(torch.randn(count, 3, 3, generator=g, dtype=torch.float64))[0]
        return q * torch.det(q)[:, None, None]

    rotation, u, v = orthogonal(), orthogonal(), orthogonal()
    reflection = rotation @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))

    def spectrum(*values):
        return u @ torch.diag(torch.tensor(values, dtype=torch.float64)) @ v.mT

    def noise(scale):
        return scale * torch.randn(count, 3, 3, generator=g, dtype=torch.float64)

    result = {
        "gaussian (untrained head)": torch.randn(count, 3, 3, generator=g, dtype=torch.float64),
        "rotation + 0.1 noise": rotation + noise(0.1),
        "det < 0, s = (1, .6, .3)": spectrum(1.0, 0.6, -0.3),
        "rank 2": spectrum(1.0, 0.5, 0.0),
        "s = (1, 1e-3, 1e-6)": spectrum(1.0, 1e-3, 1e-6),
        "s = (1, 1e-4, 1e-4)": spectrum(1.0, 1e-4, 1e-4),
    }
    for scale in (1e-1, 1e-2, 1e-3, 1e-4):
        result[f"reflection + {scale:g} noise"] = reflection + noise(scale)
    return {name: F.normalize(m.float(), p=2, dim=-1) for name, m in result.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=5000, help="matrices per case")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, {args.count} matrices per case; largest |R - R_svd64|")
    print("| case | min gap | SVD float32 | equivalent float32 | SVD x gap | equivalent x gap |")
    print("|---|---|---|---|---|---|")
    for name, m in cases(args.count).items():
        exact = svd_rotation(m.double())
        s = torch.linalg.svdvals(m.double())
        gap = s[:, 1] + torch.sign(torch.det(m.double())) * s[:, 2]
        errors = [
            (r.double() - exact).abs().amax(dim=(-2, -1))
            for r in (svd_rotation(m), closest_rotation(m))
        ]
        cells = [f"{float(e.max()):.1e}" for e in errors]
        cells += [f"{float((e * gap).max()):.1e}" for e in errors]
        print(f"| {name} | {float(gap.min()):.1e} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
