"""Ground-truth correspondences and optical flow between two frames with known depth and poses.

For pixel centres uv_i of frame i with valid depth: X_i = D_i(uv_i) * ray(uv_i) (range depth),
X_j = R_ji X_i + t_ji with ``cam_j_from_cam_i = cam_j_from_world @ inv(cam_i_from_world)``,
uv_j = project(X_j). The match is *visible* when the projection is valid, uv_j lies in the image
(-0.5 <= u < W - 0.5, same for v), the pixel there is valid in frame j, and X_j is not occluded:

* ``occlusion="depth"`` (default, any sequence with depth): the range of frame j sampled
  bilinearly at uv_j (all contributing pixels valid) agrees with |X_j| within ``rel_tol``;
  conservative at depth edges (a blend of foreground and background fails the test);
* ``occlusion="raycast"`` (synthetic sequences only): a ray is cast in the analytic scene from
  camera j towards X_j; visible when nothing is hit closer than |X_j| (1 - rel_tol). Exact.
"""

from __future__ import annotations

import numpy as np
import torch

from raytun3r_plugin.datasets.sequence import Sequence
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import relative_pose  # re-exported: its one home

__all__ = ["bilinear_sample", "correspondences", "dense_flow", "relative_pose"]


def bilinear_sample(
    image: np.ndarray, uv: np.ndarray, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinearly sample ``image`` (H, W) at pixel positions ``uv`` (M, 2) (pixel centres at
    integers, coordinates clamped to the image).

    Returns ``(values (M,), ok (M,) bool)``; ``ok`` is False where a pixel with non-zero weight is
    invalid (``valid`` (H, W) bool, default ``image > 0``) or uv is not finite.
    """
    h, w = image.shape
    if valid is None:
        valid = image > 0
    finite = np.isfinite(uv).all(axis=1)
    u = np.clip(np.where(finite, uv[:, 0], 0.0), 0.0, w - 1.0)
    v = np.clip(np.where(finite, uv[:, 1], 0.0), 0.0, h - 1.0)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    fu = u - u0
    fv = v - v0
    wts = [(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv]
    idx = [(v0, u0), (v0, u1), (v1, u0), (v1, u1)]
    out = np.zeros(uv.shape[0], dtype=np.float64)
    ok = finite.copy()
    for wt, (vv, uu) in zip(wts, idx, strict=True):
        out += wt * image[vv, uu]
        ok &= (wt <= 1e-9) | valid[vv, uu]
    return out, ok


def _range_and_mask(seq: Sequence, i: int) -> tuple[np.ndarray, np.ndarray]:
    d = seq.range_depth(i)
    if d is None:
        raise InputError(
            f"sequence {seq.name!r} has no depth; correspondences need ground-truth depth"
        )
    d = np.asarray(d, dtype=np.float64)
    m = d > 0
    fm = seq.frame_mask(i)
    if fm is not None:
        m &= fm
    return d, m


def correspondences(
    seq: Sequence,
    i: int,
    j: int,
    stride: int = 1,
    rel_tol: float = 0.02,
    occlusion: str = "depth",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth matches from frame ``i`` to frame ``j`` of ``seq``.

    Args:
        seq: sequence with ``depth``, ``cam_from_world`` and ``camera``.
        i, j: frame indices.
        stride: sample every ``stride``-th pixel centre in u and v of frame i.
        rel_tol: relative range tolerance of the occlusion test.
        occlusion: "depth" (compare with frame j's depth map) or "raycast" (analytic scene of a
            synthetic sequence; see the module docstring).

    Returns:
        ``uv_i`` (M, 2) float64 pixel centres of frame i with valid depth, ``uv_j`` (M, 2)
        float64 their projections into frame j (NaN where the projection is invalid) and
        ``visible`` (M,) bool.
    """
    if seq.cam_from_world is None:
        raise InputError(f"sequence {seq.name!r} has no poses")
    cam = seq.camera
    h, w = seq.height, seq.width
    d_i, m_i = _range_and_mask(seq, i)
    d_j, m_j = _range_and_mask(seq, j)
    vs, us = np.mgrid[0:h:stride, 0:w:stride]
    sel = m_i[vs, us]
    vs, us = vs[sel], us[sel]
    uv_i = np.stack([us, vs], -1).astype(np.float64)
    rays, _ = cam.ray_table(dtype=torch.float64)
    rays = rays.detach().cpu().numpy().astype(np.float64)
    X_i = d_i[vs, us][:, None] * rays[vs, us]
    T = relative_pose(seq.cam_from_world, i, j)
    X_j = X_i @ T[:3, :3].T + T[:3, 3]
    uv_t, okp = cam.project(torch.from_numpy(X_j))
    uv_j = uv_t.detach().cpu().numpy().astype(np.float64).reshape(-1, 2)
    okp = okp.detach().cpu().numpy().reshape(-1).astype(bool) & np.isfinite(uv_j).all(axis=1)
    uv_j = np.where(okp[:, None], uv_j, np.nan)
    inside = (
        okp
        & (uv_j[:, 0] >= -0.5)
        & (uv_j[:, 0] < w - 0.5)
        & (uv_j[:, 1] >= -0.5)
        & (uv_j[:, 1] < h - 0.5)
    )
    ui = np.clip(np.rint(np.nan_to_num(uv_j[:, 0])), 0, w - 1).astype(np.int64)
    vi = np.clip(np.rint(np.nan_to_num(uv_j[:, 1])), 0, h - 1).astype(np.int64)
    inside &= m_j[vi, ui]
    rng_j = np.linalg.norm(X_j, axis=1)
    if occlusion == "depth":
        samp, ok = bilinear_sample(d_j, np.where(inside[:, None], uv_j, 0.0), m_j)
        visible = inside & ok & (np.abs(samp - rng_j) <= rel_tol * rng_j)
    elif occlusion == "raycast":
        visible = inside & _raycast_visible(seq, j, X_j, rng_j, rel_tol)
    else:
        raise InputError(f"occlusion must be 'depth' or 'raycast', got {occlusion!r}")
    return uv_i, uv_j, visible


def _raycast_visible(
    seq: Sequence, j: int, X_j: np.ndarray, rng_j: np.ndarray, rel_tol: float
) -> np.ndarray:
    from raytun3r_plugin.synthetic.generate import scene_of
    from raytun3r_plugin.synthetic.raycast import intersect

    scene = scene_of(seq)
    T = seq.cam_from_world[j]
    R = T[:3, :3]
    origin = -R.T @ T[:3, 3]
    dirs = (X_j / np.maximum(rng_j, 1e-12)[:, None]) @ R  # camera-frame unit dirs -> world
    hit = intersect(scene, origin, torch.from_numpy(dirs.astype(np.float32)))
    t = hit.t.numpy().astype(np.float64)
    return t >= rng_j * (1.0 - rel_tol)


def dense_flow(
    seq: Sequence, i: int, j: int, rel_tol: float = 0.02, occlusion: str = "depth"
) -> tuple[np.ndarray, np.ndarray]:
    """Dense ground-truth flow from frame ``i`` to ``j``: ``flow`` (H, W, 2) float32 in pixels
    (uv_j - uv_i, NaN where not visible) and ``visible`` (H, W) bool."""
    uv_i, uv_j, vis = correspondences(seq, i, j, stride=1, rel_tol=rel_tol, occlusion=occlusion)
    h, w = seq.height, seq.width
    flow = np.full((h, w, 2), np.nan, dtype=np.float32)
    visible = np.zeros((h, w), dtype=bool)
    u = uv_i[:, 0].astype(np.int64)
    v = uv_i[:, 1].astype(np.int64)
    flow[v[vis], u[vis]] = (uv_j[vis] - uv_i[vis]).astype(np.float32)
    visible[v[vis], u[vis]] = True
    return flow, visible
