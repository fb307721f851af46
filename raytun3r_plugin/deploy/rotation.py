"""The closest rotation to a 3x3 matrix without an SVD: what a frozen Pi3 runs in place of
``torch.svd`` (ONNX has no SVD operator).

Pi3's camera head (``CameraHead.svd_orthogonalize``) normalises the rows of each predicted
3x3 matrix M and returns the proper rotation closest to it in the Frobenius norm: with
M = U diag(s) V^T, R = U diag(1, 1, d) V^T, d = det(U V^T) (the singular vectors of the
smallest singular value flipped when M has a negative determinant). That R is the unique
maximiser of trace(R^T M) over SO(3) whenever s2 + d s3 > 0.

Here it comes from Horn's (Davenport's) quaternion form of the same problem: for a unit
quaternion q, trace(R(q)^T M) = q^T N q with N the symmetric, traceless 4x4 matrix built
linearly from M, so the maximiser is the eigenvector of N's largest eigenvalue. Its
eigenvalues are s1 + s2 + d s3, s1 - s2 - d s3, -s1 + s2 - d s3 and -s1 - s2 + d s3, so the
det < 0 case needs no branch: the quaternion always describes a rotation, the one the SVD
path returns. The eigenvector comes from a power method with a fixed number of steps, each
step a squaring (the k-th squared matrix is the 2^k-th power) of N shifted to be positive
semi-definite and rescaled to unit trace; only matmuls, sums, a division, an argmax and a
gather, which ONNX has. Accuracy is that of upstream's own float32 SVD (docs/deployment.md).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

#: Squarings of the shifted matrix: the power method runs 2**SQUARINGS steps. Its error falls
#: as ((lambda2 + c) / (lambda1 + c)) ** (2**k); 30 squarings reach float32 rounding for
#: eigenvalue gaps down to ~1e-7 of the shift, far below where the rotation itself is
#: determined to float32 precision.
SQUARINGS = 30
#: Added to the shift so that the zero matrix gives the identity (as the SVD path does).
_SHIFT_FLOOR = 1e-6


def horn_matrix(m: torch.Tensor) -> torch.Tensor:
    """N (..., 4, 4) with trace(R(q)^T m) = q^T N q for unit quaternions q = (w, x, y, z).

    m: (..., 3, 3). N is symmetric and traceless.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    rows = (
        (m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01),
        (m21 - m12, m00 - m11 - m22, m01 + m10, m02 + m20),
        (m02 - m20, m01 + m10, m11 - m00 - m22, m12 + m21),
        (m10 - m01, m02 + m20, m12 + m21, m22 - m00 - m11),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def quaternion_to_rotation(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = q.unbind(-1)
    rows = (
        (w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def closest_rotation(m: torch.Tensor, squarings: int = SQUARINGS) -> torch.Tensor:
    """The proper rotation closest to each matrix in the Frobenius norm, without an SVD.

    m: (..., 3, 3) in any scale. Returns (..., 3, 3) rotations (det +1), in m's dtype:
    U diag(1, 1, det(U V^T)) V^T for m = U diag(s) V^T, as the SVD path computes it. Where
    that rotation is not unique (s2 + det-sign * s3 = 0, e.g. an exact reflection) any of the
    maximisers may be returned, as with the SVD.
    """
    n = horn_matrix(m)
    # sum |lambda| <= s1 + s2 + s3 <= sqrt(3) |m|_F: the shifted matrix is positive semi-definite.
    shift = math.sqrt(3.0) * torch.linalg.vector_norm(m, dim=(-2, -1)) + _SHIFT_FLOOR
    eye = torch.eye(4, dtype=m.dtype, device=m.device)
    power = n + shift[..., None, None] * eye
    for _ in range(squarings):
        power = power @ power
        power = power / power.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    # The limit is q q^T: its column with the largest diagonal entry is the best-scaled copy of q.
    column = power.diagonal(dim1=-2, dim2=-1).argmax(-1)
    index = column[..., None, None].expand(*column.shape, 4, 1)
    q = F.normalize(torch.take_along_dim(power, index, dim=-1)[..., 0], p=2, dim=-1)
    return quaternion_to_rotation(q)


def frozen_svd_orthogonalize(owner: nn.Module, m: torch.Tensor) -> torch.Tensor:
    """Pi3's ``CameraHead.svd_orthogonalize`` without the SVD: rows of each 3x3 normalised,
    then the closest proper rotation.

    m: (B, 9) or (B, 3, 3) float; returns (B, 3, 3).
    """
    m = F.normalize(m.reshape(-1, 3, 3), p=2, dim=-1)
    return closest_rotation(m)
