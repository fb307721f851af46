"""Relative-pose targets from correspondences (MAGSAC++ on fisheye rays).

For a pair ``(i -> j)`` the target is the pose ``cam_j_from_cam_i`` (a point ``X_i`` in camera
``i`` maps to ``X_j = R @ X_i + t``), with the translation known only up to scale (``|t| = 1``).

Pipeline (docs/conventions.md section 7):

1. Unproject both ends of each match to unit rays with the camera model.
2. Keep matches whose rays are both within ``max_angle_deg`` of the optical axis (the normalised
   plane cannot represent rays at 90 degrees and beyond, and stretches them badly before).
3. Normalise the rays to the ``z = 1`` plane and run ``cv2.findEssentialMat`` with
   ``cameraMatrix = I``, ``method = cv2.USAC_MAGSAC`` (MAGSAC++), ``prob = 0.999`` and
   ``threshold = threshold_px / focal_px``, ``focal_px`` being the camera's pixels per radian
   at the image centre (measured through ``project``, so it is right for every camera model).
4. ``cv2.recoverPose`` picks the (R, t) with most points in front of both cameras.
5. ``refine=True`` (default): in our measurements (``docs/matching.md``) the pose from
   OpenCV's USAC_MAGSAC is much less accurate than its inlier set allows, most of all the
   translation direction on short baselines (several degrees, sometimes flipped), and the
   ``UsacParams`` local-optimisation / polisher settings made no difference. We polish (R, t) by Levenberg-Marquardt
   on the *tangent-Sampson* error of the unit rays (the epipolar residual divided by its gradient
   on the two tangent planes: an angle, so one pixel means the same everywhere on a fisheye),
   with a Cauchy loss of scale ``threshold`` radians: first on every usable ray (this escapes a
   wrong minimal-sample inlier set), then twice on the inliers (error below the threshold and
   positive depth along both rays). The sign of ``t`` is re-decided by cheirality each time.
   ``refine=False`` returns steps 3-4 exactly as OpenCV gives them.

Deterministic: OpenCV's USAC uses its own fixed-seed generator; ``cv2.setRNGSeed(seed)`` is
called before the estimation as well, so the output depends only on the inputs and ``seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from raytun3r_plugin.adaptation.matchers import Matches
from raytun3r_plugin.errors import InputError

# Re-exported for the tests and benchmarks that score targets: one definition, the atan2 form
# (the arccos copies that lived here lost precision near 0 degrees).
from raytun3r_plugin.metrics import rotation_error_deg, translation_direction_error_deg

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "PoseTarget",
    "camera_focal_px",
    "estimate_relative_pose",
    "rotation_error_deg",
    "tangent_sampson_error",
    "translation_direction_error_deg",
    "unproject_pixels",
]


@dataclass
class PoseTarget:
    """Relative-pose target ``cam_j_from_cam_i`` of an ordered pair ``(i -> j)``.

    Attributes:
        R: ``(3, 3)`` float64 rotation (``X_j = R @ X_i + t``).
        t: ``(3,)`` float64 unit translation direction; all zeros when ``ok`` is false.
        inlier_mask: ``(M,)`` bool over the matches the target was estimated from.
        n_inliers: number of inliers.
        ok: the estimate is usable (enough matches and inliers). When false, ``R`` is the
            identity and ``t`` is zero: do not use them as a target.
        reason: why ``ok`` is false (empty when ok).
    """

    R: np.ndarray
    t: np.ndarray
    inlier_mask: np.ndarray
    n_inliers: int
    ok: bool
    reason: str = field(default="")

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.inlier_mask = np.asarray(self.inlier_mask, dtype=bool).reshape(-1)
        self.n_inliers = int(self.n_inliers)
        self.ok = bool(self.ok)

    @classmethod
    def failed(cls, n_matches: int, reason: str) -> PoseTarget:
        """An unusable target for ``n_matches`` matches."""
        return cls(np.eye(3), np.zeros(3), np.zeros(n_matches, bool), 0, False, reason)

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` float64 ``cam_j_from_cam_i`` with the unit translation."""
        out = np.eye(4)
        out[:3, :3] = self.R
        out[:3, 3] = self.t
        return out


# --------------------------------------------------------------------------------------------
# Camera helpers (only the project/unproject contract of raytun3r_plugin.cameras is used)
# --------------------------------------------------------------------------------------------


def _camera_dtype(camera: Camera) -> torch.dtype:
    for value in vars(camera).values() if hasattr(camera, "__dict__") else ():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            return value.dtype
    return torch.float64


