"""Evaluation metrics (docs/conventions.md section 8): relative pose errors, d_reproj, AbsRel, delta < 1.25.

Conventions: poses are ``cam_from_world`` (N, 4, 4); the relative pose of pair (i, j) is
``cam_j_from_cam_i = cam_j_from_world @ inv(cam_i_from_world)``. Angles are reported in degrees.
Depth is range along the unit ray unless stated (``depth_kind="z"``).

Choices (documented in ``docs/synthetic_and_datasets.md``):

* rotation error: geodesic angle of ``R_pred^T R_gt`` computed as ``atan2(|vee(M - M^T)| / 2,
  (tr M - 1) / 2)`` (accurate near 0 and 180 degrees, unlike ``acos``);
* translation-direction error: angle between the two translation vectors, 0..180 degrees
  (signed, as in the paper); ``folded=True`` gives ``min(e, 180 - e)`` (0..90);
* pairs whose ground-truth translation is shorter than ``min_translation`` are skipped and
  counted; skipping depends on ground truth only, so every method is scored on the same pairs;
  non-finite predictions give NaN errors (reported as ``n_nan``, and as failures in AUC);
* ``d_reproj``: see :func:`d_reproj`;
* AbsRel / delta < 1.25: prediction scaled per image by the median ratio (default) or the
  least-squares scale, over pixels with finite, positive ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.poses import _as_torch_pair, relative_poses, rotation_angle, translation_angle

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = [
    "abs_rel",
    "align_scale",
    "auc",
    "d_reproj",
    "delta_125",
    "relative_pose_errors",
    "relative_poses",
    "rotation_error_deg",
    "summarize",
    "translation_direction_error_deg",
]


# --------------------------------------------------------------------------------------------
# Pose errors
# --------------------------------------------------------------------------------------------


def rotation_error_deg(R_pred: Any, R_gt: Any) -> Any:
    """Geodesic angle (degrees, 0..180) between rotations ``R_pred`` and ``R_gt`` (..., 3, 3).

    :func:`raytun3r_plugin.poses.rotation_angle` in degrees. numpy in -> numpy out (float64);
    a torch tensor in either argument -> torch out (promoted dtype).
    """
    angle = rotation_angle(R_pred, R_gt)
    return torch.rad2deg(angle) if isinstance(angle, torch.Tensor) else np.degrees(angle)


def translation_direction_error_deg(
    t_pred: Any, t_gt: Any, folded: bool = False, eps: float = 1e-12
) -> Any:
    """Angle (degrees) between translation directions ``t_pred`` and ``t_gt`` (..., 3).

    Signed version (default): 0..180 (a reversed direction scores 180). ``folded=True``:
    ``min(e, 180 - e)``, 0..90. A vector shorter than ``eps`` gives NaN. numpy or torch in,
    the same out (torch if either argument is a tensor).
    """
    if isinstance(t_pred, torch.Tensor) or isinstance(t_gt, torch.Tensor):
        a, b = _as_torch_pair(t_pred, t_gt)
        e = torch.rad2deg(translation_angle(a, b))
        short = (torch.linalg.vector_norm(a, dim=-1) < eps) | (
            torch.linalg.vector_norm(b, dim=-1) < eps
        )
        e = torch.where(short, torch.full_like(e, math.nan), e)
        return torch.minimum(e, 180.0 - e) if folded else e
    a = np.asarray(t_pred, dtype=np.float64)
    b = np.asarray(t_gt, dtype=np.float64)
    e = np.degrees(translation_angle(a, b))
    short = (np.linalg.norm(a, axis=-1) < eps) | (np.linalg.norm(b, axis=-1) < eps)
    e = np.where(short, np.nan, e)
    return np.minimum(e, 180.0 - e) if folded else e


def relative_pose_errors(
    cam_from_world_pred: Any,
    cam_from_world_gt: Any,
    pairs: Iterable[tuple[int, int]] | np.ndarray | None = None,
    min_translation: float = 1e-3,
    folded: bool = False,
) -> dict[str, Any]:
    """Rotation and translation-direction errors of relative poses over frame pairs.

    Args:
        cam_from_world_pred: (N, 4, 4) predicted poses (any global scale; world frame arbitrary).
        cam_from_world_gt: (N, 4, 4) ground-truth poses.
        pairs: (P, 2) frame index pairs (i, j); default consecutive (k, k + 1).
        min_translation: pairs whose ground-truth relative translation is shorter than this
            (units of the ground truth, metres for the readers here) are skipped and counted,
            never scored.
        folded: fold the translation error to 0..90 (default signed, 0..180).

    Returns:
        dict with ``pairs`` (P', 2) int64 the scored pairs, ``rotation_deg`` (P',),
        ``translation_deg`` (P',), ``skipped_pairs`` (S, 2), ``n_pairs`` P', ``n_skipped`` S,
        ``gt_translation`` (P',) ground-truth baseline lengths, ``min_translation``, ``folded``.
    """
    pred = np.asarray(
        cam_from_world_pred.detach().cpu()
        if isinstance(cam_from_world_pred, torch.Tensor)
        else cam_from_world_pred,
        dtype=np.float64,
    )
    gt = np.asarray(
        cam_from_world_gt.detach().cpu()
        if isinstance(cam_from_world_gt, torch.Tensor)
        else cam_from_world_gt,
        dtype=np.float64,
    )
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[1:] != (4, 4):
        raise InputError(f"pose arrays must both be (N, 4, 4), got {pred.shape} and {gt.shape}")
    n = gt.shape[0]
    if pairs is None:
        p = (
            np.stack([np.arange(n - 1), np.arange(1, n)], -1)
            if n > 1
            else np.zeros((0, 2), np.int64)
        )
    else:
        p = np.asarray(
            list(pairs) if not isinstance(pairs, np.ndarray) else pairs, dtype=np.int64
        ).reshape(-1, 2)
    if p.size and (p.min() < 0 or p.max() >= n):
        raise InputError(f"pair indices must be in [0, {n})")
    rel_gt = relative_poses(gt, p)
    rel_pred = relative_poses(pred, p)
    base = np.linalg.norm(rel_gt[:, :3, 3], axis=1)
    keep = np.isfinite(base) & (base >= min_translation)
    rot = rotation_error_deg(rel_pred[keep, :3, :3], rel_gt[keep, :3, :3])
    trans = translation_direction_error_deg(
        rel_pred[keep, :3, 3], rel_gt[keep, :3, 3], folded=folded
    )
    return {
        "pairs": p[keep],
        "rotation_deg": np.asarray(rot, dtype=np.float64),
        "translation_deg": np.asarray(trans, dtype=np.float64),
        "skipped_pairs": p[~keep],
        "n_pairs": int(keep.sum()),
        "n_skipped": int((~keep).sum()),
        "gt_translation": base[keep],
        "min_translation": float(min_translation),
        "folded": bool(folded),
    }


# --------------------------------------------------------------------------------------------
# d_reproj
# --------------------------------------------------------------------------------------------


def _np(x: Any, dtype=np.float64) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def _sample_depth(depth: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear depth at uv (M, 2); ok where every pixel with non-zero weight has a finite,
    positive depth and uv lies within the pixel-centre grid."""
    h, w = depth.shape
    u, v = uv[:, 0], uv[:, 1]
    inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    uc = np.where(inside, u, 0.0)
    vc = np.where(inside, v, 0.0)
    u0 = np.floor(uc).astype(np.int64)
    v0 = np.floor(vc).astype(np.int64)
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    fu, fv = uc - u0, vc - v0
    good = np.isfinite(depth) & (depth > 0)
    d = np.where(good, depth, 0.0)
    out = np.zeros(uv.shape[0])
    ok = inside.copy()
    for wt, vv, uu in (
        ((1 - fu) * (1 - fv), v0, u0),
        (fu * (1 - fv), v0, u1),
        ((1 - fu) * fv, v1, u0),
        (fu * fv, v1, u1),
    ):
        out += wt * d[vv, uu]
        ok &= (wt <= 1e-12) | good[vv, uu]
    return out, ok


def _points(
    depth: np.ndarray, camera: Camera, uv: np.ndarray, depth_kind: str
) -> tuple[np.ndarray, np.ndarray]:
    """Back-projected points (M, 3) at uv with bilinear depth, and their validity (M,)."""
    d, ok = _sample_depth(depth, uv)
    rays, okr = camera.unproject(torch.from_numpy(np.where(np.isfinite(uv), uv, 0.0)))
    rays = rays.detach().cpu().numpy().astype(np.float64)
    ok &= okr.detach().cpu().numpy().astype(bool)
    if depth_kind == "z":
        rz = rays[:, 2]
        ok &= rz > 1e-9
        d = d / np.where(rz > 1e-9, rz, 1.0)
    elif depth_kind != "range":
        raise InputError(f"depth_kind must be 'range' or 'z', got {depth_kind!r}")
    return d[:, None] * rays, ok


def _project_error(camera: Camera, X: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uvp, okp = camera.project(torch.from_numpy(X))
    uvp = uvp.detach().cpu().numpy().astype(np.float64)
    okp = okp.detach().cpu().numpy().astype(bool) & np.isfinite(uvp).all(axis=1)
    err = np.linalg.norm(uvp - uv, axis=1)
    return np.where(okp, err, np.nan), okp


def d_reproj(
    depth_i: Any,
    camera: Camera,
    uv_i: Any,
    uv_j: Any,
    cam_j_from_cam_i_gt: Any,
    conf: Any = None,
    depth_j: Any = None,
    *,
    depth_kind: str = "range",
    conf_threshold: float | None = None,
    huber_px: float = 1.0,
    iterations: int = 10,
    return_details: bool = False,
) -> float | dict[str, Any]:
    """Reprojection error (pixels) of predicted depth under the ground-truth relative pose.

    Points X_i = D_i(uv_i) * ray(uv_i) (depth sampled bilinearly; a match is dropped when a
    contributing pixel has no depth) are mapped with the ground-truth pose (R, t) after a
    per-pair scale s, and compared with the matched pixels: ``mean ||project(R s X_i + t) -
    uv_j||`` over the used matches whose projection is valid.

    The scale is fitted in closed form, robustly:

    * without ``depth_j`` (default): each match constrains s R X_i + t to lie on the ray b_j of
      uv_j. With P = I - b_j b_j^T, the perpendicular residual P (s R X_i + t) is linear in s;
      divided by the range |s R X_i + t| it is the sine of the angular error. s starts at the
      median of the per-match closed-form scales and is refined by iteratively re-weighted least
      squares (``iterations`` steps), ``s = -sum w a.c / sum w |a|^2`` with a = P R X_i,
      c = P t and weights ``w = conf * huber(pixel error; huber_px) / range^2``;
    * with ``depth_j`` (the other view's predicted depth, same scale): the 3-D residual
      ``s (R X_i - X_j) + t`` (X_j from depth_j at uv_j), same initialisation and IRLS, weights
      divided by |s X_j|^2.

    A non-positive or non-finite fit (e.g. zero baseline) falls back to s = 1.

    Args:
        depth_i: (H, W) predicted depth of frame i (0 / non-finite = unknown).
        camera: the camera of both frames.
        uv_i, uv_j: (M, 2) matched pixels in frames i and j.
        cam_j_from_cam_i_gt: (4, 4) ground-truth relative pose.
        conf: (M,) match confidences (weights of the fit), default ones.
        depth_j: optional (H, W) predicted depth of frame j (switches to the 3-D residual).
        depth_kind: "range" (default) or "z".
        conf_threshold: drop matches with conf below it (from the fit and the mean).
        huber_px: Huber threshold (pixels) of the IRLS weights.
        iterations: IRLS iterations.
        return_details: return a dict (``d_reproj``, ``scale``, ``n_matches``, ``n_used``,
            ``n_invalid_projection``, ``errors`` (M,) pixel errors, NaN where unused) instead
            of the float.

    Returns:
        The mean pixel error (float; NaN if no match is usable) or the details dict.
    """
    D = _np(depth_i)
    ui = _np(uv_i).reshape(-1, 2)
    uj = _np(uv_j).reshape(-1, 2)
    if ui.shape != uj.shape:
        raise InputError(f"uv_i and uv_j must have the same shape, got {ui.shape} and {uj.shape}")
    m = ui.shape[0]
    T = _np(cam_j_from_cam_i_gt).reshape(4, 4)
    R, t = T[:3, :3], T[:3, 3]
    w0 = np.ones(m) if conf is None else _np(conf).reshape(-1)
    X, ok = _points(D, camera, ui, depth_kind)
    ok &= np.isfinite(uj).all(axis=1) & np.isfinite(w0) & (w0 > 0)
    if conf_threshold is not None:
        ok &= w0 >= conf_threshold
    if depth_j is not None:
        Xj, okj = _points(_np(depth_j), camera, uj, depth_kind)
        ok &= okj
    else:
        bj, okb = camera.unproject(torch.from_numpy(np.where(np.isfinite(uj), uj, 0.0)))
        bj = bj.detach().cpu().numpy().astype(np.float64)
        ok &= okb.detach().cpu().numpy().astype(bool)
    idx = np.flatnonzero(ok)
    errors = np.full(m, np.nan)
    details: dict[str, Any] = {"n_matches": m, "n_used": int(idx.size)}
    if idx.size == 0:
        details.update(d_reproj=math.nan, scale=math.nan, n_invalid_projection=0, errors=errors)
        return details if return_details else math.nan
    RX = X[idx] @ R.T
    wc = w0[idx]
    if depth_j is not None:
        a = RX - Xj[idx]
        c = np.broadcast_to(t, a.shape)
    else:
        b = bj[idx]
        a = RX - b * np.sum(RX * b, axis=1, keepdims=True)
        c = t[None, :] - b * (b @ t)[:, None]
    aa = np.sum(a * a, axis=1)
    ac = np.sum(a * c, axis=1)
    per = np.where(aa > 0, -ac / np.where(aa > 0, aa, 1.0), np.nan)
    per = per[np.isfinite(per)]
    s = float(np.median(per)) if per.size else 1.0
    if not (math.isfinite(s) and s > 0):
        s = 1.0
    for _ in range(max(0, int(iterations))):
        q = s * RX + t
        err, okp = _project_error(camera, q, uj[idx])
        hub = np.where(
            okp, np.minimum(1.0, huber_px / np.maximum(np.nan_to_num(err, nan=np.inf), 1e-12)), 0.0
        )
        if depth_j is not None:
            norm2 = np.maximum(s * s * np.sum(Xj[idx] ** 2, axis=1), 1e-24)
        else:
            norm2 = np.maximum(np.sum(q * q, axis=1), 1e-24)
            hub = np.where(
                np.sum(q * b, axis=1) > 0, hub, 0.0
            )  # a point behind the ray is an outlier
        w = wc * hub / norm2
        den = float(np.sum(w * aa))
        if den <= 0:
            break
        s_new = -float(np.sum(w * ac)) / den
        if not (math.isfinite(s_new) and s_new > 0):
            break
        converged = abs(s_new - s) <= 1e-12 * abs(s)
        s = s_new
        if converged:
            break
    err, okp = _project_error(camera, s * RX + t, uj[idx])
    errors[idx] = err
    value = float(np.mean(err[okp])) if okp.any() else math.nan
    details.update(d_reproj=value, scale=s, n_invalid_projection=int((~okp).sum()), errors=errors)
    return details if return_details else value


# --------------------------------------------------------------------------------------------
# Dense depth metrics
# --------------------------------------------------------------------------------------------


def _depth_valid(pred: np.ndarray, gt: np.ndarray, valid: Any) -> np.ndarray:
    ok = np.isfinite(gt) & (gt > 0) & np.isfinite(pred)
    if valid is not None:
        ok &= np.broadcast_to(_np(valid, bool), ok.shape)
    return ok


def align_scale(pred: Any, gt: Any, valid: Any = None, method: str = "median") -> float:
    """Scale s making ``s * pred`` match ``gt`` (H, W) on valid pixels.

    ``"median"``: median(gt) / median(pred); ``"lstsq"``: sum(pred gt) / sum(pred^2);
    ``"none"``: 1. NaN if no pixel is valid.
    """
    p = _np(pred)
    g = _np(gt)
    ok = _depth_valid(p, g, valid)
    if method == "none":
        return 1.0
    if not ok.any():
        return math.nan
    pv, gv = p[ok], g[ok]
    if method == "median":
        mp = float(np.median(pv))
        return float(np.median(gv)) / mp if mp != 0 else math.nan
    if method == "lstsq":
        den = float(np.sum(pv * pv))
        return float(np.sum(pv * gv)) / den if den > 0 else math.nan
    raise InputError(f"align must be 'median', 'lstsq' or 'none', got {method!r}")


def _per_image(fn, pred: Any, gt: Any, valid: Any, align: str) -> float | np.ndarray:
    p = _np(pred)
    g = _np(gt)
    if p.shape != g.shape:
        raise InputError(f"pred and gt must have the same shape, got {p.shape} and {g.shape}")
    if p.ndim == 2:
        ok = _depth_valid(p, g, valid)
        s = align_scale(p, g, ok, align)
        return fn(s * p[ok], g[ok]) if ok.any() and math.isfinite(s) else math.nan
    if p.ndim != 3:
        raise InputError(f"depth must be (H, W) or (N, H, W), got shape {p.shape}")
    v = None if valid is None else np.broadcast_to(_np(valid, bool), p.shape)
    return np.array(
        [_per_image(fn, p[k], g[k], None if v is None else v[k], align) for k in range(p.shape[0])]
    )


def abs_rel(pred: Any, gt: Any, valid: Any = None, align: str = "median") -> float | np.ndarray:
    """Mean absolute relative error ``mean(|s pred - gt| / gt)`` after per-image scale
    alignment (``align``: "median" (default), "lstsq" or "none"; see :func:`align_scale`).

    (H, W) inputs give a float, (N, H, W) inputs an (N,) array (one alignment per image). Pixels
    count where gt is finite and positive, pred finite and ``valid`` (optional mask) holds.
    """
    return _per_image(lambda p, g: float(np.mean(np.abs(p - g) / g)), pred, gt, valid, align)


def delta_125(pred: Any, gt: Any, valid: Any = None, align: str = "median") -> float | np.ndarray:
    """Fraction of pixels with ``max(s pred / gt, gt / (s pred)) < 1.25`` after per-image
    scale alignment (same conventions as :func:`abs_rel`; non-positive predictions fail)."""

    def frac(p: np.ndarray, g: np.ndarray) -> float:
        pos = p > 0
        ratio = np.where(pos, np.maximum(p / g, g / np.where(pos, p, 1.0)), np.inf)
        return float(np.mean(ratio < 1.25))

    return _per_image(frac, pred, gt, valid, align)


# --------------------------------------------------------------------------------------------
# Summary
# --------------------------------------------------------------------------------------------


def auc(errors: Any, threshold: float) -> float:
    """Area under the recall-vs-error curve up to ``threshold``, normalised to [0, 1]:
    ``mean(clip(1 - e / threshold, 0, 1))`` (exact integral of the step curve); NaN errors count
    as failures. NaN for no errors."""
    e = _np(errors).reshape(-1)
    if e.size == 0:
        return math.nan
    e = np.where(np.isfinite(e), e, np.inf)
    return float(np.mean(np.clip(1.0 - e / threshold, 0.0, 1.0)))


def _stats(x: Any) -> dict[str, float | int]:
    a = _np(x).reshape(-1)
    fin = a[np.isfinite(a)]
    return {
        "mean": float(np.mean(fin)) if fin.size else math.nan,
        "median": float(np.median(fin)) if fin.size else math.nan,
        "count": int(a.size),
        "n_nan": int(a.size - fin.size),
    }


def summarize(
    pose_errors: dict[str, Any] | None = None,
    d_reproj: Any = None,
    abs_rel: Any = None,
    delta_125: Any = None,
    thresholds: Iterable[float] = (5.0, 10.0, 20.0),
    name: str | None = None,
) -> dict[str, Any]:
    """Per-sequence summary: mean / median / count / n_nan of every metric given.

    Args:
        pose_errors: output of :func:`relative_pose_errors`; adds ``rotation_deg``,
            ``translation_deg`` and ``pose_max_deg`` (max of both per pair) statistics,
            ``translation_folded_deg`` (min(e, 180 - e), when ``translation_deg`` is signed),
            ``n_pairs``, ``n_skipped``, ``folded`` and ``auc@T`` / ``acc@T`` (fraction with
            max error < T) of the max error for every threshold T (degrees).
        d_reproj: per-pair d_reproj values (pixels).
        abs_rel, delta_125: per-image values.
        name: sequence name stored under ``"name"``.

    Means and medians ignore NaN; ``n_nan`` counts them.
    """
    out: dict[str, Any] = {}
    if name is not None:
        out["name"] = name
    if pose_errors is not None:
        rot = _np(pose_errors["rotation_deg"])
        tra = _np(pose_errors["translation_deg"])
        worst = np.where(np.isfinite(rot) & np.isfinite(tra), np.maximum(rot, tra), np.nan)
        out["rotation_deg"] = _stats(rot)
        out["translation_deg"] = _stats(tra)
        out["pose_max_deg"] = _stats(worst)
        out["n_pairs"] = int(pose_errors["n_pairs"])
        out["n_skipped"] = int(pose_errors["n_skipped"])
        out["folded"] = bool(pose_errors.get("folded", False))
        if not out["folded"]:
            # Both conventions, so a table can say which it shows: the signed error (0-180,
            # a reversed direction is 180) and VGGT-style folded one (0-90, sign-invariant).
            out["translation_folded_deg"] = _stats(np.minimum(tra, 180.0 - tra))
        for th in thresholds:
            out[f"auc@{th:g}"] = auc(worst, th)
            out[f"acc@{th:g}"] = (
                float(np.mean(np.nan_to_num(worst, nan=np.inf) < th)) if worst.size else math.nan
            )
    if d_reproj is not None:
        out["d_reproj"] = _stats(d_reproj)
    if abs_rel is not None:
        out["abs_rel"] = _stats(abs_rel)
    if delta_125 is not None:
        out["delta_125"] = _stats(delta_125)
    return out