def unproject_pixels(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(M, 2)`` -> unit rays ``(M, 3)`` float64 and validity ``(M,)`` bool.

    Uses ``camera.unproject`` (float64 when the camera accepts it); rays that are not finite
    are marked invalid.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if uv.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    with torch.no_grad():
        try:
            rays, valid = camera.unproject(torch.from_numpy(uv))
        except (RuntimeError, TypeError):
            rays, valid = camera.unproject(torch.from_numpy(uv).to(_camera_dtype(camera)))
    rays_np = rays.detach().cpu().double().numpy().reshape(-1, 3)
    valid_np = valid.detach().cpu().numpy().astype(bool).reshape(-1)
    valid_np &= np.isfinite(rays_np).all(axis=1)
    norm = np.linalg.norm(rays_np, axis=1, keepdims=True)
    rays_np = np.where(norm > 0, rays_np / np.where(norm > 0, norm, 1.0), rays_np)
    return rays_np, valid_np


def camera_focal_px(camera: Camera) -> float:
    """Pixels per radian at the image centre (optical axis), measured through ``project``.

    For pinhole and Kannala-Brandt this is ``(fx + fy) / 2``; for unified / double-sphere
    models it is the local scale of the model on the axis (e.g. ``fx / (1 + xi)`` for UCM).
    """
    eps = 1e-4
    pts = torch.tensor(
        [[0.0, 0.0, 1.0], [math.tan(eps), 0.0, 1.0], [0.0, math.tan(eps), 1.0]],
        dtype=torch.float64,
    )
    with torch.no_grad():
        try:
            uv, _ = camera.project(pts)
        except (RuntimeError, TypeError):
            uv, _ = camera.project(pts.to(_camera_dtype(camera)))
    uv = uv.detach().cpu().double().numpy()
    fx = np.linalg.norm(uv[1] - uv[0]) / eps
    fy = np.linalg.norm(uv[2] - uv[0]) / eps
    focal = 0.5 * (fx + fy)
    if not np.isfinite(focal) or focal <= 0:
        raise InputError(f"cannot measure the focal length of camera {camera!r}")
    return float(focal)


# --------------------------------------------------------------------------------------------
# Geometry on unit rays
# --------------------------------------------------------------------------------------------


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _so3_exp(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    k = _skew(w)
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(theta) / theta * k + (1 - math.cos(theta)) / theta**2 * (k @ k)


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to unit ``t``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(t, helper)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t, b1)
    return np.stack([b1, b2], axis=1)


def _essentials(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``[t]_x R`` for (3, 3) / (K, 3, 3) rotations and (3,) / (K, 3) translations."""
    t = np.asarray(t)
    zero = np.zeros(t.shape[:-1])
    skew = np.stack(
        [
            np.stack([zero, -t[..., 2], t[..., 1]], -1),
            np.stack([t[..., 2], zero, -t[..., 0]], -1),
            np.stack([-t[..., 1], t[..., 0], zero], -1),
        ],
        -2,
    )
    return skew @ R


def _sampson_of(E: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Signed tangent-Sampson error (radians) of unit rays under essential matrices.

    ``E`` (3, 3) -> (N,), or (K, 3, 3) -> (K, N). The epipolar residual ``f2^T E f1`` is divided
    by the norm of its gradient projected on the tangent planes of both unit rays, which gives
    (to first order) the angular distance to the epipolar great circles; uniform over a fisheye
    image, unlike the Sampson error on the z = 1 plane.
    """
    ef1 = np.einsum("...ij,nj->...ni", E, f1)  # E f1
    etf2 = np.einsum("...ji,nj->...ni", E, f2)  # E^T f2
    r = np.einsum("ni,...ni->...n", f2, ef1)
    denom = (ef1**2).sum(-1) + (etf2**2).sum(-1) - 2.0 * r**2
    return r / np.sqrt(np.maximum(denom, 1e-300))


def _tangent_sampson(R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Signed tangent-Sampson error (radians) of unit rays ``f1 -> f2`` under (R, t)."""
    return _sampson_of(_essentials(R, t), f1, f2)


def tangent_sampson_error(
    R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray
) -> np.ndarray:
    """Signed tangent-Sampson error of unit-ray matches under a relative pose, radians.

    The error minimised by the pose polish (module docstring, step 5), public for the
    modules that score or refine against the same residual (e.g.
    :mod:`raytun3r_plugin.adaptation.intrinsics`).

    Args:
        R: ``(3, 3)`` rotation ``cam_j_from_cam_i``.
        t: ``(3,)`` translation direction (any non-zero length; the error is scale-free).
        f1, f2: ``(N, 3)`` unit rays of the matches in frames ``i`` and ``j``.

    Returns:
        ``(N,)`` float64: ``f2^T E f1`` over its tangent-plane gradient norm (``E = [t]_x R``),
        to first order the angle between each ray and its epipolar great circle.
    """
    return _tangent_sampson(
        np.asarray(R, np.float64),
        np.asarray(t, np.float64),
        np.asarray(f1, np.float64),
        np.asarray(f2, np.float64),
    )


def _depths(
    R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint-triangulation distances along both rays (``lam2 f2 ~ lam1 R f1 + t``) and the
    parallax (sine of the angle between ``R f1`` and ``f2``)."""
    a = f1 @ R.T
    ab = np.einsum("ni,ni->n", a, f2)
    at, bt = a @ t, f2 @ t
    det = np.maximum(1.0 - ab**2, 1e-300)
    return (-at + ab * bt) / det, (bt - ab * at) / det, np.linalg.norm(np.cross(a, f2), axis=1)


def _positive_depth(
    R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray, min_parallax: float
) -> np.ndarray:
    """(N,) bool: the triangulated point lies in front of both cameras (along both rays).

    Rays whose parallax is below ``min_parallax`` (radians) carry no depth sign and pass.
    """
    lam1, lam2, parallax = _depths(R, t, f1, f2)
    return ((lam1 > 0) & (lam2 > 0)) | (parallax < min_parallax)


def _cheiral_sign(
    R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray, scale: float
) -> np.ndarray:
    """``t`` or ``-t``: whichever puts more epipolar inliers with parallax in front of both
    cameras (the epipolar error cannot tell them apart)."""
    inl = np.abs(_tangent_sampson(R, t, f1, f2)) < scale
    lam1, lam2, par = _depths(R, t, f1[inl], f2[inl])
    use = par >= scale
    front = int(np.sum((lam1 > 0) & (lam2 > 0) & use))
    behind = int(np.sum((lam1 < 0) & (lam2 < 0) & use))
    return -t if behind > front else t


def _refine_pose(
    R: np.ndarray,
    t: np.ndarray,
    f1: np.ndarray,
    f2: np.ndarray,
    scale: float,
    iterations: int = 30,
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the Cauchy-robustified (scale ``scale``, radians) tangent-Sampson
    error of the rays; 5 DoF: ``R <- exp(w) R``, ``t <- normalise(t + B d)`` with ``B`` a basis
    of the tangent plane of ``t``. Forward-difference Jacobian (one batched evaluation)."""
    if f1.shape[0] < 6:
        return R, t
    eps = 1e-7
    lam = 1e-3
    res = _tangent_sampson(R, t, f1, f2)
    cost = float(np.sum(np.log1p((res / scale) ** 2)))
    for _ in range(iterations):
        B = _tangent_basis(t)
        Rs = np.stack([_so3_exp(eps * np.eye(3)[k]) @ R for k in range(3)] + [R, R])
        ts = np.stack([t, t, t, t + eps * B[:, 0], t + eps * B[:, 1]])
        ts /= np.linalg.norm(ts, axis=1, keepdims=True)
        jac = ((_sampson_of(_essentials(Rs, ts), f1, f2) - res) / eps).T  # (N, 5)
        w = 1.0 / (1.0 + (res / scale) ** 2)  # IRLS weights of the Cauchy loss
        A = jac.T @ (jac * w[:, None])
        g = jac.T @ (w * res)
        improved = converged = False
        for _attempt in range(8):
            try:
                step = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            R_new = _so3_exp(step[:3]) @ R
            t_new = t + B @ step[3:]
            t_new /= np.linalg.norm(t_new)
            res_new = _tangent_sampson(R_new, t_new, f1, f2)
            cost_new = float(np.sum(np.log1p((res_new / scale) ** 2)))
            if cost_new < cost:
                converged = cost - cost_new < 1e-9 * max(cost, 1e-30)
                R, t, res, cost = R_new, t_new, res_new, cost_new
                lam = max(lam / 10.0, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or converged:
            break
    u, _, vt = np.linalg.svd(R)  # re-orthonormalise
    R = u @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)))]) @ vt
    return R, t / np.linalg.norm(t)


# --------------------------------------------------------------------------------------------
# Public estimation
# --------------------------------------------------------------------------------------------


def estimate_relative_pose(
    matches: Matches,
    camera: Camera,
    max_angle_deg: float = 80.0,
    threshold_px: float = 1.0,
    seed: int = 0,
    *,
    min_matches: int = 15,
    min_inliers: int = 15,
    max_iters: int = 1000,
    refine: bool = True,
) -> PoseTarget:
    """Estimate ``cam_j_from_cam_i`` (R, unit t) from the matches of the pair ``(i -> j)``.

    Args:
        matches: correspondences ``uv_i -> uv_j`` (pixels).
        camera: a raytun3r camera (``project`` / ``unproject``) shared by both frames.
        max_angle_deg: use only matches whose two rays are within this angle of the optical
            axis (must be < 90).
        threshold_px: inlier threshold in pixels, converted to normalised units by dividing by
            :func:`camera_focal_px` (and used as an angle, ``threshold_px / focal_px`` radians, by
            the refinement).
        seed: seed for OpenCV's global RNG (``cv2.setRNGSeed``); same inputs + seed -> same
            output (OpenCV's USAC is deterministic by itself, so in practice the seed does not
            change the result).
        min_matches: fewer usable matches than this -> ``ok=False``.
        min_inliers: fewer final inliers than this -> ``ok=False``.
        max_iters: MAGSAC++ iteration cap.
        refine: robust polish of (R, t) on the rays (module docstring, step 5).

    Returns:
        :class:`PoseTarget`; ``inlier_mask`` is over all ``len(matches)`` input matches. Never
        raises for degenerate data: failures give ``ok=False`` with a ``reason``.
    """
    if not 0.0 < max_angle_deg < 90.0:
        raise InputError(f"max_angle_deg must be in (0, 90), got {max_angle_deg}")
    if not threshold_px > 0:
        raise InputError(f"threshold_px must be > 0, got {threshold_px}")
    n = len(matches)
    if n < max(min_matches, 5):
        return PoseTarget.failed(n, f"too few matches ({n} < {max(min_matches, 5)})")

    rays_i, ok_i = unproject_pixels(camera, matches.uv_i)
    rays_j, ok_j = unproject_pixels(camera, matches.uv_j)
    cos_max = math.cos(math.radians(max_angle_deg))
    usable = ok_i & ok_j & (rays_i[:, 2] > cos_max) & (rays_j[:, 2] > cos_max)
    idx = np.flatnonzero(usable)
    if idx.size < max(min_matches, 5):
        return PoseTarget.failed(
            n, f"too few matches within {max_angle_deg} deg of the axis ({idx.size})"
        )
    f1, f2 = rays_i[idx], rays_j[idx]
    x1 = np.ascontiguousarray(f1[:, :2] / f1[:, 2:3])
    x2 = np.ascontiguousarray(f2[:, :2] / f2[:, 2:3])
    thr = threshold_px / camera_focal_px(camera)

    cv2.setRNGSeed(int(seed))
    try:
        E, mask = cv2.findEssentialMat(
            x1,
            x2,
            cameraMatrix=np.eye(3),
            method=cv2.USAC_MAGSAC,
            prob=0.999,
            threshold=thr,
            maxIters=int(max_iters),
        )
    except cv2.error as exc:
        return PoseTarget.failed(n, f"findEssentialMat failed: {exc}")
    if E is None or E.ndim != 2 or E.shape[0] < 3 or E.shape[1] != 3 or mask is None:
        return PoseTarget.failed(n, "findEssentialMat found no model")
    E = np.ascontiguousarray(E[:3], dtype=np.float64)
    try:
        _, R, t, pose_mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    except cv2.error as exc:
        return PoseTarget.failed(n, f"recoverPose failed: {exc}")
    inl = pose_mask.reshape(-1) > 0
    R = np.asarray(R, np.float64)
    t = np.asarray(t, np.float64).reshape(3)
    if not np.isfinite(R).all() or not np.isfinite(t).all() or np.linalg.norm(t) == 0:
        return PoseTarget.failed(n, "recoverPose returned no valid pose")
    t = t / np.linalg.norm(t)

    if refine:
        # Robust polish on every usable ray first (escapes a bad minimal-sample inlier set),
        # then twice: select inliers, polish on them.
        R, t = _refine_pose(R, t, f1, f2, thr)
        t = _cheiral_sign(R, t, f1, f2, thr)
        for _ in range(2):
            inl = (np.abs(_tangent_sampson(R, t, f1, f2)) < thr) & _positive_depth(
                R, t, f1, f2, min_parallax=thr
            )
            if inl.sum() < 6:
                break
            R, t = _refine_pose(R, t, f1[inl], f2[inl], thr)
            t = _cheiral_sign(R, t, f1, f2, thr)
        inl = (np.abs(_tangent_sampson(R, t, f1, f2)) < thr) & _positive_depth(
            R, t, f1, f2, min_parallax=thr
        )

    mask_full = np.zeros(n, bool)
    mask_full[idx[inl]] = True
    n_inl = int(inl.sum())
    if n_inl < min_inliers:
        return PoseTarget(
            np.eye(3),
            np.zeros(3),
            mask_full,
            n_inl,
            False,
            f"too few inliers ({n_inl} < {min_inliers})",
        )
    return PoseTarget(R, t, mask_full, n_inl, True)
